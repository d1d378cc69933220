"""ToF: pixels on depth edges report a depth between foreground and background."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import check_draw
from synth.sensor.registry import STAGE_DEPTH, Effect, Signature, param, register_effect


@dataclass
class FlyingPixelsParams:
    jump_m: float = param(0.1, "m")
    """A pixel is on an edge when its 3x3 neighbourhood spans more than this depth, metres."""
    probability: float = param(0.7, "1")
    """Fraction of edge pixels that become flying pixels."""


@register_effect
class FlyingPixels(Effect):
    """Edge pixels get z = a z_self + (1 - a) z_other, a ~ U(0, 1).

    Physics: a ToF pixel straddling a depth edge receives light from both surfaces; the
    phasors add and the measured phase lies between them, giving points floating between
    foreground and background (and, with motion between the four phase exposures, the same
    at moving edges). The mixing weight (the pixel's coverage) is not known from a pixel-
    centre render, so it is drawn uniformly. ``z_other`` is the neighbour depth farthest from
    the pixel's own. Draws: two U(0, 1) per pixel (whether, and how much).
    """

    name = "flying_pixels"
    SIGNATURE = Signature(
        "depths between foreground and background at edges",
        "Pixels within one or two pixels of a depth edge take intermediate depths: large spread "
        "right at the edge.",
        panels=(("edge_distance", "std"), ("edge_distance", "bias")))
    IDENTITY_PARAMS = {"probability": 0.0}
    sensor_types = ("tof",)  # phase measurement of continuous-wave time of flight
    DRAW_FROM_SHAPE = True
    Params = FlyingPixelsParams
    FITTABLE = {"jump_m": (0.005, 2.0), "probability": (0.0, 1.0)}
    stage = STAGE_DEPTH - 1

    def sample(self, rng, state):
        return {"u": rng.random(state.shape, dtype=np.float32), "a": rng.random(state.shape, dtype=np.float32)}

    def apply(self, state, draw) -> None:
        import cv2
        u = check_draw(draw, "u", state.shape, self.name)
        a = check_draw(draw, "a", state.shape, self.name)
        z = state.depth
        k = np.ones((3, 3), np.uint8)
        zmax = cv2.dilate(np.where(state.valid, z, 0).astype(np.float32), k)
        zmin = cv2.erode(np.where(state.valid, z, 1e6).astype(np.float32), k)
        edge = state.valid & ((zmax - zmin) > self.params.jump_m) & (u < self.params.probability)
        other = np.where(zmax - z > z - zmin, zmax, zmin)
        mixed = a * z + (1 - a) * other
        state.depth = np.where(edge, mixed, z).astype(np.float32)
        state.log[self.name] = {"flying_px": int(edge.sum())}
