"""Registration backends: the registry, the per-frame result and typed-config helpers.

A backend estimates the camera-to-world pose of every frame of an RGB-D sequence. It is a
small class registered by name (``@register_backend``) in a module of :mod:`slam.backends`
named like the backend (``slam/backends/icp.py`` registers ``icp``); :func:`get_backend`
imports that module on first use, so adding a backend is one new file and nothing is
discovered at import time.

Two kinds exist:

* online backends (``icp``, ``rgbd_odometry``) see one frame at a time through
  :meth:`RegistrationBackend.track`; the pipeline fuses every tracked frame into the shared
  TSDF volume, which frame-to-model backends read back by ray casting;
* offline backends (``colmap``) set ``online = False`` and compute every pose at once in
  :meth:`RegistrationBackend.run_offline`.

Configuration objects are dataclasses with a docstring under every field; the helpers here
turn them into JSON and back (unknown keys and wrong types are :class:`ConfigError`) and read
the field docstrings for ``--help`` texts.
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
import typing
from abc import ABC
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, ClassVar

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.config import config_from_dict, config_replace, config_to_dict, field_docs  # noqa: F401 (re-exported)
from data_tools.errors import ConfigError
from data_tools.geometry import rotation_angle_rad

# --------------------------------------------------------------------------------------------
# per-frame result


@dataclass
class TrackResult:
    """Outcome of registering one frame."""

    pose: np.ndarray | None
    """(4, 4) float64 camera-to-world estimate, metres; None when the frame failed."""
    fitness: float | None = None
    """Fraction of the frame's valid depth pixels with an inlier correspondence, in [0, 1];
    None for the first frame (nothing to register against) or when nothing was computed."""
    inlier_rmse: float | None = None
    """Root mean square geometric residual of the inlier correspondences, metres (point-to-plane
    for ``icp``, depth/point-to-plane for ``rgbd_odometry``, reprojection-free 3-D residual for
    ``colmap``); None when not computed."""
    failed: bool = False
    """True when the frame could not be registered reliably; it is then left out of the
    trajectory and not fused."""
    reason: str = ""
    """Why the frame failed (or how it was recovered), one short line."""
    relocalised: bool = False
    """True when the pose came from re-localisation after a tracking failure."""

    def record(self, timestamp: float, index: int) -> dict:
        """The JSON row of ``stats.json['per_frame']``."""
        return {"timestamp": float(timestamp), "index": int(index),
                "fitness": None if self.fitness is None else float(self.fitness),
                "inlier_rmse": None if self.inlier_rmse is None else float(self.inlier_rmse),
                "failed": bool(self.failed), "reason": self.reason,
                "relocalised": bool(self.relocalised)}


# --------------------------------------------------------------------------------------------
# backend base class and registry


class RegistrationBackend(ABC):
    """Base class of registration backends.

    Subclasses set ``name`` and ``Config`` (a dataclass) and implement :meth:`track` (online)
    or :meth:`run_offline` (``online = False``). Backends keep only what they need between
    frames; :meth:`state_dict` / :meth:`load_state` let the pipeline checkpoint and resume.
    """

    name: ClassVar[str] = ""
    Config: ClassVar[type] = object
    online: ClassVar[bool] = True
    uses_color: ClassVar[bool] = False
    """True when the backend needs the colour images to register (not only to colour the mesh)."""

    def __init__(self, config: Any, intrinsics: Intrinsics, tsdf_config: Any, sensor: Any = None):
        self.config = config
        self.intrinsics = intrinsics
        self.tsdf_config = tsdf_config
        self.sensor = sensor
        """The camera's :class:`data_tools.camera.SensorSpec` (how the depth was measured, from
        the sequence's camera.json), or None."""

    def track(self, frame, volume) -> TrackResult:  # pragma: no cover - offline backends
        """Register ``frame`` (a :class:`data_tools.sequence.Frame`) and return its result.

        ``volume`` is the :class:`slam.tsdf.TSDFVolume` holding every frame fused so far (the
        pipeline fuses the frame after this call when it did not fail).
        """
        raise NotImplementedError(f"backend {self.name!r} is offline: use run_offline")

    def run_offline(self, reader, indices: list[int], progress: bool = True) -> list[TrackResult]:  # pragma: no cover
        """Offline backends: register the frames ``indices`` of ``reader`` at once (one result each)."""
        raise NotImplementedError(f"backend {self.name!r} is online: use track")

    def state_dict(self) -> dict:
        """JSON-serialisable state needed to continue after frame ``k`` (see :meth:`load_state`)."""
        return {}

    def load_state(self, state: dict, reader, volume) -> None:
        """Restore :meth:`state_dict` output; ``reader`` gives access to earlier frames and
        ``volume`` already holds every fused frame up to the checkpoint."""


_REGISTRY: dict[str, type[RegistrationBackend]] = {}


def register_backend(cls: type[RegistrationBackend]) -> type[RegistrationBackend]:
    """Class decorator: make ``cls`` available under ``cls.name``."""
    if not cls.name:
        raise TypeError(f"{cls.__name__} has no backend name")
    if not dataclasses.is_dataclass(cls.Config):
        raise TypeError(f"{cls.__name__}.Config must be a dataclass")
    if inspect.isabstract(cls):
        raise TypeError(f"{cls.__name__} does not implement every abstract method")
    if cls.online and cls.track is RegistrationBackend.track:
        raise TypeError(f"{cls.__name__} is an online backend but does not implement track()")
    if not cls.online and cls.run_offline is RegistrationBackend.run_offline:
        raise TypeError(f"{cls.__name__} is an offline backend but does not implement run_offline()")
    _REGISTRY[cls.name] = cls
    return cls


def backend_names() -> list[str]:
    """Names of all backends (modules of :mod:`slam.backends` not starting with '_')."""
    import slam.backends as pkg
    return sorted(m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_"))


def get_backend(name: str) -> type[RegistrationBackend]:
    """The backend class registered as ``name`` (imports ``slam.backends.<name>`` on first use)."""
    if name not in _REGISTRY:
        known = backend_names()
        if name not in known:
            raise ConfigError(f"unknown registration backend {name!r}; choose one of {', '.join(known)}")
        importlib.import_module(f"slam.backends.{name}")
        if name not in _REGISTRY:
            raise ConfigError(f"module slam.backends.{name} registers no backend named {name!r}")
    return _REGISTRY[name]


# --------------------------------------------------------------------------------------------
# motion plausibility (shared by the online backends' failure checks)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a 3x3 rotation matrix (or the rotation of a 4x4 pose), degrees
    (:func:`data_tools.geometry.rotation_angle_rad`)."""
    return float(np.degrees(rotation_angle_rad(np.asarray(R)[:3, :3])))


def implausible_motion(T_prev: np.ndarray, T_new: np.ndarray, dt_s: float, max_speed_m_s: float,
                       max_angular_speed_deg_s: float, min_dt_s: float = 1.0 / 30.0) -> str:
    """'' when moving from ``T_prev`` to ``T_new`` (camera-to-world) in ``dt_s`` seconds is
    within the speed limits, else a short reason. ``dt_s`` is floored at ``min_dt_s`` so that
    jittery or duplicated timestamps do not make every motion implausible."""
    dt = max(float(dt_s), min_dt_s) if np.isfinite(dt_s) else min_dt_s
    D = np.linalg.inv(T_prev) @ T_new
    trans = float(np.linalg.norm(D[:3, 3]))
    ang = rotation_angle_deg(D[:3, :3])
    if trans > max_speed_m_s * dt:
        return f"implausible motion: {trans:.3f} m in {dt:.3f} s (limit {max_speed_m_s:g} m/s)"
    if ang > max_angular_speed_deg_s * dt:
        return f"implausible motion: {ang:.1f} deg in {dt:.3f} s (limit {max_angular_speed_deg_s:g} deg/s)"
    return ""


# --------------------------------------------------------------------------------------------
# failure check and re-localisation options (shared by the online backends)

MOTION_MODELS = ("constant_velocity", "static")
"""Initial-guess models of the online backends."""


@dataclass
class TrackingCheckConfig:
    """Initial guess, failure check and re-localisation options of an online backend.

    The backends' Config classes derive from this one and re-declare the fields whose default
    differs (``icp`` tracks a denoised model, so it expects more correspondences and a smaller
    residual than frame-to-frame ``rgbd_odometry``); the command-line names
    (``--icp.min_fitness``, ``--rgbd_odometry.min_fitness``, ...) come from the field names.
    """

    motion_model: str = "constant_velocity"
    """Initial guess: ``constant_velocity`` (repeat the last inter-frame motion) or ``static``."""
    min_valid_fraction: float = 0.05
    """Fail when fewer than this fraction of the pixels hold a depth in range (black/dropped frame)."""
    min_correspondences: int = 500
    """Fail when the finest stage has fewer inlier correspondences."""
    min_fitness: float = 0.3
    """Fail when fewer than this fraction of the valid pixels have an inlier correspondence."""
    max_rmse_m: float = 0.03
    """Fail when the RMS point-to-plane residual of the inliers is larger, metres."""
    max_speed_m_s: float = 1.5
    """Fail when the camera would move faster than this, metres per second."""
    max_angular_speed_deg_s: float = 150.0
    """Fail when the camera would turn faster than this, degrees per second."""
    relocalise: bool = True
    """After a failure, try the static and an ORB/PnP initial guess before giving up."""
    orb_features: int = 1500
    """ORB key points per image for the re-localisation guess."""
    pnp_min_inliers: int = 25
    """Fewest PnP RANSAC inliers for a re-localisation guess to be tried."""

    def valid_depth_fraction(self, depth_m: np.ndarray, depth_min_m: float, depth_max_m: float) -> float:
        """Fraction of the pixels of ``depth_m`` (metres) in [depth_min_m, depth_max_m]."""
        ok = np.isfinite(depth_m) & (depth_m >= depth_min_m) & (depth_m <= depth_max_m)
        return float(np.count_nonzero(ok)) / max(depth_m.size, 1)

    def predict(self, last_pose: np.ndarray, prev_pose: np.ndarray | None, after_failure: bool) -> np.ndarray:
        """Initial guess of the next camera-to-world pose by ``motion_model``: the last
        inter-frame motion repeated (``constant_velocity``, when there is one and the last
        frame did not fail) or the last pose (``static``)."""
        if self.motion_model == "constant_velocity" and prev_pose is not None and not after_failure:
            return last_pose @ (np.linalg.inv(prev_pose) @ last_pose)
        return last_pose.copy()

    def check_solution(self, sol, last_pose: np.ndarray, pose: np.ndarray, dt_s: float,
                       fitness_history=(), fitness_drop_ratio: float = 0.0) -> str:
        """'' when the registration ``sol`` (a :class:`SolveResult`-like object with ok,
        message, inliers, fitness and inlier_rmse) giving ``pose`` ``dt_s`` seconds after
        ``last_pose`` passes the checks above, else a short reason. With ``fitness_history``
        (fitness of recent accepted frames, at least 3) a fitness below ``fitness_drop_ratio``
        times their median fails too."""
        if not sol.ok:
            return sol.message
        if sol.inliers < self.min_correspondences:
            return f"too few correspondences ({sol.inliers} < {self.min_correspondences})"
        if sol.fitness < self.min_fitness:
            return f"low fitness {sol.fitness:.3f} < {self.min_fitness:g}"
        if fitness_drop_ratio > 0 and len(fitness_history) >= 3:
            med = float(np.median(fitness_history))
            if sol.fitness < fitness_drop_ratio * med:
                return f"fitness dropped to {sol.fitness:.3f} (recent median {med:.3f})"
        if not (sol.inlier_rmse <= self.max_rmse_m):
            return f"residual {sol.inlier_rmse * 1000:.1f} mm > {self.max_rmse_m * 1000:g} mm"
        return implausible_motion(last_pose, pose, dt_s, self.max_speed_m_s, self.max_angular_speed_deg_s)

    def validate_checks(self) -> None:
        """ConfigError for a bad value of the fields above (called by the subclasses' validate)."""
        name = type(self).__name__
        if self.motion_model not in MOTION_MODELS:
            raise ConfigError(f"{name}.motion_model must be one of {', '.join(MOTION_MODELS)}, "
                              f"got {self.motion_model!r}")
        check_positive(self, "max_rmse_m", "max_speed_m_s", "max_angular_speed_deg_s", "orb_features")
        check_positive(self, "min_valid_fraction", "min_correspondences", "min_fitness",
                       "pnp_min_inliers", allow_zero=True)


# --------------------------------------------------------------------------------------------
# typed configuration helpers


@lru_cache(maxsize=None)
def parse_value(text: str, tp: Any) -> Any:
    """A command-line string converted to JSON data for field type ``tp`` (lists are
    comma-separated)."""
    origin = typing.get_origin(tp)
    if origin in (tuple, list):
        return [t for t in (s.strip() for s in text.split(",")) if t]
    if text.lower() in ("none", "null"):
        return None
    return text


def check_positive(obj: Any, *names: str, allow_zero: bool = False) -> None:
    """ConfigError unless every named field of ``obj`` is a positive (or >= 0) number."""
    for n in names:
        v = getattr(obj, n)
        if not (isinstance(v, (int, float)) and np.isfinite(v) and (v >= 0 if allow_zero else v > 0)):
            raise ConfigError(f"{type(obj).__name__}.{n} must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")


__all__ = ["TrackResult", "RegistrationBackend", "register_backend", "get_backend", "backend_names",
           "TrackingCheckConfig", "MOTION_MODELS", "implausible_motion", "rotation_angle_deg", "field_docs", "config_to_dict",
           "config_from_dict", "config_replace", "parse_value", "check_positive"]
