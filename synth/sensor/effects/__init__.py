"""Sensor effects, one module per effect (discovered by synth.sensor.registry, lazily).

Modules whose name starts with ``_`` are helpers, not effects.
"""
