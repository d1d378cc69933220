"""The lab's parameter space: which numbers of a sensor model a fit may move, within which bounds,
on which search coordinate (:class:`ParamSpec`), and reading / writing them in a
:class:`~synth.sensor.config.SensorConfig` (``"effect.param"`` keys)."""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from data_tools.errors import ConfigError

__all__ = ["ParamSpec", "param_specs", "get_params", "set_params", "config_parameters", "start_values"]


def config_parameters(config, effect) -> dict:
    """The ``CONFIG_PARAMETERS`` of ``effect`` that apply to ``config``
    (:class:`synth.sensor.registry.ConfigParameter`)."""
    return {k: x for k, x in effect.CONFIG_PARAMETERS.items() if x.applies is None or x.applies(config)}


@dataclass
class ParamSpec:
    """One fitted parameter and the scale it is searched on."""

    key: str
    """``effect.param``."""
    low: float
    """Lower bound."""
    high: float
    """Upper bound."""
    value: float
    """Starting value (clipped into the bounds)."""
    integer: bool = False
    """The parameter takes integer values (searched linearly, rounded)."""
    scale: str = "linear"
    """Search coordinate t(x): ``linear``; ``log`` (log10 x: positive bounds spanning >= 2
    decades); ``asinh`` (asinh(x / e), e = 1e-2 max(|a|, |b|) over the span (a, b): bounds that
    include 0, so a grid covers 0 and two decades of magnitude on each side, e.g. a noise level of
    1 mm and of 10 cm within bounds [0, 0.1])."""
    span: tuple[float, float] | None = None
    """The effect's FITTABLE bounds when ``low``/``high`` are narrowed to the device's plausible
    ones: the search coordinate and the first sweep's grid are laid out on the span and clipped to
    the bounds, so narrowing a range removes grid values and changes nothing else (a fit whose
    optimum lies inside the plausible range searches as before). None = (low, high)."""

    @property
    def _e(self) -> float:
        a, b = self.span or (self.low, self.high)
        return 1e-2 * max(abs(a), abs(b), 1e-12)

    @property
    def grid_t_bounds(self) -> tuple[float, float]:
        """Search-coordinate bounds the first sweep's grid is laid out on (then clipped to t_bounds)."""
        if self.span is None:
            return self.t_bounds
        a, b = self.span
        return (math.log10(max(a, 1e-300)) if self.scale == "log" else self.to_t(a)), self.to_t(b)

    def to_t(self, x: float) -> float:
        if self.scale == "log":
            return math.log10(max(float(x), self.low))
        if self.scale == "asinh":
            return math.asinh(float(x) / self._e)
        return float(x)

    def from_t(self, t: float) -> float:
        if self.scale == "log":
            x = 10.0 ** t
        elif self.scale == "asinh":
            x = math.sinh(t) * self._e
        else:
            x = float(t)
        x = min(max(x, self.low), self.high)
        return float(round(x)) if self.integer else x

    @property
    def t_bounds(self) -> tuple[float, float]:
        return self.to_t(self.low), self.to_t(self.high)


def _effect(config, name):
    for e in config.effects:
        if e.name == name:
            return e
    raise ConfigError(f"effect {name!r} is not in this sensor model ({', '.join(config.names())})")


def _narrowed(lo: float, hi: float, plausible) -> tuple[float, float]:
    """FITTABLE bounds (lo, hi) intersected with an effect's plausible bounds for the device."""
    if plausible is None:
        return lo, hi
    a, b = max(float(lo), float(plausible[0])), min(float(hi), float(plausible[1]))
    return (a, b) if a < b else (float(lo), float(hi))


def param_specs(config, names: Sequence[str] | None = None, plane: bool = False) -> list[ParamSpec]:
    """Fittable parameters of the enabled effects ``names`` (default all enabled) of ``config``:
    FITTABLE bounds narrowed to what the device can physically have (``Effect.plausible_bounds``)
    and to what ``fit_start`` measured exactly (``Effect.search_bounds``).
    ``plane``: the objective has the noise-curve term of a planar reference, so the effects'
    ``PLANE_ONLY`` parameters are fitted too (e.g. axial noise's incidence term)."""
    enabled = config.names(enabled_only=True)
    names = list(enabled) if names is None else list(names)
    out = []
    for n in names:
        e = _effect(config, n)
        if not e.enabled:
            raise ConfigError(f"effect {n!r} is disabled in this model; enable it to fit it")
        types = getattr(e, "FITTABLE_FOR", {})
        plausible = e.search_bounds(config.preset)
        items = [(k, *_narrowed(lo, hi, plausible.get(k)), getattr(e.params, k)) for k, (lo, hi) in e.FITTABLE.items()
                 if (k not in types or config.preset.type in types[k])
                 and (plane or k not in getattr(e, "PLANE_ONLY", ()))]
        items += [(k, x.low, x.high, x.get(config, e)) for k, x in config_parameters(config, e).items()]
        for k, lo, hi, v in items:
            integer = isinstance(v, (int, np.integer)) and not isinstance(v, bool)
            lo, hi = float(lo), float(hi)
            span = tuple(float(x) for x in e.FITTABLE[k]) if k in e.FITTABLE else (lo, hi)
            if integer:
                scale = "linear"
            elif span[0] > 0 and span[1] / span[0] >= 100:
                scale = "log"
            elif span[0] <= 0 <= span[1] and span[1] > span[0]:
                scale = "asinh"
            else:
                scale = "linear"
            out.append(ParamSpec(f"{n}.{k}", lo, hi, min(max(float(v), lo), hi), integer, scale,
                                 span if span != (lo, hi) else None))
    return out


def get_params(config, specs: Sequence[ParamSpec]) -> dict[str, float]:
    """Current values of ``specs`` in ``config``."""
    out = {}
    for s in specs:
        en, pn = s.key.split(".", 1)
        e = _effect(config, en)
        extra = config_parameters(config, e).get(pn)
        out[s.key] = float(extra.get(config, e)) if extra else float(getattr(e.params, pn))
    return out


def set_params(config, values: dict[str, float]):
    """A copy of ``config`` with ``{"effect.param": value}`` set (FITTABLE or config parameters).

    Only the effects (and, for the config parameters that need it, the preset) change: every
    other field of ``config`` (e.g. ``motion``) is carried over with ``dataclasses.replace``."""
    plain, extra = {}, []
    for k, v in values.items():
        if "." not in k:
            raise ConfigError(f"parameter key {k!r} must be 'effect.param'")
        en, pn = k.split(".", 1)
        e = _effect(config, en)
        x = config_parameters(config, e).get(pn)
        if x is not None:
            extra.append((en, x, v))
        else:
            cur = getattr(e.params, pn, None)
            plain[k] = int(round(v)) if isinstance(cur, int) and not isinstance(cur, bool) else v
    # with_params validates names and bounds; only its effects are taken
    effects = config.with_params(plain).effects if plain else list(config.effects)
    cfg = dataclasses.replace(config, effects=effects)
    for en, x, v in extra:
        cfg = x.set(cfg, _effect(cfg, en), v)
    return cfg


def start_values(measured, config, names: Sequence[str], frames: Sequence[int]) -> dict[str, float]:
    """Data-driven starting values (each effect's ``fit_start``) of the effects ``names`` in
    ``config``, restricted to the parameters that are fitted for this sensor, the effects' data
    files (``Effect.FILE_PARAMS``: the path of a map estimated from the data, a str) and the
    choices made from the data (``Effect.START_ONLY_PARAMS``, e.g. a window shape). Effects are
    started in :attr:`~synth.sensor.registry.Effect.START_PRIORITY` order; the starts of an effect
    with a negative priority (the lens warp) are applied to the config the later ones see."""
    out = {}
    cfg = config
    for n in sorted(names, key=lambda n: _effect(config, n).START_PRIORITY):    # stable: the given order otherwise
        start = _effect(cfg, n).fit_start(measured, cfg, frames)
        if start:
            known = {s.key for s in param_specs(cfg, [n])}
            e = _effect(cfg, n)
            known |= {f"{n}.{k}" for k in (*e.FILE_PARAMS, *e.START_ONLY_PARAMS)}   # a learned map, a shape
            new = {k: v for k, v in start.items() if k in known}
            out.update(new)
            numeric = {k: v for k, v in new.items() if not isinstance(v, str)}
            if numeric and _effect(cfg, n).START_PRIORITY < 0:      # later starts see this one
                cfg = set_params(cfg, numeric)
    return out
