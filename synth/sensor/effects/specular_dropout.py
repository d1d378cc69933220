"""Direct model: shiny surfaces send the pattern away (or blind the camera)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import check_draw, drop_with_probability, sigmoid, uniform_draw
from synth.sensor.registry import STAGE_DROPOUT, Effect, Signature, param, register_effect


@dataclass
class SpecularDropoutParams:
    specular50: float = param(0.6, "1")
    """Material specular weight at which half the pixels drop."""
    width: float = param(0.1, "1")
    """Width of the transition (logistic scale)."""
    highlight_deg: float = param(5.0, "deg")
    """Pixels whose mirror direction points within this angle of the camera saturate and drop
    (when the material has any specular lobe)."""


@register_effect
class SpecularDropout(Effect):
    """Holes on mirror-like materials and at specular highlights.

    Physics: a specular surface reflects the projected light into the mirror direction, away
    from the camera, leaving too little diffuse light to match; where the mirror direction hits
    the camera the highlight saturates the sensor, which also gives no match. p_drop =
    logistic((s - specular50) / width) for a material of specular weight s, and 1 inside
    ``highlight_deg`` of the mirror direction. Draw: one U(0, 1) per pixel.
    """

    name = "specular_dropout"
    SIGNATURE = Signature(
        "holes on shiny materials",
        "The invalid fraction differs by material and peaks where the mirror reflection points "
        "back at the camera (near-normal incidence).",
        panels=(("material", "invalid_fraction"), ("incidence", "invalid_fraction")))
    DRAW_FROM_SHAPE = True
    Params = SpecularDropoutParams
    FITTABLE = {"specular50": (0.0, 1.0), "width": (0.01, 1.0), "highlight_deg": (0.0, 45.0)}
    stage = STAGE_DROPOUT

    def sample(self, rng, state):
        return uniform_draw(rng, state.shape)

    def apply(self, state, draw) -> None:
        u = check_draw(draw, "u", state.shape, self.name)
        v = state.view
        s = v.specular
        p = sigmoid((s - self.params.specular50) / self.params.width)
        p[s <= 0] = 0
        if np.any(s > 0):
            # mirror direction of the projector ray vs the direction to the camera (component-wise)
            src = np.asarray(state.preset.projector_offset_m, np.float32)
            X = [v.points_cam[..., k] for k in range(3)]
            n = [v.normals_cam[..., k] for k in range(3)]
            L = [X[k] - src[k] for k in range(3)]
            inv_l = np.float32(1.0) / np.maximum(np.sqrt(L[0] ** 2 + L[1] ** 2 + L[2] ** 2), np.float32(1e-9))
            ln2 = np.float32(2.0) * (L[0] * n[0] + L[1] * n[1] + L[2] * n[2]) * inv_l
            inv_x = np.float32(-1.0) / np.maximum(np.sqrt(X[0] ** 2 + X[1] ** 2 + X[2] ** 2), np.float32(1e-9))
            cosa = sum((L[k] * inv_l - ln2 * n[k]) * X[k] for k in range(3)) * inv_x
            hl = (cosa > np.cos(np.radians(self.params.highlight_deg))) & (s > 0)
            p = np.where(hl, np.float32(1.0), p).astype(np.float32)
        p[~v.hit] = 0
        drop_with_probability(state, p, u, self.name)
