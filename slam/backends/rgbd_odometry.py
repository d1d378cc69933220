"""``rgbd_odometry``: frame-to-frame dense RGB-D odometry (Open3D's hybrid photometric + depth
kernels, Park, Zhou and Koltun 2017), with our own failure check.

Each frame is registered to the last good frame, coarse to fine on image pyramids that are
built once per frame (the source pyramid of frame k is the target pyramid of frame k+1).
Open3D's odometry reports a transformation even when the two images do not overlap at all,
so every result is checked: valid depth, inlier correspondences and fitness of the geometric
(point-to-plane) residual at the final estimate, residual size and plausible camera speed. A
failed frame is skipped (not in the trajectory, not fused) and the next frame is registered
to the same last good frame; re-localisation tries the static guess and an ORB/PnP guess
before giving up.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import ConfigError
from slam.backends._features import orb_features, pnp_guess
from slam.backends._pyramid import Pyramid, SolveResult, rgbd_hybrid
from slam.registration import (RegistrationBackend, TrackingCheckConfig, TrackResult, check_positive,
                               register_backend)

METHODS = ("hybrid", "point_to_plane", "intensity")


@dataclass
class RGBDOdometryConfig(TrackingCheckConfig):
    """Frame-to-frame RGB-D odometry options (the failure-check and re-localisation fields
    come from :class:`slam.registration.TrackingCheckConfig`)."""

    method: str = "hybrid"
    """Loss: ``hybrid`` (intensity + depth), ``point_to_plane`` (depth only) or ``intensity``."""
    levels: tuple[int, ...] = (3, 2, 1)
    """Pyramid levels used, coarse to fine (0 = full resolution, l = downsampled by 2^l)."""
    iterations: tuple[int, ...] = (10, 6, 4)
    """Maximum Gauss-Newton iterations per level."""
    depth_diff_m: float = 0.07
    """Largest depth difference of a projective correspondence, metres."""
    depth_huber_m: float = 0.05
    """Huber width of the depth residual, metres."""
    intensity_huber: float = 0.1
    """Huber width of the intensity residual (intensities in [0, 1])."""
    min_fitness: float = 0.3
    """Fail when fewer than this fraction of the valid pixels have an inlier correspondence
    (Open3D's reconstruction system uses the same 0.3 overlap threshold)."""

    def validate(self) -> "RGBDOdometryConfig":
        if self.method not in METHODS:
            raise ConfigError(f"RGBDOdometryConfig.method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if not self.levels or len(self.iterations) != len(self.levels):
            raise ConfigError("RGBDOdometryConfig: levels and iterations need one entry per level")
        if any(l < 0 or l > 5 for l in self.levels):
            raise ConfigError(f"RGBDOdometryConfig.levels must be in 0..5, got {self.levels}")
        if any(i < 1 for i in self.iterations):
            raise ConfigError("RGBDOdometryConfig.iterations must be >= 1")
        self.validate_checks()
        check_positive(self, "depth_diff_m", "depth_huber_m", "intensity_huber")
        return self


@register_backend
class RGBDOdometryBackend(RegistrationBackend):
    """Frame-to-frame hybrid RGB-D odometry with a failure check."""

    name = "rgbd_odometry"
    Config = RGBDOdometryConfig
    uses_color = True

    def __init__(self, config: RGBDOdometryConfig, intrinsics: Intrinsics, tsdf_config, sensor=None):
        super().__init__(config.validate(), intrinsics, tsdf_config, sensor)
        self._n_levels = max(self.config.levels) + 1
        self.last_pose: np.ndarray | None = None
        self.prev_pose: np.ndarray | None = None
        self.last_t: float | None = None
        self.last_index = -1
        self.consecutive_failures = 0
        self._last_pyr: Pyramid | None = None
        self._last_frame = None
        self._kf_features = None
        self.fitness_history: deque[float] = deque(maxlen=10)

    def _pyramid(self, frame) -> Pyramid:
        rgb = frame.rgb
        if rgb is None and self.config.method != "point_to_plane":
            rgb = np.zeros(frame.depth.shape + (3,), np.uint8)  # no colour: intensity terms vanish
        return Pyramid(frame.depth, self.intrinsics, self._n_levels, self.tsdf_config.depth_min_m,
                       self.tsdf_config.depth_max_m, rgb, self.config.depth_diff_m * 2)

    def _solve(self, pyr: Pyramid, init_rel: np.ndarray) -> SolveResult:
        c = self.config
        return rgbd_hybrid(pyr, self._last_pyr, init_rel, list(c.iterations), list(c.levels),
                           c.depth_diff_m, c.depth_huber_m, c.intensity_huber, c.method)

    def _check(self, sol: SolveResult, pose: np.ndarray, t: float) -> str:
        return self.config.check_solution(sol, self.last_pose, pose, t - self.last_t)

    def _accept(self, frame, pyr: Pyramid, pose: np.ndarray, fitness: float | None) -> None:
        self.prev_pose = self.last_pose if self.consecutive_failures == 0 else None
        self.last_pose = pose
        self.last_t = float(frame.timestamp)
        self.last_index = int(frame.index)
        self.consecutive_failures = 0
        self._last_pyr = pyr
        self._last_frame = frame
        self._kf_features = None
        if fitness is not None:
            self.fitness_history.append(float(fitness))

    def _guesses(self, frame):
        c = self.config
        yield "motion model", c.predict(self.last_pose, self.prev_pose, self.consecutive_failures > 0)
        if not c.relocalise:
            return
        yield "static", self.last_pose.copy()
        kf = self._last_frame
        if frame.rgb is not None and kf is not None and kf.rgb is not None:
            if self._kf_features is None:
                self._kf_features = orb_features(kf.rgb, c.orb_features)
            g = pnp_guess(self._kf_features, kf.depth, orb_features(frame.rgb, c.orb_features),
                          self.intrinsics, c.pnp_min_inliers)
            yield "ORB/PnP", None if g is None else self.last_pose @ g.T_cur_to_kf

    def track(self, frame, volume) -> TrackResult:
        c = self.config
        depth = frame.depth
        frac = c.valid_depth_fraction(depth, self.tsdf_config.depth_min_m, self.tsdf_config.depth_max_m)
        if frac < c.min_valid_fraction:
            self.consecutive_failures += 1
            return TrackResult(None, None, None, True, f"too few valid depth pixels ({frac:.1%})")
        pyr = self._pyramid(frame)
        if self.last_pose is None:
            self._accept(frame, pyr, np.eye(4), None)
            return TrackResult(np.eye(4), None, None, False, "first frame: defines the world frame")
        T_inv_last = np.linalg.inv(self.last_pose)
        t = float(frame.timestamp)
        first_reason, tried = "", []
        for label, guess in self._guesses(frame):
            if guess is None or any(np.allclose(guess, g, atol=1e-9) for g in tried):
                continue
            tried.append(guess)
            sol = self._solve(pyr, T_inv_last @ guess)
            pose = self.last_pose @ sol.transformation
            reason = self._check(sol, pose, t)
            if not reason:
                relocalised = bool(first_reason)
                self._accept(frame, pyr, pose, sol.fitness)
                return TrackResult(pose, sol.fitness, sol.inlier_rmse, False,
                                   f"re-localised ({label}) after: {first_reason}" if relocalised else "",
                                   relocalised)
            if not first_reason:
                first_reason = reason
                if not c.relocalise:
                    break
        self.consecutive_failures += 1
        return TrackResult(None, None, None, True, first_reason or "no initial guess")

    # ---------------------------------------------------------------- resume
    def state_dict(self) -> dict:
        return {"last_pose": None if self.last_pose is None else self.last_pose.reshape(-1).tolist(),
                "prev_pose": None if self.prev_pose is None else self.prev_pose.reshape(-1).tolist(),
                "last_t": self.last_t, "last_index": self.last_index,
                "consecutive_failures": self.consecutive_failures,
                "fitness_history": list(self.fitness_history)}

    def load_state(self, state: dict, reader, volume) -> None:
        def m(v):
            return None if v is None else np.asarray(v, dtype=np.float64).reshape(4, 4)
        self.last_pose = m(state.get("last_pose"))
        self.prev_pose = m(state.get("prev_pose"))
        self.last_t = state.get("last_t")
        self.last_index = int(state.get("last_index", -1))
        self.consecutive_failures = int(state.get("consecutive_failures", 0))
        self.fitness_history = deque(state.get("fitness_history", []), maxlen=10)
        if self.last_index >= 0:
            self._last_frame = reader[self.last_index]
            self._last_pyr = self._pyramid(self._last_frame)
