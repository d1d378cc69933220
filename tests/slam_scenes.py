"""Small synthetic RGB-D fixtures for the slam tests (rendered with Open3D's RaycastingScene).

The scene is a textured room corner (floor, two walls) with a box and a sphere: enough
non-parallel surfaces to constrain all six degrees of freedom of a camera, and a random
per-vertex colour texture for the photometric terms. Everything is seeded.
"""
from __future__ import annotations

import numpy as np

from data_tools.camera import Camera, Intrinsics
from data_tools.geometry import look_at
from data_tools.mesh import TriMesh
from data_tools.sequence import Frame, SequenceWriter
from slam.render import render_mesh

INTR = Intrinsics(320, 240, 280.0, 280.0, 159.5, 119.5)
"""Small test camera, 320 x 240 (about 60 x 47 degrees field of view)."""


def _grid(origin, u, v, nu, nv, rng) -> TriMesh:
    origin, u, v = (np.asarray(a, float) for a in (origin, u, v))
    i, j = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1), indexing="ij")
    verts = origin + (i[..., None] / nu) * u + (j[..., None] / nv) * v
    idx = (i * (nv + 1) + j)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    colors = rng.uniform(0.1, 0.9, (len(verts.reshape(-1, 3)), 3))
    return TriMesh(verts.reshape(-1, 3), tris, vertex_colors=colors)


def _concat(meshes: list[TriMesh]) -> TriMesh:
    v, f, c, off = [], [], [], 0
    for m in meshes:
        v.append(m.vertices)
        f.append(m.triangles + off)
        c.append(m.vertex_colors)
        off += len(m.vertices)
    return TriMesh(np.concatenate(v), np.concatenate(f), name="scene", vertex_colors=np.concatenate(c))


def _o3d_mesh(m, rng) -> TriMesh:
    v = np.asarray(m.vertices)
    return TriMesh(v, np.asarray(m.triangles), vertex_colors=rng.uniform(0.1, 0.9, (len(v), 3)))


def room_scene(seed: int = 0) -> TriMesh:
    """Floor (z = 0), walls at y = 1.5 and x = -1.5, a box and a sphere; metres."""
    import open3d as o3d
    rng = np.random.default_rng(seed)
    parts = [
        _grid((-1.5, -1.5, 0), (3, 0, 0), (0, 3, 0), 40, 40, rng),            # floor
        _grid((-1.5, 1.5, 0), (3, 0, 0), (0, 0, 2), 40, 27, rng),             # back wall
        _grid((-1.5, -1.5, 0), (0, 3, 0), (0, 0, 2), 40, 27, rng),            # side wall
    ]
    box = o3d.geometry.TriangleMesh.create_box(0.4, 0.5, 0.45)
    box = box.subdivide_midpoint(3)
    box.translate((0.3, 0.4, 0.0))
    sph = o3d.geometry.TriangleMesh.create_sphere(0.3, 30)
    sph.translate((-0.5, 0.3, 0.3))
    parts += [_o3d_mesh(box, rng), _o3d_mesh(sph, rng)]
    return _concat(parts)


def camera_path(n: int, step_m: float = 0.02, step_deg: float = 1.0) -> list[np.ndarray]:
    """``n`` camera-to-world poses moving sideways and turning slowly, looking into the corner."""
    poses = []
    for k in range(n):
        eye = np.array([1.2 - k * step_m, -1.3 + 0.3 * k * step_m + 0.5 * step_m * np.sin(0.7 * k),
                        1.3 + 0.2 * k * step_m + 0.5 * step_m * (1 - np.cos(0.7 * k))])
        target = np.array([-0.3, 0.5, 0.35])
        T = look_at(eye, target)
        a = np.radians(step_deg * k)
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        T[:3, :3] = T[:3, :3] @ Rz  # roll about the optical axis as well
        poses.append(T)
    return poses


def render_frames(scene: TriMesh, poses, intr: Intrinsics = INTR, t0: float = 100.0, fps: float = 30.0
                  ) -> list[Frame]:
    frames = []
    for k, T in enumerate(poses):
        v = render_mesh(scene, intr, T)
        frames.append(Frame(t0 + k / fps, v.depth.copy(), v.rgb.copy(), T.copy(), k))
    return frames


def write_sequence(path, frames: list[Frame], intr: Intrinsics = INTR, depth_scale: float = 5000.0):
    """Write frames as a TUM-layout sequence (with camera.json and ground truth)."""
    with SequenceWriter(path, Camera(intr, depth_scale)) as w:
        for f in frames:
            w.write(f)
    return path
