"""Loop-closure geometry: keyframe point clouds and the dense ICP that verifies a loop candidate.

A keyframe's depth image becomes a point cloud in its camera frame (every pixel in the TSDF's
depth range, voxel-downsampled, normals from 30 neighbours turned towards the camera). A loop
candidate (keyframe j seen again at keyframe i) is verified by point-to-plane ICP of j's cloud
onto i's, coarse to fine, started from the ORB/PnP guess (or the odometry's relative pose), and
accepted only when it passes checks of the kind the tracker applies to every frame: enough
inlier correspondences, fitness (fraction of j's points with a partner) and RMS residual, plus
an *information* check (the correspondences must pin all three translation directions: two
views of one wall would slide along it) and a *consistency* check (the correction the loop asks
of the odometry must be one that drift could have produced over the path walked in between).

Reproducibility: Open3D's ICP sums its normal equations on all threads in a schedule-dependent
order; every call here runs on one Open3D thread (the clouds are a few thousand points, so this
costs milliseconds), as the tracker's kernels do.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.geometry import rotation_angle_rad
from slam.tsdf import o3d_quiet


class one_thread:
    """Context: Open3D limited to one thread inside (the previous limit restored after)."""

    def __enter__(self):
        o3d = o3d_quiet()
        self._before = o3d.utility.get_max_threads()
        o3d.utility.set_max_threads(1)
        return self

    def __exit__(self, *exc):
        o3d_quiet().utility.set_max_threads(self._before)
        return False


def _one_thread(fn, *args, **kwargs):
    o3d = o3d_quiet()
    if o3d.utility.get_max_threads() == 1:     # already inside :class:`one_thread`
        return fn(*args, **kwargs)
    with one_thread():
        return fn(*args, **kwargs)


def keyframe_cloud(depth_m: np.ndarray, intr: Intrinsics, depth_min_m: float, depth_max_m: float,
                   voxel_m: float):
    """Open3D point cloud (camera frame, metres) of an (H, W) depth image: the pixels within
    [depth_min_m, depth_max_m], voxel-downsampled to ``voxel_m``, with unit normals facing the camera."""
    o3d = o3d_quiet()
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w]
    z = np.asarray(depth_m, np.float64)
    ok = np.isfinite(z) & (z >= depth_min_m) & (z <= depth_max_m)
    z, u, v = z[ok], u[ok], v[ok]
    pts = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=1)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc = pc.voxel_down_sample(voxel_m)
    _one_thread(pc.estimate_normals, o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel_m, max_nn=30))
    pc.orient_normals_towards_camera_location(np.zeros(3))
    return pc


@dataclass
class Verification:
    """Outcome of verifying one loop candidate."""

    transformation: np.ndarray
    """(4, 4) transform of points of the later keyframe's camera into the earlier one's."""
    fitness: float
    """Fraction of the later keyframe's points with a partner within the finest distance."""
    inlier_rmse: float
    """RMS point-to-plane residual of the inlier pairs (the tracker's residual), metres."""
    correspondences: int
    """Inlier correspondences at the finest stage."""
    information: np.ndarray
    """(6, 6) information matrix of the transform (Open3D's, from the correspondences)."""
    constraint: float
    """Smallest eigenvalue of the point-to-plane translation information per correspondence
    (:func:`translation_constraint`): 0 for a single plane, 1/3 for three orthogonal planes seen equally."""
    reason: str = ""
    """'' when the loop is accepted, else why it was rejected."""


def information_matrix(src, tgt, T: np.ndarray, max_dist_m: float) -> np.ndarray:
    """Open3D's (6, 6) information of ``T`` aligning ``src`` onto ``tgt`` (one thread)."""
    o3d = o3d_quiet()
    return np.asarray(_one_thread(o3d.pipelines.registration.get_information_matrix_from_point_clouds,
                                  src, tgt, max_dist_m, T))


def translation_constraint(tgt, pairs: np.ndarray) -> float:
    """Smallest eigenvalue of the point-to-plane translation information per correspondence,
    (1/M) sum n n^T over the target normals of the (M, 2) ``pairs`` (see
    :attr:`Verification.constraint`). Open3D's information matrix is point-to-point, whose
    translation block is M times the identity whatever the geometry, so it cannot tell."""
    if len(pairs) == 0:
        return 0.0
    n = np.asarray(tgt.normals)[pairs[:, 1]]
    return float(np.linalg.eigvalsh(n.T @ n / len(n))[0])


def point_to_plane_rmse(src, tgt, T: np.ndarray, pairs: np.ndarray) -> float:
    """RMS of (T p - q) . n_q over the (M, 2) index ``pairs`` (source, target), metres; inf when empty.
    Not Open3D's ``inlier_rmse``, a point-to-point distance that between voxel-downsampled clouds
    is dominated by the voxel spacing."""
    if len(pairs) == 0:
        return float("inf")
    p = np.asarray(src.points)[pairs[:, 0]] @ T[:3, :3].T + T[:3, 3]
    q = np.asarray(tgt.points)[pairs[:, 1]]
    n = np.asarray(tgt.normals)[pairs[:, 1]]
    r = np.einsum("ij,ij->i", p - q, n)
    return float(np.sqrt(np.mean(r * r)))


def verify_loop(src, tgt, init: np.ndarray, max_correspondence_m: tuple[float, ...], iterations: int,
                min_correspondences: int, min_fitness: float, max_rmse_m: float,
                min_constraint: float) -> Verification:
    """Point-to-plane ICP of ``src`` (later keyframe) onto ``tgt`` (earlier) from ``init``, one
    stage per distance in ``max_correspondence_m`` (coarse to fine), then the checks of the module
    docstring except the consistency check (which needs the odometry: see
    :func:`odometry_consistency`)."""
    o3d = o3d_quiet()
    reg = o3d.pipelines.registration
    T = np.asarray(init, np.float64)
    res = None
    for d in max_correspondence_m:
        res = _one_thread(reg.registration_icp, src, tgt, float(d), T,
                          reg.TransformationEstimationPointToPlane(),
                          reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                                     max_iteration=int(iterations)))
        T = np.asarray(res.transformation)
    n = int(len(res.correspondence_set))
    fine = float(max_correspondence_m[-1])
    info = information_matrix(src, tgt, T, fine)
    pairs = np.asarray(res.correspondence_set)
    out = Verification(T, float(res.fitness), point_to_plane_rmse(src, tgt, T, pairs), n, info,
                       translation_constraint(tgt, pairs))
    if n < min_correspondences:
        out.reason = f"too few correspondences ({n} < {min_correspondences})"
    elif out.fitness < min_fitness:
        out.reason = f"low fitness {out.fitness:.3f} < {min_fitness:g}"
    elif not out.inlier_rmse <= max_rmse_m:
        out.reason = f"residual {out.inlier_rmse * 1000:.1f} mm > {max_rmse_m * 1000:g} mm"
    elif out.constraint < min_constraint:
        out.reason = f"degenerate geometry (translation constraint {out.constraint:.3f} < {min_constraint:g})"
    return out


def odometry_consistency(T_loop: np.ndarray, T_odo: np.ndarray, path_m: float, max_drift_m: float,
                         max_drift_per_m: float, max_drift_deg: float, max_drift_deg_per_m: float) -> str:
    """'' when the loop transform ``T_loop`` differs from the odometry's relative pose ``T_odo``
    (both: later camera -> earlier camera) by no more than drift could explain over ``path_m``
    metres of path between the two keyframes: ``max_drift_m + max_drift_per_m * path_m`` metres and
    ``max_drift_deg + max_drift_deg_per_m * path_m`` degrees; else the reason. A place that only
    looks like an earlier one (a second identical box) asks for a jump far larger than that."""
    E = np.linalg.inv(T_odo) @ T_loop
    dt = float(np.linalg.norm(E[:3, 3]))
    da = math.degrees(rotation_angle_rad(E[:3, :3]))
    lim_t = max_drift_m + max_drift_per_m * path_m
    lim_a = max_drift_deg + max_drift_deg_per_m * path_m
    if dt > lim_t:
        return f"inconsistent with odometry: {dt:.3f} m correction > {lim_t:.3f} m after {path_m:.1f} m of path"
    if da > lim_a:
        return f"inconsistent with odometry: {da:.1f} deg correction > {lim_a:.1f} deg after {path_m:.1f} m of path"
    return ""


def refine_loop(depth_src: np.ndarray, depth_tgt: np.ndarray, intr: Intrinsics, T: np.ndarray,
                depth_min_m: float, depth_max_m: float, max_correspondence_m: tuple[float, float] = (0.03, 0.015),
                iterations: tuple[int, int] = (10, 10)) -> tuple[np.ndarray, float, float]:
    """Refine a verified loop transform ``T`` (later camera -> earlier camera) with the tracker's
    projective point-to-plane ICP of the later keyframe's depth onto the earlier one's at quarter
    and half resolution (:func:`slam.backends._pyramid.icp_point_to_plane`, fixed-order sums):
    the keyframe clouds of :func:`verify_loop` are voxel-downsampled to centimetres, which leaves
    the loop edge a few millimetres to centimetres off. Returns (T, fitness, RMS residual in metres)
    at half resolution."""
    from slam.backends._pyramid import Pyramid, icp_point_to_plane, normal_map
    diff = 2 * max(max_correspondence_m)
    src = Pyramid(depth_src, intr, 3, depth_min_m, depth_max_m, None, diff)
    tgt = Pyramid(depth_tgt, intr, 3, depth_min_m, depth_max_m, None, diff)
    levels = (2, 1)
    tg = [(tgt[l].vertex_np(), normal_map(tgt[l].vertex_np(), diff), tgt[l].intr.K) for l in levels]
    sol = icp_point_to_plane([src[l] for l in levels], tg, T, list(iterations), list(max_correspondence_m),
                             eps=1e-5)
    return sol.transformation, sol.fitness, sol.inlier_rmse

