"""Command groups of the ``realgap`` CLI, one module per group (discovered by ``app.cli``).

A group module defines ``NAME``, ``HELP`` and ``register(parser)``; inside ``register`` use
:func:`add_group` to create sub-subcommands. Commands stay thin: parse -> call a library
function -> save the result.
"""
from __future__ import annotations

import argparse


def add_group(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """Sub-subcommand container for a group; ``realgap GROUP`` alone prints the group help."""
    parser.set_defaults(func=None, _group_parser=parser)
    return parser.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")
