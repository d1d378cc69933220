"""Direct model: dark or distant surfaces return too little light."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import (check_draw, cos_incidence, drop_with_probability, sigmoid,
                                          uniform_draw)
from synth.sensor.registry import STAGE_DROPOUT, Effect, register_effect


@dataclass
class LowReflectanceParams:
    signal50: float = 0.004
    """Relative returned signal at which half the pixels drop; signal = albedo (1 - specular)
    cos(incidence) / r^2 with r in metres (a white wall facing the sensor at 1 m = 1)."""
    width_decades: float = 0.25
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
