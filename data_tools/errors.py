"""The single base exception of realgap.

Every error a user can cause (bad file, bad option, bad data) is raised as a
:class:`RealgapError` (or subclass). The CLI turns it into one line on stderr and exit
code 1; anything else is a bug and keeps its traceback.
"""
from __future__ import annotations

import os


class RealgapError(Exception):
    """Base class of all user-facing realgap errors (one-line message, exit code 1)."""


class FormatError(RealgapError):
    """A file exists but its content is wrong; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class ConfigError(RealgapError):
    """An option or configuration value is invalid (negative baseline, unknown name, ...)."""


class RealgapWarning(UserWarning):
    """A realgap warning: something the user should know that is not an error (a reader dropped a
    duplicate, an alignment is ill-conditioned). Shown as one ``realgap: warning: ...`` line."""


def warn(message: str) -> None:
    """The one way realgap warns: a :class:`RealgapWarning` shown as one ``realgap: warning:`` line
    (never Python's ``path:line: UserWarning`` form, also not in worker processes, where the CLI's
    handler is not installed), once per message under Python's default filter."""
    import warnings
    warnings.warn(" ".join(str(message).split()), RealgapWarning, stacklevel=3)


def _format(message, category, filename, lineno, line=None) -> str:
    if isinstance(category, type) and issubclass(category, RealgapWarning):
        return f"realgap: warning: {message}\n"
    return _python_format(message, category, filename, lineno, line)


def _install_format() -> None:
    """Python's warning display shows a RealgapWarning as one line, in every process that imports realgap."""
    import warnings
    global _python_format
    if getattr(warnings.formatwarning, "__module__", "") != __name__:
        _python_format = warnings.formatwarning
        warnings.formatwarning = _format


_python_format = None
_install_format()
