"""Direct model: systematic depth errors (calibration residuals)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_DEPTH, Effect, register_effect


@dataclass
class DepthBiasParams:
    offset_m: float = 0.0
    """Constant depth offset, metres."""
    scale: float = 0.0
    """Relative depth scale error (z' = (1 + scale) z)."""
    disparity_offset_px: float = 0.0
    """Constant disparity error, pixels (-> depth error growing as z^2; triangulation only)."""
    radial_disparity_px: float = 0.0
    """Disparity error at the image corner, growing with the squared radius from the centre
    (the Kinect's 'depth distortion' bowl)."""


@register_effect
class DepthBias(Effect):
    """Deterministic depth error: z' = (1 + scale) z(d + e(u, v)) + offset.

    Physics: a device's factory calibration is never perfect. An error in f b or in the
    reference-plane depth gives a disparity offset (depth error ~ z^2); the IR lens and
    reference-image errors give a spatially varying disparity error that grows towards the
    corners (Herrera et al. 2012 model it as a per-pixel disparity distortion); ToF sensors
    have offset and scale errors. No randomness: the same pixel at the same depth always gets
    the same bias.
    """

    name = "depth_bias"
    IDENTITY_PARAMS = {"offset_m": 0.0, "scale": 0.0, "disparity_offset_px": 0.0, "radial_disparity_px": 0.0}
    Params = DepthBiasParams
    FITTABLE = {"offset_m": (-0.1, 0.1), "scale": (-0.1, 0.1), "disparity_offset_px": (-2.0, 2.0),
                "radial_disparity_px": (-2.0, 2.0)}
    stage = STAGE_DEPTH + 1

    def apply(self, state, draw) -> None:
        p = self.params
        z = state.depth.astype(np.float64)
        if (p.disparity_offset_px or p.radial_disparity_px) and state.preset.fb > 0:
            H, W = state.shape
            intr = state.intr
            uu, vv = np.meshgrid(np.arange(W), np.arange(H))
            r2 = ((uu - intr.cx) ** 2 + (vv - intr.cy) ** 2) / (intr.cx ** 2 + intr.cy ** 2)
            e = p.disparity_offset_px + p.radial_disparity_px * r2
            fb = state.preset.fb
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.where(z > 0, 1.0 / (1.0 / z + e / fb), 0.0)
        z = (1.0 + p.scale) * z + p.offset_m
        state.depth = np.where(state.valid, z, 0).astype(np.float32)
        state.valid &= state.depth > 0
