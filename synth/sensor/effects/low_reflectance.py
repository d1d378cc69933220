"""Direct model: dark or distant surfaces return too little light."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import (check_draw, cos_incidence, drop_with_probability, sigmoid,
                                          uniform_draw)
from synth.sensor.registry import STAGE_DROPOUT, Effect, Signature, param, register_effect


@dataclass
class LowReflectanceParams:
    signal50: float = param(0.004, "1")
    """Relative returned signal at which half the pixels drop; signal = albedo (1 - specular)
    cos(incidence) / r^2 with r in metres (a white wall facing the sensor at 1 m = 1)."""
    width_decades: float = param(0.25, "decades")
    """Width of the transition in decades of signal (logistic scale)."""


@register_effect
class LowReflectance(Effect):
    """Pixels drop with probability logistic(log10(signal50 / signal) / width).

    Physics: the pattern (or ToF amplitude) returned by a surface scales with its diffuse
    albedo, the cosine of incidence and the inverse squared distance; below the sensor's noise
    floor no match (no phase) is found - black fabric, dark plastics and far surfaces turn into
    holes. Draw: one U(0, 1) per pixel.
    """

    name = "low_reflectance"
    SIGNATURE = Signature(
        "holes where little light returns",
        "The invalid fraction differs by material (dark surfaces) and grows with distance and "
        "obliquity (the returned signal falls with z² and cos θ).",
        panels=(("material", "invalid_fraction"), ("distance", "invalid_fraction"), ("incidence", "invalid_fraction")))
    DRAW_FROM_SHAPE = True
    Params = LowReflectanceParams
    FITTABLE = {"signal50": (1e-6, 1.0), "width_decades": (0.01, 3.0)}
    stage = STAGE_DROPOUT

    def sample(self, rng, state):
        return uniform_draw(rng, state.shape)

    def apply(self, state, draw) -> None:
        u = check_draw(draw, "u", state.shape, self.name)
        v = state.view
        cos_i, r = cos_incidence(v, state.preset.projector_offset_m)
        s = v.albedo * (1 - v.specular) * cos_i / np.maximum(r * r, 1e-9)
        with np.errstate(divide="ignore"):
            x = np.log10(self.params.signal50) - np.log10(np.maximum(s, 1e-12))
        p = sigmoid(x / self.params.width_decades)
        p[~v.hit] = 0
        drop_with_probability(state, p, u, self.name)

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """Measured hole rate on dark (albedo < 0.2) vs brighter materials.

        Signature present: the dark-material rate exceeds the brighter materials' rate and the
        current model's dark-material rate by :data:`ctx.MIN_RATE_EXCESS` and is at least 1.5x the
        brighter materials' rate."""
        ids = ctx.material_ids()
        alb = np.array([ctx.albedo.get(int(i), np.nan) for i in range(int(ids.max()) + 1)])[ids]
        names = {}
        for o in ctx.observations:
            names.update(o.material_names)
        hole = ctx.measured <= 0
        known = np.isfinite(alb)
        if not known.any():
            return ctx.weak("reflectance signature", gain, "no material albedos are known")
        cut = 0.2
        dark = known & (alb < cut)
        bright = known & (alb >= cut)
        if not dark.any():
            return ctx.weak("reflectance signature", gain,
                         f"no material darker than albedo {cut} is in view; bright surfaces lose {ctx.pct(ctx.rate(hole, bright))}")
        dark_names = sorted({names.get(int(i), str(i)) for i in np.unique(ids[dark])})
        r_d, r_b, r_mod = ctx.rate(hole, dark), ctx.rate(hole, bright), ctx.rate(ctx.simulated <= 0, dark)
        numbers = (f"dark materials (albedo < {cut}: {', '.join(dark_names[:4])}) lose {ctx.pct(r_d)} of their pixels, "
                   f"brighter ones {ctx.pct(r_b)} (current model: {ctx.pct(r_mod)} on the dark ones)")
        if not (ctx.ge(r_d, r_b + ctx.MIN_RATE_EXCESS) and ctx.ge(r_d, 1.5 * r_b) and ctx.ge(r_d, r_mod + ctx.MIN_RATE_EXCESS)):
            return ctx.weak("reflectance signature", gain, numbers)
        return (f"dark materials (albedo < {cut}: {', '.join(dark_names[:4])}) lose {ctx.pct(r_d)} of their pixels, "
                f"more than brighter ones ({ctx.pct(r_b)}) and than the current model on the dark ones ({ctx.pct(r_mod)}).")
