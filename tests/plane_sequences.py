"""Hand-made flat-target captures with a known noise-vs-distance curve (no simulator involved):
the depth of a plane seen by a pinhole camera, computed in closed form, plus Gaussian noise of a
given std per pixel depth sigma(z), seeded, rounded to the PNG's 1/5000 m steps. The capture is
written without poses; ``make_plane_reference`` then fits poses, masks and the plane as it does
for a real capture (``realgap data make-reference --plane``)."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np


def _rot(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def plane_depth(T_c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, w: int, h: int) -> np.ndarray:
    """(h, w) z-depth of the world plane z = 0 seen from camera pose T (OpenCV axes), 0 where the
    ray misses it (points away)."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)      # z component 1: t = depth
    R, c = T_c2w[:3, :3], T_c2w[:3, 3]
    dz = d_cam @ R[2]                                                          # world z of the ray direction
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -c[2] / dz
    return np.where(np.isfinite(t) & (t > 0), t, 0.0).astype(np.float32)


def incidence_rad(T_c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, w: int, h: int) -> np.ndarray:
    """(h, w) angle between each pixel's camera ray and the world plane z = 0's normal, radians."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.arccos(np.clip(np.abs(d @ T_c2w[:3, :3][2]), 0.0, 1.0))


def hand_made_plane_capture(out: Path, distances: Sequence[float], sigma_m: Callable[..., np.ndarray],
                            seed: int = 0, width: int = 160, height: int = 120,
                            tilts_deg: Sequence[float] | None = None) -> dict:
    """Write a flat-target capture (no groundtruth.txt): frame k sees the plane from
    ``distances[k]`` metres, tilted up to 6 degrees, with depth noise N(0, sigma_m(z)^2) per pixel.
    Kinect v1 geometry cropped to ``width`` x ``height``. Returns {"poses": [...], "sigma": fn}.
    ``tilts_deg``: frame k's plane is turned by exactly ``tilts_deg[k]`` about the camera's x axis
    (a known incidence), and the noise is N(0, sigma_m(z, theta)^2) with theta (radians) the angle
    between the pixel's ray and the plane's normal."""
    from data_tools.camera import Camera, Intrinsics, SensorSpec
    from data_tools.scene_spec import Material, SceneSpec
    from data_tools.sequence import Frame, SequenceWriter
    from synth.sensor.testscenes import quad_mesh
    f = 580.0                                   # Kinect v1's focal length: the preset cropped to width x height
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    cam = Camera(Intrinsics(width, height, f, f, cx, cy), 5000.0, SensorSpec("structured_light", 0.075, (0.075, 0, 0)))
    scene = SceneSpec([quad_mesh([0, 0, 0], [6, 0, 0], [0, 6, 0], "target", "target", 2)],
                      {"target": Material(0.6, 0.0)})
    rng = np.random.default_rng(seed)
    poses = []
    with SequenceWriter(out, cam, scene) as w:
        for k, z in enumerate(distances):
            T = np.eye(4)
            axis = rng.normal(size=3) if tilts_deg is None else np.array([1.0, 0.0, 0.0])   # draws in the old order
            tilt = np.radians(rng.uniform(0, 6)) if tilts_deg is None else np.radians(float(tilts_deg[k]))
            T[:3, :3] = _rot(axis, tilt) @ np.diag([1.0, -1.0, -1.0])
            T[:3, 3] = [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), float(z)]
            ideal = plane_depth(T, f, f, cx, cy, width, height)
            sig = (sigma_m(ideal) if tilts_deg is None
                   else sigma_m(ideal, incidence_rad(T, f, f, cx, cy, width, height)))
            noisy = ideal + rng.normal(size=ideal.shape) * sig
            depth = np.where(ideal > 0, np.round(noisy * 5000.0) / 5000.0, 0.0).astype(np.float32)
            w.write(Frame(float(k), depth, None, None, k))
            poses.append(T)
    (out / "groundtruth.txt").unlink(missing_ok=True)
    return {"poses": poses, "sigma": sigma_m}


def plane_reference(root: Path, distances: Sequence[float], sigma_m, seed: int = 0, width: int = 160,
                    height: int = 120, tilts_deg: Sequence[float] | None = None) -> Path:
    """:func:`hand_made_plane_capture` + ``make_plane_reference``: the lab-ready sequence folder."""
    from slam.plane_reference import PlaneReferenceConfig, make_plane_reference
    cap = root / "capture"
    hand_made_plane_capture(cap, distances, sigma_m, seed, width, height, tilts_deg)
    make_plane_reference(cap, root / "ref", PlaneReferenceConfig(), progress=False)
    return root / "ref"
