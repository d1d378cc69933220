"""Guards that keep a fitted model from throwing the measurement away (issue 43, item 1).

A sensor model can explain a large gap by invalidating pixels: a refit that pulls
``range_limits.max_depth_m`` below most measured depths "wins" by comparing almost nothing, and
every candidate effect then looks inert. Three rules:

* :func:`bound_depth_limits`: a parameter that cuts the depth range (``Effect.DEPTH_LIMIT_PARAMS``)
  is searched only where it keeps the measured valid depths: a minimum at most their 0.5th
  percentile, a maximum at least their 99.5th (0 = the device's, kept when the device's own limit
  obeys the same rule).
* :func:`lost_fraction`: the share of measured-valid pixels (with reference geometry) that a
  model's simulation makes invalid (counting only pixels whose ideal depth lies within the measured
  range: beyond it a pixel is valid only through an effect that moved it, the effect to be diagnosed);
  :func:`synth.lab.diagnose.diagnose` rejects a refit that loses
  more of them than the model as given (the given model's losses stand for what its effects
  explain - an approximation: no per-effect attribution of each lost pixel).
* :func:`cut_reason`: the sentence an error gives when the base model leaves nothing to diagnose.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

__all__ = ["MeasuredRange", "measured_range", "bound_depth_limits", "lost_fraction", "lost_fractions", "cut_reason",
           "LOST_TOLERANCE"]

LOST_TOLERANCE = 0.02
"""A refit may lose at most this share of the measured-valid pixels more than the given model."""


@dataclasses.dataclass(frozen=True)
class MeasuredRange:
    """Measured valid depths of some frames, metres."""

    low: float
    """0.5th percentile."""
    high: float
    """99.5th percentile."""
    count: int
    """Valid pixels they were taken from."""


def _valid(measured, k: int) -> np.ndarray:
    m = measured.measured_depth(k)
    ok = m > 0
    mask = measured.mask(k) if getattr(measured, "has_masks", False) else None
    return ok & mask if mask is not None else ok


def measured_range(measured, frames: Sequence[int]) -> MeasuredRange | None:
    """0.5th / 99.5th percentile of the measured valid depths of kept frames ``frames`` (masked
    pixels only when the sequence has masks); None below 100 valid pixels."""
    vals = [measured.measured_depth(k)[_valid(measured, k)] for k in frames]
    v = np.concatenate(vals) if vals else np.zeros(0)
    if v.size < 100:
        return None
    lo, hi = np.percentile(v, [0.5, 99.5])
    return MeasuredRange(float(lo), float(hi), int(v.size))


def bound_depth_limits(specs, config, rng: MeasuredRange | None):
    """``specs`` (:class:`~synth.lab.params.ParamSpec`) with every depth-limit parameter's bounds
    narrowed to keep ``rng``: a ``max`` parameter gets ``low >= rng.high``, a ``min`` one
    ``high <= rng.low``. A value 0 (= the device's limit) starts from the device's limit. Returns
    (specs, changed) where ``changed`` says whether a starting value moved."""
    if rng is None:
        return list(specs), False
    from synth.lab.params import _effect
    out, changed = [], False
    for s in specs:
        en, pn = s.key.split(".", 1)
        side = type(_effect(config, en)).DEPTH_LIMIT_PARAMS.get(pn)
        if side is None:
            out.append(s)
            continue
        dev = float(getattr(config.preset, pn, 0.0) or 0.0)
        v = s.value if s.value > 0 else dev
        if side == "max" and s.high >= rng.high:
            low = max(s.low, rng.high)
            ns = dataclasses.replace(s, low=low, value=min(max(v, low), s.high))
        elif side == "min" and s.low <= rng.low:
            high = min(s.high, rng.low)
            ns = dataclasses.replace(s, high=high, value=min(max(v, s.low), high))
        else:
            ns = s
        if ns.value != s.value and not (s.value == 0 and ns.value == dev):
            changed = True
        out.append(ns)
    return out, changed


def lost_fractions(measured, sims: Sequence[np.ndarray], frames: Sequence[int],
                   seen: MeasuredRange | None) -> tuple[float, float]:
    """(:func:`lost_fraction` without ``seen``, with ``seen``) in one pass over the frames (one
    render and one mask per frame): every lost pixel, and those whose ideal depth lies within the
    measured range ``seen`` (None: the same as the first)."""
    lost = lost_seen = tot = 0
    for d, k in zip(sims, frames):
        z = measured.render(k).depth
        ok = _valid(measured, k) & (z > 0)
        tot += int(ok.sum())
        cut = ok & ~(d > 0)
        lost += int(cut.sum())
        lost_seen += int((cut & (z >= seen.low) & (z <= seen.high)).sum()) if seen is not None else int(cut.sum())
    return (lost / tot, lost_seen / tot) if tot else (0.0, 0.0)


def lost_fraction(measured, sims: Sequence[np.ndarray], frames: Sequence[int],
                  seen: MeasuredRange | None = None) -> float:
    """Share of the measured-valid pixels with reference geometry (ideal depth > 0) that the
    simulated depths ``sims`` of kept frames ``frames`` leave invalid.

    With ``seen`` (the measured valid depths' range, :func:`measured_range`), a lost pixel counts
    only when its IDEAL depth lies within that range: a measured-valid pixel whose true surface lies
    beyond every depth the sensor measured (a background behind a fattened edge, a flying pixel)
    is valid only because some effect moved it into the range; a model without that effect that
    cuts it (a range limit at the measured maximum) throws no measurement away, the missing effect
    does (mystery edge_fattening seed 40: such pixels were 2.8 % of the measured ones, and a
    refit that set the range limit was rejected for them). The denominator stays every
    measured-valid pixel with geometry. (Both counts at once: :func:`lost_fractions`.)"""
    return lost_fractions(measured, sims, frames, seen)[1]


def cut_reason(config, lost: float, refit: bool = True) -> str:
    """Why a base model leaves nothing to diagnose: the share of measured pixels it cuts and the
    depth-limit parameters it has (e.g. ``max_depth_m 0.87 m``)."""
    lims = []
    for e in config.effects:
        for pn in type(e).DEPTH_LIMIT_PARAMS:
            v = float(getattr(e.params, pn))
            if v > 0:        # 0 = the device's limit, which is not the model's doing
                lims.append(f"{pn} {v:.2f} m")
    return f"the {'refit ' if refit else ''}base model cuts {100 * lost:.0f} % of the measured pixels" + (
        f": {', '.join(lims)}" if lims else "")


def bound_for_objective(objective, config, specs):
    """:func:`bound_depth_limits` with the measured range of the objective's frames (cached on the
    objective; an objective without ``measured``/``frames`` leaves ``specs`` as they are)."""
    measured, frames = getattr(objective, "measured", None), getattr(objective, "frames", None)
    if measured is None or frames is None or not any(
            type(e).DEPTH_LIMIT_PARAMS for e in config.effects):
        return list(specs), False
    rng = getattr(objective, "_measured_range", False)
    if rng is False:
        rng = measured_range(measured, frames)
        try:
            objective._measured_range = rng
        except AttributeError:
            pass
    return bound_depth_limits(specs, config, rng)
