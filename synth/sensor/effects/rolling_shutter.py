"""Rolling shutter: image rows are exposed one after the other while the camera moves."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_GEOMETRY, Effect, Signature, param, register_effect


@dataclass
class RollingShutterParams:
    readout_time_s: float = param(0.03, "s")
    """Time between the exposure of the first and the last row, seconds (0 = global shutter)."""


def row_times_frames(H: int, readout_s: float, frame_dt_s: float) -> np.ndarray:
    """(H,) exposure time of each row relative to the centre row, in frame periods."""
    v = np.arange(H, dtype=np.float64)
    return (v / max(H - 1, 1) - 0.5) * readout_s / frame_dt_s


@register_effect
class RollingShutter(Effect):
    """Each row sees the scene from the pose the camera had when that row was exposed.

    Physics: a rolling-shutter CMOS sensor (the Kinect v1 IR camera's) reads rows sequentially
    over ``readout_time_s``; a moving camera therefore sees straight edges sheared and
    surfaces at the wrong depth. The projector is rigid with the camera, so it moves along.
    Implementation: the camera path is the constant-velocity interpolation through
    ``prev_pose`` and ``pose`` (one frame period apart); row v is re-rendered (ray cast) from
    the pose at its exposure time, centre row = ``pose``. Depth is then reported in the frame
    of the row's own pose, as the device does. Runs in both the physical pipeline and the
    direct model (it changes what each pixel sees). No-op for a static camera.
    """

    name = "rolling_shutter"
    SIGNATURE = Signature(
        "edge displacement under motion",
        "Depth edges appear shifted: biased errors on both sides of edges and a bias that changes "
        "across the image.",
        panels=(("edge_distance", "bias"), ("radial", "bias")))
    KEEPS_INVALID = False  # each row is re-rendered at its own pose
    IDENTITY_PARAMS = {"readout_time_s": 0.0}
    Params = RollingShutterParams
    FITTABLE = {"readout_time_s": (0.0, 0.2)}
    stage = STAGE_GEOMETRY

    def apply(self, state, draw) -> None:
        from synth.sensor.state import cast_view
        rt = self.params.readout_time_s
        if not state.frame.moving or rt <= 0 or state.renderer is None or state.is_reference:
            state.log[self.name] = {"active": False}
            return
        H = state.shape[0]
        s = row_times_frames(H, rt, state.frame.frame_dt_s)
        rows = state.frame.pose_at(s)
        state.view = cast_view(state.renderer, state.ray_dirs_cam, rows)
        state.publish("row_time_frames", s)
        state.depth = state.view.depth
        state.valid = state.view.hit.copy()
        shift = np.linalg.norm(rows[-1, :3, 3] - rows[0, :3, 3])
        state.log[self.name] = {"active": True, "top_to_bottom_translation_m": float(shift)}
