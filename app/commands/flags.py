"""Command-line flags generated from configuration dataclasses: one flag per field, so that a new option is on the
command line without being written twice (``slam run`` / ``batch``, ``demo``, ``neural train``, ``neural
refine-*``, ``neural train-topview``, ``recog train``).

Per field: the flag ``--PREFIX.NAME`` (dashes for underscores; the underscore spelling accepted too), the field's
docstring and default as its help (a shared flag of :data:`app.commands.SHARED_FLAGS` keeps its standard help
first), a nested dataclass field's fields as ``--NAME.FIELD``. Typed flags convert the value to the field's type,
offer a ``Literal``'s choices and check the :class:`data_tools.config.Range` of its annotation, so a bad value is a
one-line usage error (``argument --steps: must be >= 1, got 0``) before any work; a tuple field takes a comma
list (``--ambient 0.1,0.2``); the whole configuration is then
checked by its ``validate()``. Values land in ``args`` as ``cfg:DOTTED.NAME`` (:func:`config_overrides`).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import typing
from typing import Any

__all__ = ["add_config_flags", "config_overrides", "list_parser", "number_parser", "type_name"]


def list_parser(tp):
    """argparse ``type`` of a tuple field: ``"a,b,c"`` -> a tuple of the element type (``tuple[float, float]``: exactly
    two numbers; ``tuple[str, ...]``: any count); a bad element or count raises ArgumentTypeError (one usage line)."""
    args = typing.get_args(tp)
    elems = (args[0],) if len(args) == 2 and args[1] is Ellipsis else args

    def parse(text: str):
        items = [t.strip() for t in text.split(",")] if text.strip() else []
        if elems and not (len(args) == 2 and args[1] is Ellipsis) and len(items) != len(elems):
            raise argparse.ArgumentTypeError(f"expected {len(elems)} comma-separated values, got {text!r}")
        out = []
        for i, item in enumerate(items):
            et = str if not elems else elems[0] if len(elems) == 1 else elems[i]
            out.append(number_parser(et, None)(item) if et in (int, float) else item)
        return tuple(out)
    parse.__name__ = "list"
    return parse


def type_name(tp) -> str:
    """The metavar of a field type: INT, FLOAT, BOOL, STR, LIST (a tuple), VALUE (anything else)."""
    if typing.get_origin(tp) is tuple or tp is tuple:
        return "LIST"
    return {int: "INT", float: "FLOAT", bool: "BOOL", str: "STR"}.get(tp, "VALUE")


def number_parser(tp, rng, choices=None):
    """argparse ``type`` of a field or a flag: the text converted to ``tp`` (int, float, str) and checked
    against the ``Range`` ``rng`` (its wording: ``must be >= 1, got 0``) and the ``choices``; a bad value
    raises ArgumentTypeError, which ``app.cli`` turns into one line naming the flag. The one number parser
    of the command line (``app.commands.ranged`` builds on it)."""
    def parse(text: str):
        try:
            v = tp(text)
        except ValueError:
            what = {int: "a whole number", float: "a number"}.get(tp, tp.__name__)
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if tp is float and not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        if rng is not None and (msg := rng.problem(v)) is not None:
            raise argparse.ArgumentTypeError(f"{msg}, got {text}")
        return v
    parse.__name__ = type_name(tp).lower() if choices is None else "choice"
    return parse


def add_config_flags(p, cls, prefix: str = "", *, exclude: tuple = (), aliases: dict | None = None,
                     typed: bool = True, nested: bool = True, underscore_alias: bool = True,
                     defaults: Any = None, flag_prefix: str | None = None) -> None:
    """Add one flag per field of dataclass ``cls`` to parser or group ``p`` (see the module docstring).

    ``prefix``: of the flags and of their ``cfg:`` destinations (``"tsdf."``); ``exclude``: field names (or full
    dotted names, ``"model.view"``) without a flag; ``aliases``: full dotted name -> extra flag names (a
    field that had a flag of its own before it moved into a nested configuration keeps it); ``typed``: convert and
    check values here (False: the raw text, for a caller that parses it itself - ``slam run``); ``nested``: flags
    for the fields of nested dataclasses (False: skipped); ``underscore_alias``: also accept ``--field_name``;
    ``defaults``: the instance whose values the help shows (default ``cls()``); ``flag_prefix``: the flags'
    spelling of ``prefix`` where it differs (``"loop-closure."`` for the destinations ``loop_closure.*``)."""
    from app.commands import SHARED_FLAGS
    from data_tools.config import field_choices, field_docs, field_range
    docs, hints, inst = field_docs(cls), typing.get_type_hints(cls), defaults if defaults is not None else cls()
    aliases = aliases or {}
    flag_prefix = prefix if flag_prefix is None else flag_prefix
    for f in dataclasses.fields(cls):
        name, tp = f"{prefix}{f.name}", hints[f.name]
        if f.name in exclude or name in exclude or tp is typing.Any:
            continue
        if dataclasses.is_dataclass(tp):
            if nested:
                add_config_flags(p, tp, f"{name}.", exclude=exclude, aliases=aliases, typed=typed,
                                 underscore_alias=underscore_alias, defaults=getattr(inst, f.name),
                                 flag_prefix=f"{flag_prefix}{f.name.replace('_', '-')}.")
            continue
        default = getattr(inst, f.name)
        shown = ",".join(str(x) for x in default) if isinstance(default, tuple) else default
        if typed and default == "":
            shown = "''"
        help_text = f"{docs.get(f.name, '')} (default: {shown})".strip()
        flag = f"--{flag_prefix}{f.name.replace('_', '-')}"
        if flag in SHARED_FLAGS:
            help_text = f"{SHARED_FLAGS[flag]}: {help_text}"
        names = [flag] + ([f"--{name}"] if underscore_alias and "_" in f.name else []) + list(aliases.get(name, ()))
        kw: dict = {"dest": f"cfg:{name}", "default": argparse.SUPPRESS, "help": help_text.replace("%", "%%")}
        choices = field_choices(tp)
        if not typed:
            kw["metavar"] = type_name(tp)
        elif tp is bool:
            kw["action"] = argparse.BooleanOptionalAction
        elif choices is not None:
            kw["choices"] = choices
        elif tp in (int, float, str):
            kw.update(type=number_parser(tp, field_range(cls, f.name)), metavar=type_name(tp))
        elif typing.get_origin(tp) is tuple:
            kw.update(type=list_parser(tp), metavar=type_name(tp))
        else:
            kw["metavar"] = type_name(tp)
        p.add_argument(*names, **kw)


def config_overrides(args) -> dict:
    """``{"dotted.name": value}`` of the generated flags given on the command line."""
    return {k[4:]: v for k, v in vars(args).items() if k.startswith("cfg:")}
