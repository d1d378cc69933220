"""Direct model: the device reports disparity in sub-pixel steps."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_QUANTIZE, Effect, register_effect


@dataclass
class DisparityQuantizationParams:
    step_px: float = 0.0
    """Disparity step, pixels; 0 = the preset's (Kinect v1: 1/8)."""


@register_effect
class DisparityQuantization(Effect):
    """Depth snaps to the levels of a quantised disparity: z = 1 / (1/z0 + k step / (f b)).

    Physics/device: the correlator's sub-pixel interpolation has a fixed resolution (Kinect v1:
    1/8 px, 11-bit disparity); depth is computed from that integer code, so it takes discrete
    values whose spacing grows with the square of depth: dz ~ z^2 step / (f b) (2.9 mm at 1 m,
    4.6 cm at 4 m for Kinect v1). The physical pipeline quantises inside ``block_matching``;
    applying this effect after it changes nothing (idempotent). No-op for ToF.
    """

    name = "disparity_quantization"
    sensor_types = ("structured_light", "active_stereo")  # triangulation
    Params = DisparityQuantizationParams
    FITTABLE = {"step_px": (0.0, 1.0)}
    stage = STAGE_QUANTIZE

    def apply(self, state, draw) -> None:
        import dataclasses
        from synth.sensor.matching import MatchSetup
        pre = state.preset
        if pre.type == "tof" or pre.fb <= 0:
            state.log[self.name] = {"active": False}
            return
        setup = MatchSetup.for_preset(pre)
        if self.params.step_px:
            setup = dataclasses.replace(setup, step=float(self.params.step_px))
        d = setup.quantize(setup.depth_to_disparity(np.where(state.valid, state.depth, 0)))
        z = setup.disparity_to_depth(d)
        state.depth = np.where(state.valid, z, 0).astype(np.float32)
        state.valid &= state.depth > 0
        state.disparity = np.where(state.valid, d, np.nan).astype(np.float32)
        state.log[self.name] = {"step_px": setup.step}
