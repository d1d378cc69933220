"""Configuration dataclasses and the command-line flags generated from them (data_tools.config's Range /
check_fields / Literal coercion, app.commands.flags): a range or a choice is written once, in the annotation, and
both ``validate()`` and the flags enforce it; a bad value on the command line is one usage line."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

import pytest

from data_tools.config import Range, check_fields, config_from_dict, config_replace
from data_tools.errors import ConfigError


@dataclass
class Inner:
    size: Annotated[int, Range(1)] = 3
    """Cells (>= 1)."""


@dataclass
class Outer:
    steps: Annotated[int, Range(1)] = 10
    """Steps."""
    rate: Annotated[float, Range(0, 1, open_lo=True)] = 0.5
    """A fraction in (0, 1]."""
    kind: Literal["grid", "image"] = "grid"
    """Input kind."""
    name: str = "x"
    """A free string."""
    flag: bool = False
    """On or off."""
    inner: Inner = field(default_factory=Inner)
    """Nested."""

    def validate(self):
        check_fields(self)
        check_fields(self.inner)
        return self


def test_range_messages_by_hand():
    assert Range(1).problem(1) is None and Range(1).problem(0) == "must be >= 1"
    assert Range(0, open_lo=True).problem(0.0) == "must be > 0"
    assert Range(0, 1, open_lo=True).problem(1.0) is None and Range(0, 1, open_lo=True).problem(0) == "must be in (0, 1]"
    assert Range(None, 2, open_hi=True).problem(2) == "must be < 2"
    assert Range(0).problem(float("nan")) == "must be a finite number"


def test_check_fields_and_literal_coercion():
    check_fields(Outer())
    with pytest.raises(ConfigError, match=r"^steps must be >= 1, got 0$"):
        check_fields(Outer(steps=0))
    with pytest.raises(ConfigError, match="rate must be in"):
        check_fields(Outer(rate=0.0))
    with pytest.raises(ConfigError, match="kind must be one of grid, image, got 'rays'"):
        check_fields(Outer(kind="rays"))
    with pytest.raises(ConfigError, match="cfg.kind: expected one of grid, image, got 'rays'"):
        config_from_dict(Outer, {"kind": "rays"}, "cfg")            # a typo in a file is an error, not a default
    assert config_replace(Outer(), {"inner.size": "7", "kind": "image"}).inner.size == 7


def _parser():
    from app.cli import _Parser
    from app.commands.flags import add_config_flags
    p = _Parser(prog="t")
    add_config_flags(p, Outer, exclude=("name",), aliases={"inner.size": ("--size",)})
    return p


def test_flags_are_typed_checked_and_nested():
    from app.cli import UsageError
    from app.commands.flags import config_overrides
    p = _parser()
    args = p.parse_args(["--steps", "4", "--rate", "1", "--kind", "image", "--flag", "--inner.size", "2"])
    assert config_overrides(args) == {"steps": 4, "rate": 1.0, "kind": "image", "flag": True, "inner.size": 2}
    assert config_overrides(p.parse_args(["--size", "5"])) == {"inner.size": 5}      # an alias of a moved field
    assert config_overrides(p.parse_args([])) == {}                                   # defaults stay the config's
    with pytest.raises(UsageError, match="--name"):
        p.parse_args(["--name", "y"])           # excluded: no such flag


@pytest.mark.parametrize("argv,msg", [(["--steps", "0"], "argument --steps: must be >= 1, got 0"),
                                      (["--steps", "two"], "expected a whole number, got 'two'"),
                                      (["--rate", "nan"], "must be a finite number"),
                                      (["--kind", "rays"], "invalid choice: 'rays'"),
                                      (["--inner.size", "-1"], "must be >= 1, got -1")])
def test_bad_flag_values_are_one_usage_line(argv, msg):
    from app.cli import UsageError
    with pytest.raises(UsageError) as e:
        _parser().parse_args(argv)
    assert msg in str(e.value) and "\n" not in str(e.value)


@dataclass
class Ranges:
    span: tuple[float, float] = (0.0, 1.0)
    """A range LO,HI."""
    names: tuple[str, ...] = ("a",)
    """Any number of names."""
    sizes: tuple[int, ...] = (1, 2)
    """Whole numbers."""


def test_tuple_flags_take_comma_lists():
    """A tuple field's flag reads ``LO,HI`` into the field's element types; a wrong count or a bad element is an
    argparse error naming the flag (one usage line), and the parsed value round-trips through config_replace."""
    import argparse

    from app.commands.flags import add_config_flags, config_overrides
    p = argparse.ArgumentParser(exit_on_error=False)
    add_config_flags(p, Ranges)
    args = p.parse_args(["--span", "0.25,0.5", "--names", "x,y,z", "--sizes", "3"])
    assert config_overrides(args) == {"span": (0.25, 0.5), "names": ("x", "y", "z"), "sizes": (3,)}
    assert config_replace(Ranges(), config_overrides(args)) == Ranges((0.25, 0.5), ("x", "y", "z"), (3,))
    for bad in (["--span", "0.25"], ["--span", "0.1,abc"], ["--sizes", "1,2.5"]):
        with pytest.raises(argparse.ArgumentError, match="--span|--sizes"):
            p.parse_args(bad)
