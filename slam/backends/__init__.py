"""Registration backends, one module per backend, named like the backend.

Modules whose name starts with ``_`` are shared helpers, not backends. Nothing is imported
here: :func:`slam.registration.get_backend` imports a backend module when it is first asked
for by name.
"""
