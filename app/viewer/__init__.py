"""The PyVista desktop viewer of ``realgap view``: :mod:`app.viewer.data` loads what is shown
(no plotting library), :mod:`app.viewer.window` draws it."""
