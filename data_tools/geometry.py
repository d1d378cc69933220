"""SE(3) pose helpers and pinhole (un)projection.

Poses are 4x4 float64 homogeneous matrices, camera-to-world unless a name says otherwise.
Quaternions are (qx, qy, qz, qw) as in the TUM format.
"""
from __future__ import annotations

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError

UNIT_QUAT_TOL = 1e-3
"""Largest allowed | |q| - 1 | for a quaternion read from a file (TUM files carry ~1e-4 rounding)."""


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4) in x y z w order (normalised first)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) x y z w with w >= 0 from rotation matrices (..., 3, 3)."""
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    out = np.empty((m.shape[0], 4))
    for i, r in enumerate(m):
        t = np.trace(r)
        if t > 0:
            s = np.sqrt(t + 1.0) * 2
            w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
        elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
            s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
            w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
        elif r[1, 1] > r[2, 2]:
            s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
            w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s
        else:
            s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
            w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s
        q = np.array([x, y, z, w])
        q /= np.linalg.norm(q)
        out[i] = q if q[3] >= 0 else -q
    return out.reshape(R.shape[:-2] + (4,))


def pose_from_tum(txyz_qxyzw: np.ndarray) -> np.ndarray:
    """4x4 poses (..., 4, 4) from TUM rows (..., 7) = tx ty tz qx qy qz qw."""
    v = np.asarray(txyz_qxyzw, dtype=np.float64)
    T = np.zeros(v.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_to_matrix(v[..., 3:7])
    T[..., :3, 3] = v[..., :3]
    T[..., 3, 3] = 1.0
    return T


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """TUM rows (..., 7) = tx ty tz qx qy qz qw from 4x4 poses (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], matrix_to_quat(T[..., :3, :3])], axis=-1)


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4) without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def is_rigid(T: np.ndarray, tol: float = 1e-6) -> bool:
    """True when T is a finite 4x4 rigid transform (orthonormal rotation, det +1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol
            and np.allclose(T[3], [0, 0, 0, 1]))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: z forward, y down) at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise RealgapError("look_at: eye and target coincide")
    z /= n
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def pixel_grid(intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) pixel coordinates, each (H, W) float64, pixel centres at integers."""
    return np.meshgrid(np.arange(intr.width, dtype=np.float64),
                       np.arange(intr.height, dtype=np.float64))


def pixel_rays(intr: Intrinsics, idx: np.ndarray | None = None, unit: bool = True) -> np.ndarray:
    """Viewing rays of pixels in the camera frame (OpenCV axes), float64: (H, W, 3) for the whole
    image or (N, 3) for flat pixel indices ``idx`` (v * W + u). Pixel centres at integers (see
    ../shared/FORMATS.md), no distortion. ``unit``: unit-length rays; else z = 1 (the ray to
    ``depth`` z is ``ray * z``)."""
    if idx is None:
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    else:
        v, u = np.divmod(np.asarray(idx, dtype=np.int64), intr.width)
    r = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(np.shape(u))], axis=-1)
    return r / np.linalg.norm(r, axis=-1, keepdims=True) if unit else r


def rotation_angle_rad(R: np.ndarray) -> np.ndarray:
    """Rotation angles (...) in radians, in [0, pi], of rotation matrices (..., 3, 3).

    atan2 of the sine (from the skew part) and cosine (from the trace): accurate near 0 and pi,
    unlike arccos of the trace alone. Equals evo's ``so3_log_angle`` (norm of the rotation vector).
    The angle between two rotations R_a, R_b is ``rotation_angle_rad(R_b @ R_a.T)``.
    """
    R = np.asarray(R, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sn = np.linalg.norm(v, axis=-1) / 2.0
    return np.arctan2(sn, c)


def unproject(depth_m: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame points (H, W, 3) metres from a z-depth image (H, W) metres (0 stays 0).

    Distortion is ignored: depth images of ``realgap`` are undistorted unless a sensor
    effect says otherwise.
    """
    depth_m = np.asarray(depth_m, dtype=np.float64)
    if depth_m.shape != intr.shape:
        raise RealgapError(f"depth shape {depth_m.shape} does not match intrinsics {intr.shape}")
    u, v = pixel_grid(intr)
    x = (u - intr.cx) / intr.fx * depth_m
    y = (v - intr.cy) / intr.fy * depth_m
    return np.stack([x, y, depth_m], axis=-1)


def project(points_cam: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (..., 2) and z-depth (...) of camera-frame points (..., 3) metres."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p[..., 0] / z + intr.cx
        v = intr.fy * p[..., 1] / z + intr.cy
    return np.stack([u, v], axis=-1), z


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points (..., 3)."""
    T = np.asarray(T, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]
