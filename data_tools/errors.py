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
