"""Device post-processing: filling small holes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_POST, Effect, Signature, param, register_effect


@dataclass
class HoleFillingParams:
    max_hole_px: int = param(30, "px²")
    """Holes (connected invalid regions) up to this area, pixels, are filled; larger stay."""
    mode: str = param("farthest", "", choices=("farthest", "nearest"))
    """Fill value from the hole's border: ``farthest`` (background wins, RealSense's default
    hole-filling filter mode) or ``nearest`` (foreground wins)."""


@register_effect
class HoleFilling(Effect):
    """Fill small holes from their border, as device post-processing filters do.

    Device: RealSense's hole-filling filter (and many driver pipelines) replace isolated
    invalid pixels by a neighbour's value; the Kinect v1 firmware does not (so it is off in
    that preset). Implementation: connected components of the invalid mask up to
    ``max_hole_px`` pixels are filled by repeated 3x3 grey dilation (farthest) or erosion
    (nearest) of the valid depths.
    """

    name = "hole_filling"
    SIGNATURE = Signature(
        "fewer holes than the physics predicts",
        "Small holes are filled in: the measured invalid fraction at edges is lower than the "
        "model's.",
        panels=(("edge_distance", "invalid_fraction"),))
    KEEPS_INVALID = False  # it fills holes
    IDENTITY_PARAMS = {"max_hole_px": 0}
    Params = HoleFillingParams
    FITTABLE = {"max_hole_px": (0, 100000)}
    stage = STAGE_POST + 5

    def apply(self, state, draw) -> None:
        import cv2
        inv = (~state.valid).astype(np.uint8)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
        small = np.zeros(n, bool)
        small[1:] = stats[1:, cv2.CC_STAT_AREA] <= self.params.max_hole_px
        # components touching the border are not holes (nothing surrounds them)
        H, W = inv.shape
        border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
        small[border] = False
        target = small[lab]
        if not target.any():
            state.log[self.name] = {"filled_px": 0}
            return
        far = self.params.mode == "farthest"
        z = state.depth.copy()
        filled = state.valid.copy()
        k = np.ones((3, 3), np.uint8)
        todo = target.copy()
        for _ in range(int(np.sqrt(self.params.max_hole_px)) + 2):
            if not todo.any():
                break
            src = np.where(filled, z, 0.0 if far else np.float32(1e9)).astype(np.float32)
            grown = cv2.dilate(src, k) if far else cv2.erode(src, k)
            ok = todo & ((grown > 0) if far else (grown < 1e9))
            z[ok] = grown[ok]
            filled |= ok
            todo &= ~ok
        state.depth = z
        state.valid = filled
        state.log[self.name] = {"filled_px": int((target & filled).sum())}
