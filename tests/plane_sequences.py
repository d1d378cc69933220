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


def twisted_depth(T_c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, w: int, h: int,
                  twist_per_m: float) -> np.ndarray:
    """(h, w) z-depth of the surface z = twist_per_m x y (world metres: the plane z = 0 twisted - a
    board or floor that is not flat over metres, whose far end is turned against its near end) seen
    from camera pose T; 0 where the ray misses the plane. The height is taken at the ray's
    intersection with the plane: t' = t + height / (ray's world z per unit depth), exact to first
    order in the surface's slope (a few 1e-2 here)."""
    t = plane_depth(T_c2w, fx, fy, cx, cy, w, h).astype(np.float64)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    R, c = T_c2w[:3, :3], T_c2w[:3, 3]
    dw = d_cam @ R.T                                                           # world ray per unit depth
    x, y = c[0] + t * dw[..., 0], c[1] + t * dw[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = t + twist_per_m * x * y / dw[..., 2]
    return np.where((t > 0) & (out > 0), out, 0.0).astype(np.float32)


def hand_made_plane_capture(out: Path, distances: Sequence[float], sigma_m: Callable[..., np.ndarray],
                            seed: int = 0, width: int = 160, height: int = 120,
                            tilts_deg: Sequence[float] | None = None, twist_per_m: float = 0.0,
                            focal_px: float = 580.0) -> dict:
    """Write a flat-target capture (no groundtruth.txt): frame k sees the plane from
    ``distances[k]`` metres, tilted up to 6 degrees, with depth noise N(0, sigma_m(z)^2) per pixel.
    Kinect v1 geometry cropped to ``width`` x ``height``. Returns {"poses": [...], "sigma": fn}.
    ``tilts_deg``: frame k's plane is turned by exactly ``tilts_deg[k]`` about the camera's x axis
    (a known incidence), and the noise is N(0, sigma_m(z, theta)^2) with theta (radians) the angle
    between the pixel's ray and the plane's normal. ``twist_per_m`` != 0: the target is not flat but
    twisted (:func:`twisted_depth`, 1/m): the reference plane fitted to it misses the far, grazing part
    by more than the noise there - a low-frequency error, not sensor noise - while the noise is drawn,
    as without it, from the flat plane's depth and incidence. The noise and the tilts draw the same
    numbers with or without the twist. ``focal_px``: the focal length (580: Kinect v1's, the image a
    crop of its centre; 145 at 160 px: its whole 57 deg field of view, downscaled)."""
    from data_tools.camera import Camera, Intrinsics, SensorSpec
    from data_tools.scene_spec import Material, SceneSpec
    from data_tools.sequence import Frame, SequenceWriter
    from synth.sensor.testscenes import quad_mesh
    f = float(focal_px)                         # 580: Kinect v1's focal length, the preset cropped to width x height
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
            if twist_per_m:
                ideal = np.where(ideal > 0, twisted_depth(T, f, f, cx, cy, width, height, twist_per_m), 0.0)
            noisy = ideal + rng.normal(size=ideal.shape) * sig
            depth = np.where(ideal > 0, np.round(noisy * 5000.0) / 5000.0, 0.0).astype(np.float32)
            w.write(Frame(float(k), depth, None, None, k))
            poses.append(T)
    (out / "groundtruth.txt").unlink(missing_ok=True)
    return {"poses": poses, "sigma": sigma_m}


def plane_reference(root: Path, distances: Sequence[float], sigma_m, seed: int = 0, width: int = 160,
                    height: int = 120, tilts_deg: Sequence[float] | None = None, twist_per_m: float = 0.0,
                    focal_px: float = 580.0) -> Path:
    """:func:`hand_made_plane_capture` + ``make_plane_reference``: the lab-ready sequence folder."""
    from slam.plane_reference import PlaneReferenceConfig, make_plane_reference
    cap = root / "capture"
    hand_made_plane_capture(cap, distances, sigma_m, seed, width, height, tilts_deg, twist_per_m, focal_px)
    make_plane_reference(cap, root / "ref", PlaneReferenceConfig(), progress=False)
    return root / "ref"


def _law_nguyen(z, theta):
    """1.2 mm + 1.9 mm/m^2 (z - 0.4 m)^2 + 0.3 mm theta^2 / (pi/2 - theta)^2 / sqrt(z / 1 m)."""
    from synth.sensor.effects.axial_noise import incidence_factor
    return 0.0012 + 0.0019 * (z - 0.4) ** 2 + 0.0003 * incidence_factor(theta) / np.sqrt(np.maximum(z, 0.05))


def _law_disparity(z, theta):
    """1.0 mm + 1.6 mm/m^2 z^2 + 0.05 mm theta^2 / (pi/2 - theta)^2 (z / 1 m)^2."""
    from synth.sensor.effects.axial_noise import incidence_factor
    return 0.0010 + 0.0016 * z ** 2 + 0.00005 * incidence_factor(theta) * z ** 2


LAWS = {"nguyen": _law_nguyen, "disparity": _law_disparity}
"""Known noise laws sigma(z m, theta rad) -> m of the synthetic plane sequences (docs/sensor_lab.md)."""


def main(argv=None) -> int:
    """Write a synthetic planar reference for ``benchmarks/bench_plane_noise.py``: ``--frames`` frames
    turned by 0, 50, 65, 72, 78 deg in turn about the camera's x axis, at 0.8-2.9 m along the axis
    (times cos(tilt) from the plane), noise law ``--law``, optionally twisted (``--twist``, 1/m)."""
    import argparse
    ap = argparse.ArgumentParser(description=main.__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--law", choices=sorted(LAWS), default="nguyen")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--twist", type=float, default=0.0, help="twist of the target, 1/m (twisted_depth)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--focal", type=float, default=580.0, help="focal length, px (hand_made_plane_capture)")
    a = ap.parse_args(argv)
    tilts = np.resize([0, 50, 65, 72, 78], a.frames)
    dist = np.linspace(0.8, 2.9, a.frames) * np.cos(np.radians(tilts))
    print(plane_reference(a.out, dist, LAWS[a.law], a.seed, a.width, a.height, tilts, a.twist, a.focal))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
