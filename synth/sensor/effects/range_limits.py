"""Device post-processing: the reported working range."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_POST, Effect, Signature, param, register_effect


@dataclass
class RangeLimitsParams:
    min_depth_m: float = param(0.0, "m")
    """Nearest reported depth, metres (0 = the preset's)."""
    max_depth_m: float = param(0.0, "m")
    """Farthest reported depth, metres (0 = the preset's)."""


@register_effect
class RangeLimits(Effect):
    """Pixels outside [min_depth_m, max_depth_m] become holes.

    Device: the firmware reports depth only inside its working range (for structured light
    the disparity search range is bounded by it too: nearer surfaces cannot be matched). The
    same effect serves the physical pipeline and the direct model.
    """

    name = "range_limits"
    SIGNATURE = Signature(
        "holes beyond the working range",
        "Everything nearer than the minimum or farther than the maximum range is invalid.",
        panels=(("distance", "invalid_fraction"),))
    Params = RangeLimitsParams
    FITTABLE = {"min_depth_m": (0.0, 5.0), "max_depth_m": (0.0, 50.0)}
    DEPTH_LIMIT_PARAMS = {"min_depth_m": "min", "max_depth_m": "max"}

    @classmethod
    def plausible_bounds(cls, preset) -> dict[str, tuple[float, float]]:
        """At most 1.5 x the device's own limits (0 keeps the device's value): the near limit is
        set by the disparity search range / the projector's dot overlap, the far one by the
        signal, and both are in the data sheet; a fit that wants a near limit of several metres
        is explaining holes another effect makes (incidence, reflectance)."""
        return {"min_depth_m": (0.0, 1.5 * float(preset.min_depth_m)),
                "max_depth_m": (0.0, 1.5 * float(preset.max_depth_m))}
    stage = STAGE_POST

    def apply(self, state, draw) -> None:
        lo = self.params.min_depth_m or state.preset.min_depth_m
        hi = self.params.max_depth_m or state.preset.max_depth_m
        z = state.depth
        state.invalidate((z < lo) | (z > hi), self.name)
        state.log[self.name].update({"min_depth_m": lo, "max_depth_m": hi})

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """Each limit where the data shows it: the farthest (nearest) measured depth, its 99.9th
        (0.1th) percentile, is the maximum (minimum) range when the ideal geometry extends > 2 %
        beyond it over >= 200 pixels of which >= 90 % are holes; a limit the data does not reach
        is left to the search (and to the preset)."""
        from synth.sensor.effects._common import measured_samples
        meas, ideal, hole = [], [], []
        rng = np.random.default_rng(0)
        for _, m, r, ok in measured_samples(measured):
            idx = np.flatnonzero(ok)
            if idx.size > 50000:
                idx = rng.choice(idx, 50000, replace=False)
            mm, zz = m.ravel()[idx], r.depth.ravel()[idx]
            meas.append(mm[mm > 0])
            ideal.append(zz)
            hole.append(mm <= 0)
        if not meas or sum(len(x) for x in meas) < 1000:
            return {}
        mv, z, h = np.concatenate(meas), np.concatenate(ideal), np.concatenate(hole)
        lo, hi = np.percentile(mv, [0.1, 99.9])
        out = {}
        far = z > hi * 1.02
        if far.sum() >= 200 and h[far].mean() >= 0.9:
            out[f"{cls.name}.max_depth_m"] = float(np.clip(hi, *cls.FITTABLE["max_depth_m"]))
        near = z < lo * 0.98
        if near.sum() >= 200 and h[near].mean() >= 0.9:
            out[f"{cls.name}.min_depth_m"] = float(np.clip(lo, *cls.FITTABLE["min_depth_m"]))
        return out
