"""Ambient infrared light (sunlight, incandescent lamps) on top of the projected pattern."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import check_draw, cos_incidence, drop_with_probability, sigmoid, uniform_draw
from synth.sensor.registry import STAGE_DROPOUT, STAGE_LIGHT, Effect, Signature, param, register_effect


@dataclass
class AmbientLightParams:
    level: float = param(0.0, "1")
    """Ambient IR radiance of a white surface, in the projector's units (1 = the pattern's
    brightest dot on a white surface at 1 m). Indoors ~0.01; overcast daylight ~1; direct sun
    >> 10."""
    contrast50: float = param(0.3, "1")
    """Direct model: pattern contrast signal / (signal + ambient) at which half the pixels drop."""
    contrast_width: float = param(0.08, "1")
    """Direct model: width of that transition (logistic scale)."""


@register_effect
class AmbientLight(Effect):
    """Ambient IR adds a uniform radiance ``level * albedo`` to every surface.

    Physics: band-pass-filtered sunlight/lamp light reaches the IR camera regardless of the
    projector. It carries no pattern, so it lowers the pattern's contrast and adds shot noise;
    strong ambient light saturates the sensor (structured-light sensors fail outdoors).
    Physical pipeline: stores the ambient radiance for ``ir_capture`` (which adds it before the
    noise). Direct model: drops pixels with probability logistic((contrast50 - c) / width),
    c = s / (s + level * albedo), s = albedo cos(incidence) / r^2 the pattern signal.
    """

    name = "ambient_light"
    SIGNATURE = Signature(
        "holes growing with distance under ambient light",
        "Sunlight or lamps drown the projected pattern: the invalid fraction rises with distance "
        "(weaker pattern) over the whole image.",
        panels=(("distance", "invalid_fraction"), ("radial", "invalid_fraction")))
    IDENTITY_PARAMS = {"level": 0.0}
    DRAW_FROM_SHAPE = True
    Params = AmbientLightParams
    FITTABLE = {"level": (0.0, 100.0), "contrast50": (0.0, 1.0), "contrast_width": (0.005, 1.0)}

    def stage_for(self, physical_model: bool) -> int:
        return STAGE_LIGHT if physical_model else STAGE_DROPOUT

    def sample(self, rng, state):
        return None if state.physical else uniform_draw(rng, state.shape)

    def apply(self, state, draw) -> None:
        lvl = np.float32(self.params.level)
        if state.physical:
            state.publish("ambient", np.where(state.view.hit, lvl * state.view.albedo, 0).astype(np.float32))
            if state.second_view is not None:
                sv = state.second_view
                state.publish("ambient_second", np.where(sv.hit, lvl * sv.albedo, 0).astype(np.float32))
            state.log[self.name] = {"level": float(lvl)}
            return
        u = check_draw(draw, "u", state.shape, self.name)
        v = state.view
        cos_i, r = cos_incidence(v, state.preset.projector_offset_m)
        s = v.albedo * (1 - v.specular) * cos_i / np.maximum(r * r, 1e-6)
        c = s / np.maximum(s + lvl * v.albedo, 1e-12)
        p = sigmoid((self.params.contrast50 - c) / self.params.contrast_width)
        p[~v.hit] = 0
        if lvl <= 0:
            p[:] = 0
        drop_with_probability(state, p, u, self.name)
