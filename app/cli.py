"""The ``realgap`` command line.

Each module in :mod:`app.commands` is a command group: it defines ``NAME`` (the subcommand),
``HELP`` (one line) and ``register(parser)`` which adds its own sub-subcommands and sets
``func`` on them. Groups are discovered by name, so adding a group is one new file.

Every :class:`data_tools.errors.RealgapError` becomes one line on stderr and exit code 1; so does
an operating-system error on a file (``realgap: error: PATH: No such file or directory``) and any
usage error argparse finds (unknown option, bad or out-of-range value: one line naming the flag,
not a usage dump) and any other, unexpected exception (one line plus "re-run with --debug for the traceback"; ``realgap
--debug ...`` or ``REALGAP_DEBUG=1`` shows the traceback). Every
Python warning is one ``realgap: warning:`` line; Ctrl-C exits with 130, leaves finished
outputs in place and says what a re-run does: a command that continues sets
``on_interrupt`` (``parser.set_defaults(on_interrupt=RESUMES)``), any other says it starts again.
``--no-progress`` on any command switches every progress display off. Before any work every command
checks that no output lands in an input and applies the one re-run rule (a finished output needs
``--overwrite``; an unfinished one is continued: :data:`app.commands.RERUN`). A closed stdout
(``realgap sensor effects | head``) ends quietly with :data:`EXIT_BROKEN_PIPE`.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import re
import sys
import warnings

from data_tools.errors import RealgapError


def _command_modules():
    import app.commands as pkg
    mods = []
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"app.commands.{info.name}")
        if hasattr(mod, "register") and hasattr(mod, "NAME"):
            mods.append(mod)
    return mods


EXIT_BROKEN_PIPE = 141
"""Exit code when stdout's reader closed the pipe (128 + SIGPIPE, as a Unix tool killed by it)."""


class UsageError(Exception):
    """A command line argparse refused (unknown option, bad value, missing argument)."""


class _Parser(argparse.ArgumentParser):
    """argparse with the realgap dialect: a usage error is one line and exit code 1, like every
    other error (not argparse's exit 2 and usage dump), and a value that starts with ``-`` and is
    made of numbers (``--bbox -50,-50,100,100``, ``--pose "-1 0 2 ..."``) is a value, not an option."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-[\d.,eE+\- ]+$")

    def error(self, message: str):
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="realgap",
        description="Bridge the realism gap between synthetic and real RGB-D data: simulate depth "
                    "sensors, compare them with measurements, register and evaluate RGB-D sequences.")
    parser.add_argument("--version", action="version", version=f"realgap {_version()}")
    parser.add_argument("--debug", action="store_true",
                        help="show the Python traceback of an unexpected error (also: REALGAP_DEBUG=1)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        mod.register(p)
    _declare_io(parser)
    return parser


def _declare_io(parser: argparse.ArgumentParser) -> None:
    """Give every command its inputs and outputs (checked in :func:`main` before any work)."""
    from app.commands import io_arguments
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        inputs, outputs = io_arguments(parser)
        if outputs:
            parser.set_defaults(_io=(inputs, outputs))
    for a in subs:
        for sp in a.choices.values():
            _declare_io(sp)


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("realgap")
    except Exception:
        return "unknown"


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Library warnings (a reader dropped duplicates, an alignment is ill-conditioned) as one line."""
    print(f"realgap: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as e:
        print(f"realgap: error: {_one_line(str(e))}", file=sys.stderr)
        return 1
    func = getattr(args, "func", None)
    if func is None:
        # a group without its subcommand: print that group's help
        (getattr(args, "_group_parser", None) or parser).print_help()
        return 1 if args.command else 0
    from data_tools.progress import set_progress_enabled
    from data_tools.results import running_command
    set_progress_enabled(not getattr(args, "no_progress", False))
    try:
        with warnings.catch_warnings(), running_command(sys.argv[1:] if argv is None else argv):
            warnings.simplefilter("default")
            warnings.showwarning = _one_line_warning
            from app.commands import check_io, check_rerun_args
            check_io(args)
            check_rerun_args(args)
            rc = func(args)
            sys.stdout.flush()
    except BrokenPipeError:
        # the reader of our stdout went away (``realgap sensor effects | head``): quiet, like any Unix tool
        import io
        import os
        try:                                 # the interpreter's final flush must not raise again
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, io.UnsupportedOperation):     # no real stdout (captured): nothing to do
            pass
        return EXIT_BROKEN_PIPE
    except RealgapError as e:
        print(f"realgap: error: {_one_line(str(e))}", file=sys.stderr)
        return 1
    except OSError as e:
        if _debug(args):
            raise
        import errno
        where = f"{e.filename}: " if e.filename else ""
        hint = (" (could not be written; an unfinished output keeps its incomplete marker: free space and re-run)"
                if e.errno in (errno.ENOSPC, errno.EDQUOT) else "")
        print(f"realgap: error: {where}{_one_line(e.strerror or str(e))}{hint}", file=sys.stderr)
        return 1
    except Exception as e:
        if _debug(args):
            raise
        print(f"realgap: error: unexpected {type(e).__name__}: {_one_line(str(e))} (a bug: re-run with --debug for "
              f"the traceback)", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        note = getattr(args, "on_interrupt", None) or "files already written are kept; re-running starts again"
        print(f"realgap: interrupted ({note})", file=sys.stderr)
        return 130
    finally:
        set_progress_enabled(True)
    return int(rc or 0)


def _debug(args) -> bool:
    import os
    return bool(getattr(args, "debug", False)) or os.environ.get("REALGAP_DEBUG", "") not in ("", "0")


def _one_line(text: str) -> str:
    return " ".join(text.split()) or "(no message)"


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
