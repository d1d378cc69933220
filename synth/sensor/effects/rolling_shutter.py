"""Rolling shutter: image rows are exposed one after the other while the camera moves."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_GEOMETRY, Effect, Signature, param, register_effect


@dataclass
class RollingShutterParams:
    readout_time_s: float = param(0.03, "s")
    """Time between the exposure of the first and the last row, seconds (0 = global shutter)."""
    reference_row: float = param(0.5, "1")
    """Which row the frame's timestamp and pose belong to, as a fraction of the image height: 0.5 =
    the centre row (a driver that stamps mid-exposure), 0 = the first row (a stamp at the start of
    the readout), 1 = the last. Datasets differ and rarely say; the lab fits it."""


def row_times_frames(H: int, readout_s: float, frame_dt_s: float, reference_row: float = 0.5) -> np.ndarray:
    """(H,) exposure time of each row relative to the reference row (the row exposed at the frame's
    timestamp: a fraction of the height, 0.5 = the centre row), in frame periods."""
    v = np.arange(H, dtype=np.float64)
    return (v / max(H - 1, 1) - reference_row) * readout_s / frame_dt_s


@register_effect
class RollingShutter(Effect):
    """Each row sees the scene from the pose the camera had when that row was exposed.

    Physics: a rolling-shutter CMOS sensor (the Kinect v1 IR camera's) reads rows sequentially
    over ``readout_time_s``; a moving camera therefore sees straight edges sheared and
    surfaces at the wrong depth. The projector is rigid with the camera, so it moves along.
    Implementation: the camera path is the constant-velocity interpolation through
    ``prev_pose`` and ``pose`` (one frame period apart); row v is re-rendered (ray cast) from
    the pose at its exposure time; the row at ``reference_row`` (default the centre) is exposed at
    ``pose``. With a constant velocity, moving the reference row shifts every row's pose by the same
    time (readout x the change): a dataset that stamps the first row's exposure (reference 0) seen
    through a centre-row model needs a global shift no readout can give, so the fitted readout
    comes out several times too long (an independent generator stamping the first row: 0.087 s
    fitted for 0.027 s true) - hence the fitted reference row. Depth is then reported in the frame
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
    FITTABLE = {"readout_time_s": (0.0, 0.2), "reference_row": (0.0, 1.0)}
    stage = STAGE_GEOMETRY

    def apply(self, state, draw) -> None:
        from synth.sensor.state import cast_view
        rt = self.params.readout_time_s
        if not state.frame.moving or rt <= 0 or state.renderer is None or state.is_reference:
            state.log[self.name] = {"active": False}
            return
        H = state.shape[0]
        s = row_times_frames(H, rt, state.frame.frame_dt_s, self.params.reference_row)
        rows = state.frame.pose_at(s)
        state.view = cast_view(state.renderer, state.ray_dirs_cam, rows)
        state.publish("row_time_frames", s)
        state.depth = state.view.depth
        state.valid = state.view.hit.copy()
        shift = np.linalg.norm(rows[-1, :3, 3] - rows[0, :3, 3])
        state.log[self.name] = {"active": True, "top_to_bottom_translation_m": float(shift)}
