"""Geometry of the neural memory in 3D (thesis 4.3.1 / 4.4.3): ground projection and planar poses.

A ground robot's camera moves on the floor plane at a fixed height, pitch and roll (those of the
first frame). Its *level frame* L has the camera's centre as origin, x to the right and z forward
*in the horizontal plane*, y down along gravity (OpenCV-like, only levelled):
``R_c_L`` (3 x 3) turns level-frame vectors into camera-frame ones.

The *egocentric grid* is q x q cells of ``cell_m`` metres seen from above: the camera sits at the
centre cell (q // 2, q // 2) looking up the grid (towards row 0); a level-frame point (x, y, z)
falls into row ``q//2 - round(z / cell_m)``, column ``q//2 + round(x / cell_m)``. Only the front half
(rows 0 .. q // 2) holds points of an unturned grid: the view field (:func:`view_wedge`) is the wedge
of the camera's horizontal field of view. Seen from above the grid is a right-handed top view (x right, forward
up), so a counter-clockwise grid rotation (``torch.rot90``, kornia's positive angles) is a left turn
of the robot, i.e. a positive yaw about the world's z axis.

*Allocentric* poses (row, col, yaw) are in the first observation's egocentric grid: rows/columns
in cells (row = -forward / cell_m, col = right / cell_m), yaw in radians counter-clockwise.
:func:`planar_relative` / :func:`allocentric_to_world` convert between those and camera-to-world
poses (4 x 4, metres, OpenCV camera axes, world z up).
"""
from __future__ import annotations

import math

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError

__all__ = ["level_rotation", "camera_height_m", "egocentric_cells", "view_wedge", "planar_state",
           "planar_relative", "grid_pose", "allocentric_to_world", "project_max", "downsample_intrinsics"]


def level_rotation(T_w_c: np.ndarray) -> np.ndarray:
    """R_c_L (3, 3) of a camera-to-world pose (world z up): the level frame keeps the camera's heading
    (its optical axis projected on the floor) and drops pitch and roll."""
    R = np.asarray(T_w_c, float)[:3, :3]
    fwd = R[:, 2].copy()
    fwd[2] = 0.0
    n = np.linalg.norm(fwd)
    if n < 1e-6:
        raise RealgapError("the first camera looks straight up or down: no heading for a planar memory")
    zL = fwd / n
    yL = np.array([0.0, 0.0, -1.0])
    xL = np.cross(yL, zL)
    R_w_L = np.stack([xL, yL, zL], axis=1)
    return R.T @ R_w_L


def camera_height_m(T_w_c: np.ndarray, floor_z: float = 0.0) -> float:
    return float(np.asarray(T_w_c)[2, 3] - floor_z)


def planar_state(T_w_c: np.ndarray) -> tuple[float, float, float]:
    """(x, y, yaw) of a camera on the floor plane: world position and the heading of its optical
    axis (radians, counter-clockwise about z from the world x axis)."""
    T = np.asarray(T_w_c, float)
    f = T[:3, 2]
    return float(T[0, 3]), float(T[1, 3]), math.atan2(f[1], f[0])


def planar_relative(T_w_a: np.ndarray, T_w_b: np.ndarray, cell_m: float) -> tuple[float, float, float]:
    """Pose of camera b in camera a's egocentric grid: (row, col) in cells (fractional) and yaw (rad)."""
    xa, ya, ta = planar_state(T_w_a)
    xb, yb, tb = planar_state(T_w_b)
    dx, dy = xb - xa, yb - ya
    fwd = dx * math.cos(ta) + dy * math.sin(ta)
    left = -dx * math.sin(ta) + dy * math.cos(ta)
    dyaw = (tb - ta + math.pi) % (2 * math.pi) - math.pi
    return -fwd / cell_m, -left / cell_m, dyaw


def grid_pose(T_w_a: np.ndarray, T_w_b: np.ndarray, cell_m: float, rotations: int) -> tuple[int, int, int]:
    """:func:`planar_relative` rounded to the memory's grid: (row, col) cells and the heading index
    (0 .. rotations - 1, counter-clockwise)."""
    row, col, yaw = planar_relative(T_w_a, T_w_b, cell_m)
    return int(round(row)), int(round(col)), int(round(yaw / (2 * math.pi / rotations))) % rotations


def allocentric_to_world(T_w_c0: np.ndarray, row: float, col: float, yaw: float, cell_m: float) -> np.ndarray:
    """The camera-to-world pose of an allocentric estimate: the first camera's pose moved by
    (forward, left) = (-row, -col) x cell_m on the floor and turned by ``yaw`` about the world z axis
    (height, pitch and roll stay the first camera's)."""
    T0 = np.asarray(T_w_c0, float)
    _, _, t0 = planar_state(T0)
    fwd, left = -row * cell_m, -col * cell_m
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = Rz @ T0[:3, :3]
    T[0, 3] = T0[0, 3] + fwd * math.cos(t0) - left * math.sin(t0)
    T[1, 3] = T0[1, 3] + fwd * math.sin(t0) + left * math.cos(t0)
    T[2, 3] = T0[2, 3]
    return T


def downsample_intrinsics(intr: Intrinsics, width: int, height: int) -> Intrinsics:
    """Intrinsics of the image resized to width x height (pixel centres at integers)."""
    sx, sy = width / intr.width, height / intr.height
    return Intrinsics(width, height, intr.fx * sx, intr.fy * sy, (intr.cx + 0.5) * sx - 0.5, (intr.cy + 0.5) * sy - 0.5)


def egocentric_cells(depth_m: np.ndarray, intr: Intrinsics, R_c_L: np.ndarray, cell_m: float, q: int,
                     max_range_m: float | None = None, rotations: int = 0) -> np.ndarray:
    """(H * W,) int64 flat egocentric cell (row * q + col) of every pixel of ``depth_m`` (H, W, metres,
    0 = no measurement) with intrinsics ``intr`` of that size; -1 where the pixel has no depth or
    falls outside the grid (or beyond ``max_range_m``).

    ``rotations`` = r > 0: (r, H * W), the cells of the grid turned counter-clockwise by k / r of a
    full turn, k = 0 .. r - 1 (the points are turned, then binned: an exact rotation bank of the
    ground projection, no resampling of the grid)."""
    H, W = depth_m.shape
    if (intr.width, intr.height) != (W, H):
        raise RealgapError(f"depth is {W}x{H} but the intrinsics are {intr.width}x{intr.height}")
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    z = np.asarray(depth_m, np.float64)
    P = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], -1).reshape(-1, 3)
    L = P @ np.asarray(R_c_L, float)             # rows: level-frame points (R_c_L^T p)
    c = q // 2
    valid = (z.reshape(-1) > 0) & np.isfinite(z.reshape(-1)) & (L[:, 2] > 0)
    if max_range_m is not None:
        valid &= np.hypot(L[:, 0], L[:, 2]) <= max_range_m
    out = []
    for k in range(max(rotations, 1)):
        a = 2 * math.pi * k / rotations if rotations else 0.0
        x = L[:, 0] * math.cos(a) - L[:, 2] * math.sin(a)       # counter-clockwise seen from above
        f = L[:, 0] * math.sin(a) + L[:, 2] * math.cos(a)
        row = c - np.rint(f / cell_m).astype(np.int64)
        col = c + np.rint(x / cell_m).astype(np.int64)
        ok = valid & (row >= 0) & (row < q) & (col >= 0) & (col < q)
        out.append(np.where(ok, row * q + col, -1))
    return np.stack(out) if rotations else out[0]


def view_wedge(intr: Intrinsics, R_c_L: np.ndarray, cell_m: float, q: int, max_range_m: float) -> np.ndarray:
    """(q, q) bool: the cells of the egocentric grid inside the camera's horizontal field of view
    (the level-frame bearing of the left and right image borders at the principal row) and within
    ``max_range_m``; the camera's own cell included."""
    c = q // 2
    rows, cols = np.mgrid[0:q, 0:q]
    fwd, right = (c - rows) * cell_m, (cols - c) * cell_m
    # bearings of the image's left/right borders projected onto the floor plane
    rays = np.array([[(0 - intr.cx) / intr.fx, 0.0, 1.0], [(intr.width - 1 - intr.cx) / intr.fx, 0.0, 1.0]])
    L = rays @ np.asarray(R_c_L, float)
    a_lo, a_hi = math.atan2(L[0, 0], L[0, 2]), math.atan2(L[1, 0], L[1, 2])
    bearing = np.arctan2(right, np.maximum(fwd, 1e-9))
    m = (fwd > 0) & (bearing >= a_lo - 1e-9) & (bearing <= a_hi + 1e-9) & (np.hypot(fwd, right) <= max_range_m)
    m[c, c] = True
    return m


def project_max(features, cells, q: int):
    """Ground projection of per-pixel features (B, n, H, W) into (B, n, q, q) egocentric grids by the
    flat cell index of each pixel (B, H * W; -1 = dropped): max-pool per cell, empty cells 0
    (``torch.Tensor.scatter_reduce`` with ``amax``: differentiable, gradient to the maximum)."""
    import torch
    B, n, H, W = features.shape
    f = features.reshape(B, n, H * W)
    idx = cells.reshape(B, 1, H * W)
    ok = idx >= 0
    # dropped pixels go to a spare slot q*q that is cut off afterwards
    safe = torch.where(ok, idx, torch.full_like(idx, q * q)).expand(B, n, H * W)
    out = f.new_zeros(B, n, q * q + 1)
    out = out.scatter_reduce(2, safe, f, reduce="amax", include_self=False)
    return out[:, :, :q * q].reshape(B, n, q, q)
