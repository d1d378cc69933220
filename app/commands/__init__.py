"""Command groups of the ``realgap`` CLI, one module per group (discovered by ``app.cli``).

A group module defines ``NAME``, ``HELP`` and ``register(parser)``; inside ``register`` use
:func:`add_group` to create sub-subcommands. Commands stay thin: parse -> call a library
function -> save the result.

One dialect: the same idea has the same flag in every command, added by :func:`add_shared`
with the help text of :data:`SHARED_FLAGS` (``tests/test_cli_dialect.py`` walks the parser and
checks it): ``--out``, ``--overwrite``, ``--max-frames``, ``--seed``, ``--workers``,
``--no-progress``, ``--json``.
"""
from __future__ import annotations

import argparse

SHARED_FLAGS: dict[str, str] = {
    "--out": "output",
    "--overwrite": "replace a finished result already at --out (without it such an output is an error)",
    "--max-frames": "use at most N frames of the sequence",
    "--seed": "random seed: the same seed gives the same output",
    "--workers": "parallel worker processes",
    "--no-progress": "no progress display on stderr (also: REALGAP_NO_PROGRESS=1)",
    "--json": "print the result as JSON on stdout instead of text",
}
"""The shared flags and the start of their help text (each command appends its specifics)."""

RESUMES = "re-run the same command to continue: finished steps are kept and skipped"
"""``on_interrupt`` note of a command that continues an interrupted run (see :mod:`app.cli`)."""

FORBIDDEN_SYNONYMS = ("--out-dir", "--output", "--force", "--jobs", "--num-workers", "--quiet", "--random-seed",
                      "--n-frames", "--num-frames", "--limit-frames")
"""Other names for the shared ideas, which no command may use."""


def add_group(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """Sub-subcommand container for a group; ``realgap GROUP`` alone prints the group help."""
    parser.set_defaults(func=None, _group_parser=parser)
    return parser.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")


def add_shared(p: argparse.ArgumentParser, flag: str, detail: str = "", **kwargs) -> argparse.Action:
    """Add the shared ``flag`` (one of :data:`SHARED_FLAGS`) with its standard help + ``detail``."""
    base = SHARED_FLAGS[flag]
    help_text = f"{base}: {detail}" if detail else base
    if flag in ("--overwrite", "--no-progress", "--json"):
        kwargs.setdefault("action", "store_true")
    if flag == "--max-frames":
        kwargs.setdefault("type", _positive_int("--max-frames"))
        kwargs.setdefault("metavar", "N")
    if flag == "--workers":
        kwargs.setdefault("type", _positive_int("--workers"))
        kwargs.setdefault("metavar", "N")
    if flag == "--seed":
        kwargs.setdefault("type", int)
    return p.add_argument(flag, help=help_text.replace("%", "%%"), **kwargs)


def _positive_int(flag: str):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if v < 1:
            raise argparse.ArgumentTypeError(f"must be at least 1, got {v}")
        return v
    parse.__name__ = flag
    return parse
