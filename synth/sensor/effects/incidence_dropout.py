"""Direct model: grazing surfaces are lost."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import check_draw, cos_view, drop_with_probability, sigmoid, uniform_draw
from synth.sensor.registry import STAGE_DROPOUT, Effect, register_effect


@dataclass
class IncidenceDropoutParams:
    angle50_deg: float = 78.0
    """Angle between the surface normal and the viewing ray at which half the pixels drop."""
    width_deg: float = 2.5
    """Width of the transition (logistic scale), degrees."""


@register_effect
class IncidenceDropout(Effect):
    """Pixels drop with probability logistic((theta - angle50) / width), theta the angle between
    the surface normal and the viewing ray.

    Physics: at grazing incidence the returned signal falls with cos(theta) and, for
    structured light, the pattern is compressed by the steep disparity gradient until the
    correlation window no longer matches (the physical pipeline shows this through the
    matcher's speckle/consistency filter); real Kinect v1 data loses most pixels beyond
    ~75-80 degrees. Draw: one U(0, 1) per pixel.
    """

    name = "incidence_dropout"
    DRAW_FROM_SHAPE = True
    Params = IncidenceDropoutParams
    FITTABLE = {"angle50_deg": (30.0, 90.0), "width_deg": (0.1, 30.0)}
    stage = STAGE_DROPOUT

    def sample(self, rng, state):
        return uniform_draw(rng, state.shape)

    def apply(self, state, draw) -> None:
        u = check_draw(draw, "u", state.shape, self.name)
        c = cos_view(state.view, state.ray_dirs_cam)
        theta = np.degrees(np.arccos(np.clip(c, 0, 1)))
        p = sigmoid((theta - self.params.angle50_deg) / self.params.width_deg)
        p[~state.view.hit] = 0
        drop_with_probability(state, p, u, self.name)
