"""Typed dataclass configurations <-> JSON data, shared by every package (slam, synth, app).

:func:`config_to_dict` turns a (nested) dataclass into plain JSON data; :func:`config_from_dict`
builds one back, converting each value to its field's annotated type and raising
:class:`~data_tools.errors.ConfigError` that names the key for unknown keys and wrong types
(then it calls the object's ``validate()`` when it has one); :func:`config_replace` applies
``{"a.b": value}`` overrides; :func:`config_from_options` applies ``KEY=VALUE`` command-line options.
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import textwrap
import types
import typing
from typing import Any

import numpy as np

from data_tools.errors import ConfigError

__all__ = ["config_to_dict", "config_from_dict", "config_replace", "config_from_options", "Range", "check_fields",
           "field_range", "field_choices"]


@dataclasses.dataclass(frozen=True)
class Range:
    """The allowed values of a number field, declared once in its annotation (``Annotated[int, Range(1)]``) and
    read by :func:`check_fields` (a config's ``validate()``) and by the command-line flags generated from the
    dataclass (``app.commands.flags``): ``lo`` / ``hi`` the bounds (None: unbounded), ``open_lo`` / ``open_hi``
    whether a bound itself is excluded. Every checked number must also be finite."""

    lo: float | None = None
    hi: float | None = None
    open_lo: bool = False
    open_hi: bool = False

    def problem(self, v) -> str | None:
        """None when ``v`` is allowed, else what it must be (``must be >= 1``)."""
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not np.isfinite(v):
            return "must be a finite number"
        low_ok = self.lo is None or (v > self.lo if self.open_lo else v >= self.lo)
        high_ok = self.hi is None or (v < self.hi if self.open_hi else v <= self.hi)
        if low_ok and high_ok:
            return None
        if self.hi is None:
            return f"must be {'>' if self.open_lo else '>='} {self.lo:g}"
        if self.lo is None:
            return f"must be {'<' if self.open_hi else '<='} {self.hi:g}"
        return (f"must be in {'(' if self.open_lo else '['}{self.lo:g}, {self.hi:g}{')' if self.open_hi else ']'}")


def field_range(cls: type, name: str) -> Range | None:
    """The :class:`Range` annotated on field ``name`` of dataclass ``cls``, or None."""
    tp = typing.get_type_hints(cls, include_extras=True)[name]
    if typing.get_origin(tp) is typing.Annotated:
        return next((m for m in tp.__metadata__ if isinstance(m, Range)), None)
    return None


def field_choices(tp: Any) -> tuple | None:
    """The allowed values of a ``Literal[...]`` annotation (None for any other type)."""
    if typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    return typing.get_args(tp) if typing.get_origin(tp) is typing.Literal else None


def check_fields(obj: Any) -> None:
    """Check every field of dataclass ``obj`` against its annotation: a :class:`Range` bound, a ``Literal`` choice;
    raises :class:`ConfigError` naming the first field that is not allowed (``steps must be >= 1, got 0``). Nested
    dataclasses are checked by their own ``validate()``."""
    hints = typing.get_type_hints(type(obj), include_extras=True)
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        choices = field_choices(hints[f.name])
        if choices is not None and v not in choices:
            raise ConfigError(f"{f.name} must be one of {', '.join(map(str, choices))}, got {v!r}")
        rng = field_range(type(obj), f.name)
        if rng is not None and (msg := rng.problem(v)) is not None:
            raise ConfigError(f"{f.name} {msg}, got {v!r}")


def config_to_dict(cfg: Any) -> Any:
    """Dataclass (possibly nested) -> plain JSON data (tuples become lists)."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: config_to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [config_to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: config_to_dict(v) for k, v in cfg.items()}
    if isinstance(cfg, np.generic):
        return cfg.item()
    return cfg


def _coerce(value: Any, tp: Any, where: str, strict: bool = False) -> Any:
    """Check/convert a JSON value to the annotated type ``tp``. ``strict``: the value must already
    have the JSON type (a file: ``"false"`` where a boolean belongs is an error); otherwise strings
    are converted too (values typed on a command line)."""
    if strict and isinstance(value, str) and tp in (bool, int, float):
        what = {bool: "true/false (a JSON boolean)", int: "an integer (a JSON number)", float: "a number (a JSON number)"}
        raise ConfigError(f"{where}: expected {what[tp]}, got the string {value!r}")
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: expected one of {', '.join(map(str, args))}, got {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        last = None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where, strict)
            except ConfigError as e:
                last = e
        raise last or ConfigError(f"{where}: invalid value {value!r}")
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected an object, got {value!r}")
        return config_from_dict(tp, value, where, strict=strict)
    if origin is tuple or tp is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if not args:
            return tuple(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where, strict) for v in value)
        if len(args) != len(value):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, where, strict) for v, a in zip(value, args))
    if origin is list or tp is list:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        return [_coerce(v, args[0], where, strict) for v in value] if args else list(value)
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected an object, got {value!r}")
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not (isinstance(value, (int, np.integer)) or
                                           (isinstance(value, float) and value.is_integer()) or
                                           (isinstance(value, str) and value.strip().lstrip("-").isdigit())):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return int(value)
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
        if not np.isfinite(v):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return v
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def config_from_dict(cls: type, data: dict, where: str = "config", item: str = "option",
                     strict: bool = False) -> Any:
    """Build dataclass ``cls`` from JSON data; missing keys keep their defaults, unknown keys
    and values of the wrong type raise :class:`ConfigError` naming the key (``item``: what a
    key is called in the message, e.g. "parameter"). ``strict`` (data read from a file): a
    string is never converted to a boolean or a number."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected an object, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown {item}(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}")
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}", strict) for k, v in data.items()}
    obj = cls(**kwargs)
    validate = getattr(obj, "validate", None)
    if callable(validate):
        validate()
    return obj


def config_replace(cfg: Any, dotted: dict[str, Any], where: str = "config") -> Any:
    """A copy of dataclass ``cfg`` with ``{"a.b": value}`` overrides applied (values as JSON
    data or strings, converted to the field types)."""
    data = config_to_dict(cfg)
    for key, value in dotted.items():
        parts = key.split(".")
        node = data
        for p in parts[:-1]:
            if not isinstance(node, dict) or p not in node or not isinstance(node[p], dict):
                raise ConfigError(f"{where}: unknown option {key!r}")
            node = node[p]
        if parts[-1] not in node:
            raise ConfigError(f"{where}: unknown option {key!r}")
        node[parts[-1]] = value
    return config_from_dict(type(cfg), data, where)


def config_from_options(cls: type, items, flag: str, base: dict | None = None) -> Any:
    """Dataclass ``cls`` (defaults) with ``KEY=VALUE`` overrides from a command line option such
    as ``--fit-option`` (values parsed as JSON when they are JSON, else kept as strings, then
    converted to the field's type as a typed command-line value is: ``max_evaluations=abc`` or
    ``=1e400`` is an error naming ``--fit-option max_evaluations``), then ``validate()``d. ``base``
    holds overrides applied first. Errors name ``flag``."""
    known = {f.name for f in dataclasses.fields(cls) if f.init}
    hints = typing.get_type_hints(cls)
    over = dict(base or {})
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"{flag} expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        k = k.strip()
        if k not in known:
            raise ConfigError(f"{flag}: unknown option {k!r}; known: {', '.join(sorted(known))}")
        try:
            value = json.loads(v)
        except json.JSONDecodeError:
            value = v
        over[k] = _coerce(value, hints[k], f"{flag} {k}")
    try:
        obj = dataclasses.replace(cls(), **{k: v for k, v in over.items() if k in known})
        validate = getattr(obj, "validate", None)
        if callable(validate):
            validate()
    except (TypeError, ValueError, OverflowError) as e:
        raise ConfigError(f"{flag}: bad value ({e})") from None
    return obj


def field_docs(cls: type) -> dict[str, str]:
    """Docstrings written under the fields of dataclass ``cls`` (and its bases), by field name."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is object or not dataclasses.is_dataclass(klass):
            continue
        try:
            src = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = ast.parse(src).body[0].body
        for a, b in zip(body, body[1:]):
            if (isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name)
                    and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)
                    and isinstance(b.value.value, str)):
                docs[a.target.id] = " ".join(b.value.value.split())
    return docs
