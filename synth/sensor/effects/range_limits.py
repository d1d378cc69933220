"""Device post-processing: the reported working range."""
from __future__ import annotations

from dataclasses import dataclass

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
    stage = STAGE_POST

    def apply(self, state, draw) -> None:
        lo = self.params.min_depth_m or state.preset.min_depth_m
        hi = self.params.max_depth_m or state.preset.max_depth_m
        z = state.depth
        state.invalidate((z < lo) | (z > hi), self.name)
        state.log[self.name].update({"min_depth_m": lo, "max_depth_m": hi})
