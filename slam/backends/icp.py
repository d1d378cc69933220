"""``icp``: KinectFusion-style frame-to-model tracking against the fused TSDF volume.

For every frame the TSDF model is ray cast from the previous tracked pose (by default with the
numba ray caster of :mod:`slam.raycast_kernel`, every hit at the zero of the trilinear TSDF and
verified, see ``raycaster`` and ``refine_model``; vertex map, and normals from the
bilateral-filtered model depth), and the new depth image is registered to that model view with
coarse-to-fine projective point-to-plane ICP (see :mod:`slam.backends._pyramid`; its sums have a
fixed order, so a run gives the same bits on any number of threads). The initial guess is the previous pose, or that pose moved by
the last inter-frame motion (``motion_model = constant_velocity``).

Failure check (a frame is never silently accepted): too few valid depth pixels, too few
inlier correspondences, fitness below an absolute floor or far below the recent median,
residual too large, or a motion faster than a hand-held camera. A failed frame is left out of
the trajectory and not fused. Re-localisation then tries other initial guesses against the
model at the last good pose: the static guess and an ORB/PnP guess from the last good frame
(keyframe); a guess is accepted only if the dense ICP started from it passes the same checks.

Why the defaults (one reason each; the ablations, their ATEs and speeds are in docs/slam.md
and docs/performance.md):

* ``raycaster = kernel``: Open3D's ray cast followed by the refinement and repair of its hits
  cost about three times as much as one march of the trilinear TSDF that starts near the last
  fused depth and gives verified sub-voxel hits directly.
* ``source_levels = (2, 1, 1)``: the model view is cast at half resolution, so full-resolution
  source points add four times the work of the last stage for the same target pixels and gave
  the same ATE.
* ``raycast_every = 2``, ``fuse_every = 2``: at camera rate the model seen from the last pose
  barely changes between frames; re-using it (re-cast anyway after 5 cm or 3 degrees) and
  fusing every other frame cut the two largest costs left without changing the ATE.
* ``convergence_eps = 2e-4``: a stage stops once a step moves less than 0.2 mm and 0.01 degrees,
  far below the depth noise; most stages converge in a few of their iterations.

* ``refine_model``: Open3D's raw ray cast lies several millimetres in front of the surface and misses
  some hits, which biases the pose in weakly constrained views; every hit is moved to the zero of the
  trilinear TSDF.
* ``repair_model``: dropping the hits that fail that check leaves slanted surfaces, which pin sideways
  motion, under-represented; they are searched again instead.
* ``disparity_noise_px``: far, coarsely quantised depth dominates an unweighted fit, so each point is
  weighted by its sensor's depth noise. The weight enters the ICP kernel as model normals
  scaled by sqrt(w), so the rejection distance applies to sqrt(w) x r; the failure check's fitness and
  RMS residual stay unweighted.
"""
from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import ConfigError
from data_tools.geometry import rotation_angle_rad
from slam.backends._features import orb_features, pnp_guess
from slam.backends._pyramid import (Level, Pyramid, SolveResult, downsample_depth, downsample_image,
                                    icp_point_to_plane, normal_map, smooth_normal_map)
from slam.registration import (RegistrationBackend, TrackingCheckConfig, TrackResult, check_positive,
                               register_backend)
from slam.tsdf import RaycastResult


@dataclass
class ICPConfig(TrackingCheckConfig):
    """Frame-to-model ICP options (the failure-check and re-localisation fields come from
    :class:`slam.registration.TrackingCheckConfig`; stricter defaults are re-declared here)."""

    source_levels: tuple[int, ...] = (2, 1, 1)
    """Pyramid level of the new frame used by each stage, coarse to fine (0 = full resolution,
    l = downsampled by 2^l)."""
    iterations: tuple[int, ...] = (10, 5, 4)
    """Maximum Gauss-Newton iterations per stage."""
    max_correspondence_m: tuple[float, ...] = (0.10, 0.05, 0.025)
    """Largest point-to-plane distance of a correspondence per stage, metres (rejects outliers)."""
    huber_delta_m: float = 0.0
    """Huber width of the robust loss, metres; 0 = plain least squares over the inliers."""
    model_normals: str = "depth"
    """Normals of the model view: ``depth`` (central differences of the bilateral-filtered
    ray-cast depth, KinectFusion's choice) or ``tsdf`` (TSDF gradient in the hit voxel; noisy
    when pixels are smaller than voxels, since each voxel samples one pixel)."""
    refine_model: bool = True
    """Track against a verified, sub-voxel model view: every ray-cast hit is moved to the zero
    of the trilinear TSDF and false hits of Open3D's ray marcher are searched again or dropped
    (:meth:`slam.tsdf.TSDFVolume.raycast`); ``false`` tracks against the raw cast like
    Open3D's dense SLAM (measurements: module docstring)."""
    repair_model: bool = True
    """With ``refine_model``: search the crossing again along the rays whose hit fails the
    check instead of dropping them (measurements: module docstring)."""
    raycast_scale: float = 0.5
    """Resolution of the model ray cast relative to the frame (1, 0.5 or 0.25): the model view is
    the target of projective association; half resolution costs a quarter of the ray casting."""
    convergence_eps: float = 2e-4
    """A stage stops early when a Gauss-Newton step moves less than this (metres and radians):
    0.2 mm and 0.01 degrees, well below the depth noise, end a stage once it has converged."""
    raycaster: str = "kernel"
    """Model ray caster: ``kernel`` (:mod:`slam.raycast_kernel`: marches the trilinear TSDF from
    the last fused depth, sub-voxel hits with the same verification as ``refine_model``) or
    ``open3d`` (Open3D's ray cast, then ``refine_model`` / ``repair_model`` on its hits). The
    kernel needs ``model_normals = depth`` and ``refine_model``; otherwise Open3D's is used."""
    fuse_every: int = 2
    """Fuse every n-th frame of the sequence (after ``frame_step``) into the TSDF; the frames in
    between are only registered: at camera rate consecutive frames see nearly the same surface,
    and fusion is a large share of the run time (1 = every frame, KinectFusion)."""
    raycast_every: int = 2
    """Ray cast the model at most every this many frames: in between, the frame is registered
    to the last model view (1 = every frame, KinectFusion)."""
    recast_translation_m: float = 0.05
    """With ``raycast_every`` > 1: ray cast anyway once the camera is farther than this from
    the pose of the last model view, metres."""
    recast_rotation_deg: float = 3.0
    """With ``raycast_every`` > 1: ray cast anyway once the camera turned more than this from
    the pose of the last model view, degrees."""
    min_correspondences: int = 1000
    """Fail when the finest stage has fewer inlier correspondences."""
    min_fitness: float = 0.2
    """Fail when fewer than this fraction of the valid pixels have an inlier correspondence."""
    fitness_drop_ratio: float = 0.5
    """Fail when the fitness falls below this fraction of the median of the last 10 good frames."""
    max_rmse_m: float = 0.02
    """Fail when the RMS point-to-plane residual of the inliers is larger, metres."""
    disparity_noise_px: float = 0.07
    """Disparity noise of a triangulating depth sensor, pixels: sigma_z = disparity_noise_px x
    z^2 / (fx x baseline), fx and the baseline from the ``sensor`` block of camera.json (0.07 px
    gives Kinect v1's 4 cm at 5 m, Khoshelham and Elberink 2012). Each point-to-plane residual
    gets the inverse-variance weight w = sigma_0^2 / (sigma_0^2 + (sigma_z cos)^2), cos = |n .
    ray|, sigma_0 = voxel size / sqrt(12) the model's own noise; a model point fused from n
    observations counts sigma_z^2 (1 + 1/n) times. 0, or no sensor block: unweighted
    (measurements: module docstring)."""

    def validate(self) -> "ICPConfig":
        n = len(self.source_levels)
        if n == 0 or len(self.iterations) != n or len(self.max_correspondence_m) != n:
            raise ConfigError("ICPConfig: source_levels, iterations and max_correspondence_m need one entry per stage")
        if any(l < 0 or l > 5 for l in self.source_levels):
            raise ConfigError(f"ICPConfig.source_levels must be in 0..5, got {self.source_levels}")
        if any(i < 1 for i in self.iterations) or any(not (d > 0) for d in self.max_correspondence_m):
            raise ConfigError("ICPConfig: iterations must be >= 1 and max_correspondence_m > 0")
        if self.raycast_scale not in (1.0, 0.5, 0.25):
            raise ConfigError(f"ICPConfig.raycast_scale must be 1, 0.5 or 0.25, got {self.raycast_scale}")
        if self.raycaster not in ("kernel", "open3d"):
            raise ConfigError(f"ICPConfig.raycaster must be kernel or open3d, got {self.raycaster!r}")
        if self.model_normals not in ("depth", "tsdf"):
            raise ConfigError(f"ICPConfig.model_normals must be depth or tsdf, got {self.model_normals!r}")
        self.validate_checks()
        check_positive(self, "fitness_drop_ratio", "huber_delta_m", "disparity_noise_px", "convergence_eps",
                       "recast_translation_m", "recast_rotation_deg", allow_zero=True)
        check_positive(self, "raycast_every", "fuse_every")
        return self


class ModelView:
    """The ray-cast model at one pose as a target pyramid of (vertex, normal, K) numpy arrays.

    ``levels[k]`` holds the normals scaled by the square root of the residual weight of each
    model point (see ``ICPConfig.disparity_noise_px``; unit normals without weighting), used by
    the Gauss-Newton steps; :meth:`unit_level` the same level with unit normals, used for the
    statistics of the failure check (fitness, RMS residual in metres)."""

    def __init__(self, volume, intr: Intrinsics, pose_c2w: np.ndarray, n_levels: int, max_diff_m: float,
                 normals: str = "depth", refine: bool = False, repair: bool = False,
                 noise_depth_m: float = 0.0, raycaster: str = "open3d", hint: np.ndarray | None = None,
                 times: dict | None = None, cast: RaycastResult | None = None):
        t0 = time.perf_counter()
        if cast is not None:            # a saved cast (resume): the same view without the volume
            r = cast
        elif raycaster == "kernel":
            from slam.raycast_kernel import cast_model
            d, w = cast_model(volume, intr, pose_c2w, hint)
            r = RaycastResult(d, None, None, w if noise_depth_m > 0 else None)
        else:
            r = volume.raycast(intr, pose_c2w, with_color=False, with_normal=normals == "tsdf",
                               block_coords=volume.last_block_coords, refine=refine, repair=repair,
                               with_weight=noise_depth_m > 0, times=times)
        self.cast = r
        """The ray cast behind this view (saved in checkpoints to rebuild the view exactly)."""
        t1 = time.perf_counter()
        if times is not None and raycaster == "kernel":
            times["raycast_kernel"] = times.get("raycast_kernel", 0.0) + t1 - t0
        depth = r.depth.copy()
        miss = ~(depth > 0)
        depth[miss] = np.nan
        if normals == "tsdf":
            nrm = r.normal.copy()
            nrm[miss] = np.nan
            nrm[~np.isfinite(nrm).all(-1) | (np.abs(nrm).sum(-1) < 0.5)] = np.nan
        else:
            nrm = smooth_normal_map(depth, intr.K, max_diff_m)
        lvl = Level(depth, intr)
        self.valid = int(np.count_nonzero(~miss))
        weighted = noise_depth_m > 0
        obs = r.weight
        self._unit_normals = [nrm]     # (H, W, 3) float32 unit normals per level (for unit_level)
        self._weighted_levels = weighted
        self.levels = [(lvl.vertex_np(), self._weighted(nrm, lvl.vertex_np(), noise_depth_m, obs), lvl.intr.K)]
        for _ in range(1, n_levels):
            lvl = Level(downsample_depth(lvl.depth, max_diff_m), lvl.intr.scaled(0.5))
            nrm = normal_map(lvl.vertex_np(), max_diff_m)
            if obs is not None:
                obs = downsample_image(obs)
            self._unit_normals.append(nrm)
            self.levels.append((lvl.vertex_np(), self._weighted(nrm, lvl.vertex_np(), noise_depth_m, obs), lvl.intr.K))
        if times is not None:
            times["model_normals"] = times.get("model_normals", 0.0) + time.perf_counter() - t1

    def unit_level(self, k: int):
        """Level k with unit normals (the failure-check statistics read one level per frame; without
        weighting it is ``levels[k]`` itself)."""
        if not self._weighted_levels:
            return self.levels[k]
        vertex, _, K = self.levels[k]
        return vertex, self._unit_normals[k], K

    @staticmethod
    def _weighted(nrm: np.ndarray, vertex: np.ndarray, noise_depth_m: float, obs: np.ndarray | None = None):
        """Normals (H, W, 3) float32 times sqrt(w), w = 1 / (1 + q^2 (1 + 1 / n)),
        q = z^2 cos / z0^2, with z0 = ``noise_depth_m`` (the depth at which the sensor noise
        equals the model noise, see ``ICPConfig.disparity_noise_px``), cos = |n . ray| (depth
        noise lies along the viewing ray, so a point-to-plane residual sees cos times it) and
        n = ``obs``, the observations fused at the model point (a model point seen n times
        carries 1/n of a frame's noise; None = many); unit normals when z0 is 0."""
        if not noise_depth_m > 0:
            return np.ascontiguousarray(nrm, dtype=np.float32)
        x, y, z = vertex[..., 0], vertex[..., 1], vertex[..., 2]
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            r = np.sqrt(x * x + y * y + z * z)
            cos = np.abs(nrm[..., 0] * x + nrm[..., 1] * y + nrm[..., 2] * z) / r
            q = z * z * cos / np.float32(noise_depth_m * noise_depth_m)
            q2 = q * q
            if obs is not None:
                q2 = q2 * (1.0 + 1.0 / np.maximum(obs, np.float32(1.0)))
            scale = (1.0 / np.sqrt(1.0 + q2)).astype(np.float32)
        return np.ascontiguousarray(nrm * scale[..., None], dtype=np.float32)


@register_backend
class ICPBackend(RegistrationBackend):
    """Frame-to-model point-to-plane ICP against the TSDF model (KinectFusion)."""

    name = "icp"
    Config = ICPConfig

    def __init__(self, config: ICPConfig, intrinsics: Intrinsics, tsdf_config, sensor=None):
        super().__init__(config.validate(), intrinsics, tsdf_config, sensor)
        c = self.config
        self._ray_down = int(round(math.log2(1.0 / c.raycast_scale)))
        self._ray_intr = intrinsics
        for _ in range(self._ray_down):
            self._ray_intr = self._ray_intr.scaled(0.5)
        self._n_src_levels = max(c.source_levels) + 1
        self._n_tgt_levels = max(0, max(c.source_levels) - self._ray_down) + 1
        self.last_pose: np.ndarray | None = None
        self.prev_pose: np.ndarray | None = None   # pose of the good frame before last_pose (velocity)
        self.last_t: float | None = None
        self.last_index = -1
        self.consecutive_failures = 0
        self.fitness_history: deque[float] = deque(maxlen=10)
        self.keyframe_index = -1
        self._kf_rgb: np.ndarray | None = None
        self._kf_depth: np.ndarray | None = None
        self._kf_features = None
        self._view: ModelView | None = None
        self._view_key = None
        self.stage_times: dict[str, float] = {}
        """Seconds spent per tracking stage so far (raycast, model_normals, pyramid,
        icp_level<l>, icp_stats): the profile in stats.json and the benchmark."""

    # ---------------------------------------------------------------- helpers
    def depth_noise_per_m(self) -> float:
        """Coefficient k of the sensor's depth noise sigma_z = k z^2 (1/metre), from
        ``disparity_noise_px`` and the camera's sensor block; 0 = no noise model (no sensor
        block, a time-of-flight sensor or no baseline)."""
        sensor = self.sensor
        if (sensor is None or sensor.type not in ("structured_light", "active_stereo")
                or not sensor.baseline_m > 0 or not self.config.disparity_noise_px > 0):
            return 0.0
        return self.config.disparity_noise_px / (self.intrinsics.fx * sensor.baseline_m)

    def _view_is_current(self, volume) -> bool:
        """Whether the last model view may serve the next frame too (``raycast_every``)."""
        if self._view is None or self._view_key is None:
            return False
        n_view, pose_view, count = self._view_key
        if n_view == volume.frames_integrated and np.array_equal(pose_view, self.last_pose):
            return True
        c = self.config
        if count + 1 >= c.raycast_every:
            return False
        D = np.linalg.inv(pose_view) @ self.last_pose
        return (np.linalg.norm(D[:3, 3]) <= c.recast_translation_m
                and math.degrees(rotation_angle_rad(D[:3, :3])) <= c.recast_rotation_deg)

    def _model_view(self, volume) -> ModelView:
        if self._view_is_current(volume):
            n_view, pose_view, count = self._view_key
            if not (n_view == volume.frames_integrated and np.array_equal(pose_view, self.last_pose)):
                self._view_key = (n_view, pose_view, count + 1)
        else:
            c = self.config
            k = self.depth_noise_per_m()
            sigma0 = self.tsdf_config.voxel_size_m / math.sqrt(12.0)
            noise_depth = math.sqrt(sigma0 / k) if k > 0 else 0.0
            kernel = c.raycaster == "kernel" and c.model_normals == "depth" and c.refine_model
            hint = None
            if kernel and self._kf_depth is not None:
                from slam.raycast_kernel import min_pool
                hint = min_pool(self._kf_depth, 2 ** self._ray_down)
            self._view = ModelView(volume, self._ray_intr, self.last_pose, self._n_tgt_levels,
                                   self.tsdf_config.sdf_trunc_m * 2, c.model_normals,
                                   c.refine_model, c.repair_model, noise_depth,
                                   "kernel" if kernel else "open3d", hint, self.stage_times)
            self._view_key = (volume.frames_integrated, self.last_pose.copy(), 0)
        return self._view

    def _solve(self, pyr: Pyramid, view: ModelView, init_rel: np.ndarray) -> SolveResult:
        c = self.config
        src = [pyr[l] for l in c.source_levels]
        tgt = [view.levels[max(0, l - self._ray_down)] for l in c.source_levels]
        times: list[float] = []
        sol = icp_point_to_plane(src, tgt, init_rel, list(c.iterations), list(c.max_correspondence_m),
                                 c.huber_delta_m, c.convergence_eps,
                                 stats_target=view.unit_level(max(0, c.source_levels[-1] - self._ray_down)),
                                 stage_times=times)
        names = [f"icp_level{l}" for l in c.source_levels[:len(times) - 1]] + ["icp_stats"]
        for name, dt in zip(names, times):
            self.stage_times[name] = self.stage_times.get(name, 0.0) + dt
        return sol

    def _check(self, sol: SolveResult, pose: np.ndarray, t: float) -> str:
        return self.config.check_solution(sol, self.last_pose, pose, t - self.last_t, self.fitness_history,
                                          self.config.fitness_drop_ratio)

    def _predict(self) -> np.ndarray:
        return self.config.predict(self.last_pose, self.prev_pose, self.consecutive_failures > 0)

    def _accept(self, frame, pose: np.ndarray, fitness: float | None) -> None:
        self.prev_pose = self.last_pose if self.consecutive_failures == 0 else None
        self.last_pose = pose
        self.last_t = float(frame.timestamp)
        self.last_index = int(frame.index)
        self.consecutive_failures = 0
        if fitness is not None:
            self.fitness_history.append(float(fitness))
        self.keyframe_index = int(frame.index)
        self._kf_rgb = frame.rgb
        self._kf_depth = frame.depth
        self._kf_features = None

    # ---------------------------------------------------------------- tracking
    def track(self, frame, volume) -> TrackResult:
        c = self.config
        depth = frame.depth
        frac = c.valid_depth_fraction(depth, self.tsdf_config.depth_min_m, self.tsdf_config.depth_max_m)
        if frac < c.min_valid_fraction:
            return self._fail(f"too few valid depth pixels ({frac:.1%})")
        if self.last_pose is None:
            pose = np.eye(4)
            self._accept(frame, pose, None)
            return TrackResult(pose, None, None, False, "first frame: defines the world frame")
        t0 = time.perf_counter()
        pyr = Pyramid(depth, self.intrinsics, self._n_src_levels, self.tsdf_config.depth_min_m,
                      self.tsdf_config.depth_max_m, None, self.tsdf_config.sdf_trunc_m * 2)
        for l in set(c.source_levels):
            pyr[l].vertex_np()
        self.stage_times["pyramid"] = self.stage_times.get("pyramid", 0.0) + time.perf_counter() - t0
        view = self._model_view(volume)
        if view.valid < c.min_correspondences:
            return self._fail(f"model view has too few surface pixels ({view.valid})")
        view_pose = self._view_key[1]           # the model view's camera-to-world pose
        T_inv_view = np.linalg.inv(view_pose)
        t = float(frame.timestamp)
        first_reason = ""
        tried = []
        for label, guess in self._guesses(frame):
            if guess is None:
                continue
            if any(np.allclose(guess, g, atol=1e-9) for g in tried):
                continue
            tried.append(guess)
            sol = self._solve(pyr, view, T_inv_view @ guess)
            pose = view_pose @ sol.transformation
            reason = self._check(sol, pose, t)
            if not reason:
                relocalised = bool(first_reason)
                self._accept(frame, pose, sol.fitness)
                return TrackResult(pose, sol.fitness, sol.inlier_rmse, False,
                                   f"re-localised ({label}) after: {first_reason}" if relocalised else "",
                                   relocalised)
            if not first_reason:
                first_reason = reason
                if not c.relocalise:
                    break
        return self._fail(first_reason or "no initial guess")

    def _guesses(self, frame):
        """Initial camera-to-world guesses, in the order they are tried."""
        yield "motion model", self._predict()
        if not self.config.relocalise:
            return
        yield "static", self.last_pose.copy()
        if frame.rgb is not None and self._kf_rgb is not None and self._kf_depth is not None:
            if self._kf_features is None:
                self._kf_features = orb_features(self._kf_rgb, self.config.orb_features)
            g = pnp_guess(self._kf_features, self._kf_depth, orb_features(frame.rgb, self.config.orb_features),
                          self.intrinsics, self.config.pnp_min_inliers)
            # the keyframe is the last tracked frame, whose pose is last_pose
            yield "ORB/PnP", None if g is None else self.last_pose @ g.T_cur_to_kf

    def _fail(self, reason: str) -> TrackResult:
        self.consecutive_failures += 1
        return TrackResult(None, None, None, True, reason)

    # ---------------------------------------------------------------- resume
    def state_dict(self) -> dict:
        """The tracking state for a checkpoint, with the cached model view's ray cast (so that a
        resumed run re-uses the same view as an uninterrupted one, ``raycast_every`` > 1)."""
        return {"view": self._view_state(),
                "last_pose": None if self.last_pose is None else self.last_pose.reshape(-1).tolist(),
                "prev_pose": None if self.prev_pose is None else self.prev_pose.reshape(-1).tolist(),
                "last_t": self.last_t, "last_index": self.last_index,
                "consecutive_failures": self.consecutive_failures,
                "fitness_history": list(self.fitness_history), "keyframe_index": self.keyframe_index}

    def load_state(self, state: dict, reader, volume) -> None:
        def m(v):
            return None if v is None else np.asarray(v, dtype=np.float64).reshape(4, 4)
        self.last_pose = m(state.get("last_pose"))
        self.prev_pose = m(state.get("prev_pose"))
        self.last_t = state.get("last_t")
        self.last_index = int(state.get("last_index", -1))
        self.consecutive_failures = int(state.get("consecutive_failures", 0))
        self.fitness_history = deque(state.get("fitness_history", []), maxlen=10)
        self.keyframe_index = int(state.get("keyframe_index", -1))
        if self.keyframe_index >= 0:
            kf = reader[self.keyframe_index]
            self._kf_rgb, self._kf_depth = kf.rgb, kf.depth
        self._load_view_state(state.get("view"), volume)

    def _view_state(self) -> dict | None:
        if self._view is None or self._view_key is None:
            return None
        import base64

        def enc(a):
            return None if a is None else base64.b64encode(np.ascontiguousarray(a, np.float32).tobytes()).decode()
        n_view, pose_view, count = self._view_key
        r = self._view.cast
        return {"frames_integrated": int(n_view), "pose": pose_view.reshape(-1).tolist(), "count": int(count),
                "shape": list(r.depth.shape), "depth": enc(r.depth), "weight": enc(r.weight), "normal": enc(r.normal)}

    def _load_view_state(self, st: dict | None, volume) -> None:
        self._view, self._view_key = None, None
        if not st:
            return
        import base64
        h, w = st["shape"]

        def dec(a, *tail):
            return None if a is None else np.frombuffer(base64.b64decode(a), np.float32).reshape(h, w, *tail).copy()
        cast = RaycastResult(dec(st["depth"]), None, dec(st["normal"], 3), dec(st["weight"]))
        pose = np.asarray(st["pose"], np.float64).reshape(4, 4)
        c = self.config
        k = self.depth_noise_per_m()
        sigma0 = self.tsdf_config.voxel_size_m / math.sqrt(12.0)
        noise_depth = math.sqrt(sigma0 / k) if k > 0 else 0.0
        self._view = ModelView(volume, self._ray_intr, pose, self._n_tgt_levels, self.tsdf_config.sdf_trunc_m * 2,
                               c.model_normals, c.refine_model, c.repair_model, noise_depth, cast=cast)
        self._view_key = (int(st["frames_integrated"]), pose, int(st["count"]))
