"""Small analytic scenes for sensor experiments and tests (flat wall, box before a wall, corner).

All are :class:`SceneSpec` objects built in the camera-aligned world frame used by
:func:`camera_pose` (camera at the origin looking along +z, x right, y down), so an ideal
depth value is simply the world z of the surface.
"""
from __future__ import annotations

import numpy as np

from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material, SceneSpec


def camera_pose() -> np.ndarray:
    """Camera-to-world pose of the test scenes: identity (world = camera frame)."""
    return np.eye(4)


def quad_mesh(center, axis_u, axis_v, name: str, material: str = "default", subdiv: int = 1) -> TriMesh:
    """Rectangle centre +- axis_u +- axis_v (metres), split into ``subdiv`` x ``subdiv`` cells."""
    c, a, b = (np.asarray(x, np.float64) for x in (center, axis_u, axis_v))
    n = int(subdiv)
    s = np.linspace(-1.0, 1.0, n + 1)
    uu, vv = np.meshgrid(s, s)
    verts = c + uu.reshape(-1, 1) * a + vv.reshape(-1, 1) * b
    tris = []
    for i in range(n):
        for j in range(n):
            k = i * (n + 1) + j
            tris += [[k, k + 1, k + n + 2], [k, k + n + 2, k + n + 1]]
    return TriMesh(verts, np.asarray(tris), name, material)


def box_mesh(center, size, name: str, material: str = "default") -> TriMesh:
    """Axis-aligned closed box (metres)."""
    c = np.asarray(center, np.float64)
    h = np.asarray(size, np.float64) / 2
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64) * h + c
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return TriMesh(v, np.asarray(f), name, material)


def wall_scene(distance_m: float = 2.0, tilt_deg: float = 0.0, axis: str = "y", size_m: float = 20.0,
               albedo: float = 0.8, specular: float = 0.0) -> SceneSpec:
    """A large flat wall whose centre is ``distance_m`` in front of the camera, rotated by
    ``tilt_deg`` about the camera's ``axis`` ('y': vertical axis, the wall recedes to the
    right for positive tilt; 'x': horizontal axis)."""
    t = np.radians(tilt_deg)
    if axis == "y":
        u = np.array([np.cos(t), 0.0, np.sin(t)])
        v = np.array([0.0, 1.0, 0.0])
    elif axis == "x":
        u = np.array([1.0, 0.0, 0.0])
        v = np.array([0.0, np.cos(t), np.sin(t)])
    else:
        raise ValueError("axis must be 'x' or 'y'")
    wall = quad_mesh([0.0, 0.0, distance_m], u * size_m / 2, v * size_m / 2, "wall", "wall")
    return SceneSpec([wall], {"wall": Material(albedo, specular)})


def box_before_wall_scene(wall_m: float = 2.0, box_m: float = 1.2, box_size_m: float = 0.3,
                          albedo: float = 0.8, box_material: Material | None = None) -> SceneSpec:
    """A box whose front face is at ``box_m - box_size_m / 2`` in front of a fronto wall."""
    wall = quad_mesh([0.0, 0.0, wall_m], [10.0, 0, 0], [0, 10.0, 0], "wall", "wall")
    box = box_mesh([0.0, 0.0, box_m], [box_size_m] * 3, "box", "box")
    return SceneSpec([wall, box], {"wall": Material(albedo, 0.0), "box": box_material or Material(albedo, 0.0)})


def corner_scene(distance_m: float = 2.0, albedo: float = 0.8) -> SceneSpec:
    """A concave 90-degree corner (two walls meeting on the optical axis at ``distance_m``,
    each at 45 degrees to the view direction): the classic multipath configuration."""
    a = 1.0 / np.sqrt(2)
    left = quad_mesh([-2.0 * a, 0, distance_m - 2.0 * a], [2.0 * a, 0, 2.0 * a], [0, 3.0, 0], "left", "wall", 4)
    right = quad_mesh([2.0 * a, 0, distance_m - 2.0 * a], [2.0 * a, 0, -2.0 * a], [0, 3.0, 0], "right", "wall", 4)
    return SceneSpec([left, right], {"wall": Material(albedo, 0.0)})
