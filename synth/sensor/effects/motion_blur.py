"""Motion blur: the image integrates the scene over the exposure while the camera moves."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_DEPTH, STAGE_OPTICS, Effect, Signature, param, register_effect


@dataclass
class MotionBlurParams:
    exposure_s: float = param(0.015, "s")
    """Exposure time, seconds."""
    taps: int = param(3, "1", 1, 64)
    """Sub-exposures averaged (physical) / samples along the motion (direct)."""
    mix_jump_m: float = param(0.05, "m")
    """Direct model: if the depths seen during the exposure spread more than this (an edge
    swept over the pixel), the pixel becomes a hole instead of a mixed value."""


@register_effect
class MotionBlur(Effect):
    """Blur along the camera motion during the exposure.

    Physics: the sensor integrates light over ``exposure_s``; with a moving camera the image
    of every surface point moves. For structured light the dots move with the rig (the
    projector is rigid with the camera), so the pattern itself only shifts where the depth
    along a projector ray changes - moving edges smear, flat walls stay sharp. Physical
    pipeline: the pattern radiance is re-computed (ray cast) for ``taps`` sub-exposure poses
    on the constant-velocity path through prev_pose and pose and averaged (exact for this
    path). Direct model: depth is sampled along each pixel's image motion; pixels that see
    an edge sweep by (depth spread > mix_jump_m) become holes, others get the mean.
    No-op for a static camera.
    """

    name = "motion_blur"
    SIGNATURE = Signature(
        "errors at edges under motion",
        "Errors concentrate next to depth edges (mixed depths during the exposure).",
        panels=(("edge_distance", "std"), ("edge_distance", "invalid_fraction")))
    IDENTITY_PARAMS = {"exposure_s": 0.0}
    Params = MotionBlurParams
    FITTABLE = {"exposure_s": (0.0, 0.1), "mix_jump_m": (0.001, 1.0)}
    FRAME_EXPOSURE_PARAM = "exposure_s"

    def stage_for(self, physical_model: bool) -> int:
        return STAGE_OPTICS if physical_model else STAGE_DEPTH

    def _offsets(self, state) -> np.ndarray:
        k = max(int(self.params.taps), 1)
        return ((np.arange(k) + 0.5) / k - 0.5) * self.params.exposure_s / state.frame.frame_dt_s

    def apply(self, state, draw) -> None:
        from synth.sensor.state import cast_view
        if not state.frame.moving or self.params.exposure_s <= 0 or state.renderer is None or state.is_reference:
            state.log[self.name] = {"active": False}
            return
        H, W = state.shape
        row_s = state.product("row_time_frames", np.zeros(H))
        offs = self._offsets(state)
        if state.physical:
            from synth.sensor.effects.pattern_projection import compute_radiance
            proj = state.product("projector")
            if proj is None or state.radiance is None:
                state.log[self.name] = {"active": False, "reason": "no pattern_projection"}
                return
            pb = proj.pattern_blurred
            acc = np.zeros((H, W), np.float32)
            acc2 = np.zeros((H, W), np.float32) if state.radiance_second is not None else None
            off2 = (state.preset.projector_side * state.preset.baseline_m, 0.0, 0.0)
            for o in offs:
                if abs(o) < 1e-12:  # the centre of the exposure is the frame itself: reuse it
                    acc += state.radiance
                    if acc2 is not None:
                        acc2 += state.radiance_second
                    continue
                rows = state.frame.pose_at(row_s + o)
                v = cast_view(state.renderer, state.ray_dirs_cam, rows)
                acc += compute_radiance(v, (0, 0, 0), state.preset, pb, proj.params, state.renderer,
                                        state.ray_dirs_cam)[0]
                if acc2 is not None:
                    v2 = cast_view(state.renderer, state.ray_dirs_cam, rows, off2)
                    acc2 += compute_radiance(v2, off2, state.preset, pb, proj.params, state.renderer,
                                             state.ray_dirs_cam)[0]
            state.radiance = acc / len(offs)
            if acc2 is not None:
                state.radiance_second = acc2 / len(offs)
            state.log[self.name] = {"active": True, "taps": len(offs)}
            return
        # direct: sample depth along the image motion of each pixel
        import cv2
        from data_tools.geometry import invert_pose
        X = state.view.points_cam.reshape(-1, 3).astype(np.float64)
        T0 = state.pose_c2w
        zs = []
        intr = state.intr
        for o in offs:
            Tk = state.frame.pose_at(o)
            M = invert_pose(Tk) @ T0                      # camera(0) -> camera(o)
            Y = X @ M[:3, :3].T + M[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = intr.fx * Y[:, 0] / Y[:, 2] + intr.cx
                v = intr.fy * Y[:, 1] / Y[:, 2] + intr.cy
            uu, vv = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
            du = np.nan_to_num(u.reshape(H, W) - uu, nan=0.0, posinf=0.0, neginf=0.0)
            dv = np.nan_to_num(v.reshape(H, W) - vv, nan=0.0, posinf=0.0, neginf=0.0)
            # backward sampling: the pixel sees at time o what was at (u - flow) at time 0
            zk = cv2.remap(state.depth, (uu - du).astype(np.float32), (vv - dv).astype(np.float32),
                           cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            zs.append(zk)
        Z = np.stack(zs)
        bad = (Z <= 0).any(0) | ((Z.max(0) - Z.min(0)) > self.params.mix_jump_m)
        state.depth = np.where(bad, 0.0, Z.mean(0)).astype(np.float32)
        state.invalidate(bad, self.name)
        state.log[self.name]["active"] = True
