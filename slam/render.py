"""Novel views of a reconstruction: colour and depth of the fused model from any pose.

Two sources give the same picture: the mesh of a RUN folder (``mesh.ply``, ray cast with
Open3D's ``RaycastingScene``, colours interpolated from the vertex colours), or the TSDF
volume itself (``volume.npz`` when the run saved it, ray cast by the ``VoxelBlockGrid``).
Pixels whose ray does not meet the model (never observed) get :data:`UNOBSERVED_RGB`
(magenta) and depth 0.

Rays go through pixel centres at integer coordinates with the pinhole intrinsics; the depth is
z-depth in metres (the ray direction has unit z in the camera frame, so the hit distance along
it is the z-depth).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import FormatError, RealgapError
from data_tools.geometry import is_rigid, pixel_rays, pose_from_tum
from data_tools.mesh import TriMesh

UNOBSERVED_RGB = (255, 0, 255)
"""Colour of pixels that see no reconstructed surface (magenta)."""


@dataclass
class RenderedView:
    """A rendered view of the model."""

    rgb: np.ndarray
    """(H, W, 3) uint8 colour; :data:`UNOBSERVED_RGB` where nothing was hit."""
    depth: np.ndarray
    """(H, W) float32 z-depth, metres; 0 where nothing was hit."""
    pose: np.ndarray
    """(4, 4) camera-to-world pose of the view."""
    intrinsics: Intrinsics

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool, True where the model was hit."""
        return self.depth > 0

    @property
    def coverage(self) -> float:
        """Fraction of pixels that see the model."""
        return float(self.mask.mean())


def camera_rays(intr: Intrinsics, pose_c2w: np.ndarray) -> np.ndarray:
    """(H, W, 6) float32 rays (origin, direction) in the world frame; directions have unit
    z-component in the camera frame."""
    T = np.asarray(pose_c2w, dtype=np.float64)
    d = pixel_rays(intr, unit=False) @ T[:3, :3].T
    o = np.broadcast_to(T[:3, 3], d.shape)
    return np.concatenate([o, d], -1).astype(np.float32)


def _finish(depth: np.ndarray, rgb_f: np.ndarray | None, pose, intr) -> RenderedView:
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    hit = depth > 0
    if rgb_f is None:
        shade = np.full(depth.shape + (3,), 200, np.uint8)
    else:
        shade = (np.clip(rgb_f, 0, 1) * 255 + 0.5).astype(np.uint8)
    rgb = np.empty(depth.shape + (3,), np.uint8)
    rgb[:] = UNOBSERVED_RGB
    rgb[hit] = shade[hit]
    return RenderedView(rgb, depth, np.asarray(pose, np.float64), intr)


def render_mesh(mesh: TriMesh, intr: Intrinsics, pose_c2w: np.ndarray,
                depth_max_m: float = float("inf")) -> RenderedView:
    """Ray cast ``mesh`` (world frame) from ``pose_c2w``; colours from its vertex colours
    (grey without), interpolated barycentrically."""
    import open3d as o3d
    if len(mesh.triangles) == 0:
        raise RealgapError("cannot render an empty mesh")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    ans = scene.cast_rays(o3d.core.Tensor(camera_rays(intr, pose_c2w)))
    t = ans["t_hit"].numpy()
    t = np.where(np.isfinite(t) & (t <= depth_max_m), t, 0.0)
    rgb_f = None
    if mesh.vertex_colors is not None:
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy()
        hit = t > 0
        rgb_f = np.zeros(t.shape + (3,), np.float64)
        tri = mesh.triangles[prim[hit]]
        c = np.asarray(mesh.vertex_colors, np.float64)
        a, b = uv[hit, 0:1], uv[hit, 1:2]
        rgb_f[hit] = (1 - a - b) * c[tri[:, 0]] + a * c[tri[:, 1]] + b * c[tri[:, 2]]
    return _finish(t, rgb_f, pose_c2w, intr)


def render_volume(volume, intr: Intrinsics, pose_c2w: np.ndarray,
                  depth_max_m: float | None = None) -> RenderedView:
    """Ray cast a :class:`slam.tsdf.TSDFVolume` from ``pose_c2w``."""
    r = volume.raycast(intr, pose_c2w, with_color=True, with_normal=False, depth_max_m=depth_max_m)
    return _finish(r.depth, r.color, pose_c2w, intr)


def parse_pose(text: str) -> np.ndarray:
    """Camera-to-world 4x4 from 'tx ty tz qx qy qz qw' (TUM order; commas allowed)."""
    parts = text.replace(",", " ").split()
    try:
        vals = np.array([float(p) for p in parts])
    except ValueError:
        raise RealgapError(f"pose {text!r}: expected 7 numbers 'tx ty tz qx qy qz qw'") from None
    if len(vals) != 7 or not np.all(np.isfinite(vals)):
        raise RealgapError(f"pose {text!r}: expected 7 finite numbers 'tx ty tz qx qy qz qw', got {len(vals)}")
    n = np.linalg.norm(vals[3:])
    if not 0.5 < n < 1.5:
        raise RealgapError(f"pose {text!r}: quaternion norm {n:.3f} is far from 1")
    T = pose_from_tum(vals)
    if not is_rigid(T, 1e-6):
        raise RealgapError(f"pose {text!r}: not a rigid transform")
    return T


def render_run(run_dir: str | os.PathLike, pose_c2w: np.ndarray, scale: float = 1.0,
               source: str = "auto", hallucinate: bool = False) -> RenderedView:
    """Render a RUN folder from ``pose_c2w`` with the run's camera (``scale`` resizes it).

    ``source``: ``mesh`` (RUN/mesh.ply), ``volume`` (RUN/volume.npz), ``neural`` (the view the run's
    neural memory recalls, :func:`slam.neural.inference.recall_view`, resized from the decoder's small image;
    ``hallucinate``: after its hallucination module filled the unobserved cells) or ``auto`` (neural for
    a run of the neural backend, else the volume when saved, else the mesh).
    """
    from data_tools.camera import read_camera_json
    from data_tools.mesh import load_mesh
    run = Path(run_dir)
    if not (run / "camera.json").is_file():
        raise FormatError(run, "not a SLAM run folder (camera.json missing)")
    intr = read_camera_json(run / "camera.json").intrinsics
    if scale != 1.0:
        if not (0 < scale <= 8):
            raise RealgapError(f"scale must be in (0, 8], got {scale}")
        intr = intr.scaled(scale)
    if source not in ("auto", "mesh", "volume", "neural"):
        raise RealgapError(f"unknown render source {source!r}; choose auto, mesh, volume or neural")
    neural = source == "neural" or (source == "auto" and (run / "memory" / "memory.json").is_file())
    if hallucinate and not neural:
        raise RealgapError(f"{run_dir}: --hallucinate needs a run of the neural backend (it has no memory/)")
    if neural:
        from slam.neural.inference import recall_view
        rgb, depth = recall_view(run, pose_c2w, hallucinate, size=(intr.width, intr.height))
        return RenderedView(rgb, depth, np.asarray(pose_c2w, float), intr)
    use_volume = source == "volume" or (source == "auto" and (run / "volume.npz").is_file())
    if use_volume:
        from slam.tsdf import TSDFVolume
        return render_volume(TSDFVolume.load(run / "volume.npz"), intr, pose_c2w)
    if not (run / "mesh.ply").is_file():
        raise FormatError(run, "run has no mesh.ply (unfinished run, or nothing was fused)")
    return render_mesh(load_mesh(run / "mesh.ply", validate=False), intr, pose_c2w)


def run_pose(run_dir: str | os.PathLike, pose: str | None = None, frame: int = 0) -> np.ndarray:
    """The 4x4 camera-to-world pose to render a RUN from: ``pose`` parsed (:func:`parse_pose`), or
    pose number ``frame`` of RUN/trajectory.txt (negative numbers count from the end)."""
    from data_tools.trajectory import read_tum
    if pose is not None:
        return parse_pose(pose)
    traj = read_tum(Path(run_dir) / "trajectory.txt")
    if not -len(traj) <= frame < len(traj):
        raise RealgapError(f"--frame {frame}: the trajectory has {len(traj)} poses")
    return traj.poses[frame]


def render_run_to_png(run_dir: str | os.PathLike, png: str | os.PathLike, pose: str | None = None, frame: int = 0,
                      scale: float = 1.0, source: str = "auto",
                      hallucinate: bool = False) -> tuple[RenderedView, dict[str, str], float]:
    """``slam render``: render RUN from ``pose`` or trajectory pose ``frame`` (:func:`run_pose`)
    and save it (:func:`save_view`, depth in the run camera's depth scale). Returns (view,
    written paths, depth scale). ``source`` and ``hallucinate``: see :func:`render_run`."""
    from data_tools.camera import read_camera_json
    view = render_run(run_dir, run_pose(run_dir, pose, frame), scale=scale, source=source, hallucinate=hallucinate)
    depth_scale = read_camera_json(Path(run_dir) / "camera.json").depth_scale
    return view, save_view(view, png, depth_scale), depth_scale


def save_view(view: RenderedView, png: str | os.PathLike, depth_scale: float = 1000.0) -> dict[str, str]:
    """Write PNG (colour), PNG stem + '_depth.png' (16-bit, metres x depth_scale, 0 = unobserved)
    and stem + '.json' (pose, intrinsics, coverage). Returns the paths."""
    import cv2
    from data_tools.sequence import write_depth_png
    png = Path(png)
    if png.suffix.lower() != ".png":
        raise RealgapError(f"{png}: output must be a .png file")
    png.parent.mkdir(parents=True, exist_ok=True)
    depth_path = png.with_name(png.stem + "_depth.png")
    meta_path = png.with_suffix(".json")
    if not cv2.imwrite(str(png), np.ascontiguousarray(view.rgb[:, :, ::-1])):
        raise RealgapError(f"{png}: cannot write image")
    write_depth_png(depth_path, view.depth, depth_scale)
    i = view.intrinsics
    meta = {"pose_c2w": view.pose.tolist(), "coverage": view.coverage, "depth_scale": depth_scale,
            "unobserved_rgb": list(UNOBSERVED_RGB), "colour": png.name, "depth": depth_path.name,
            "intrinsics": {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy}}
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    return {"colour": str(png), "depth": str(depth_path), "meta": str(meta_path)}
