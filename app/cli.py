"""The ``realgap`` command line.

Each module in :mod:`app.commands` is a command group: it defines ``NAME`` (the subcommand),
``HELP`` (one line) and ``register(parser)`` which adds its own sub-subcommands and sets
``func`` on them. Groups are discovered by name, so adding a group is one new file.

Every :class:`data_tools.errors.RealgapError` becomes one line on stderr and exit code 1; so does
an operating-system error on a file (``realgap: error: PATH: No such file or directory``) and any
other, unexpected exception (one line plus "re-run with --debug for the traceback"; ``realgap
--debug ...`` or ``REALGAP_DEBUG=1`` shows the traceback). Usage errors exit 2 (argparse). Every
Python warning is one ``realgap: warning:`` line; Ctrl-C exits with 130, leaves finished
outputs in place and says what a re-run does: a command that continues sets
``on_interrupt`` (``parser.set_defaults(on_interrupt=RESUMES)``), any other says it starts again.
``--no-progress`` on any command switches every progress display off.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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
    return parser


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
    args = parser.parse_args(argv)
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
            rc = func(args)
    except RealgapError as e:
        print(f"realgap: error: {_one_line(str(e))}", file=sys.stderr)
        return 1
    except OSError as e:
        if _debug(args):
            raise
        where = f"{e.filename}: " if e.filename else ""
        print(f"realgap: error: {where}{_one_line(e.strerror or str(e))}", file=sys.stderr)
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
