"""Pose refinement: the CAD model rendered at the estimated pose, aligned to the measured points of
the detection window by Open3D's point-to-plane ICP (thesis section 3.4.3: "the nearest
neighbour's pose is then rendered and aligned to the input scan ... using ICP").

Each round renders the model's visible surface at the current pose (Open3D ray casting of the
object alone, rays of the window's pixels only), unprojects the measured depth of the window
(grown by 10 %), keeps the measured points within one object diameter of the rendered surface's
depth range, and runs point-to-plane ICP (normals of the measured points) with a correspondence
distance that shrinks over the rounds (20 %, 8 %, 3 % of the diameter). The pose is kept only if
the final fitness (fraction of model points with a measured neighbour) is at least the initial
one and the object centre moved by less than half its diameter (``max_shift``): an estimate
that far off was not a local error ICP can fix, and sliding onto the ground plane around the
object raises the fitness while ruining the pose.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics
from recog.objects import RecogObject

__all__ = ["ICPResult", "refine_pose", "ModelRaycaster", "verification_score"]


@dataclass
class ICPResult:
    pose: np.ndarray
    """(4, 4) refined object-to-camera pose."""
    fitness: float
    """Fraction of rendered model points with a measured point within the last distance."""
    rmse_m: float
    """RMS point-to-plane residual of those pairs, metres."""
    accepted: bool
    """False when ICP did not improve the fitness (the initial pose is returned)."""


class ModelRaycaster:
    """Open3D ray casting of one object in its own frame (the BVH is built once)."""

    def __init__(self, obj: RecogObject):
        import open3d as o3d
        m = obj.merged()
        self.scene = o3d.t.geometry.RaycastingScene()
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(m.vertices.astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(m.triangles.astype(np.int32))
        self.scene.add_triangles(mesh)
        self.diameter = obj.diameter_m

    def silhouette(self, T_o2c: np.ndarray, intr: Intrinsics, bbox) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, v, z) of the window's pixels that see the model (z-depth, metres)."""
        import open3d as o3d
        x0, y0, x1, y1 = bbox
        us, vs = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
        us, vs = us.ravel(), vs.ravel()
        d = np.stack([(us - intr.cx) / intr.fx, (vs - intr.cy) / intr.fy, np.ones(us.shape)], -1)
        T_c2o = np.linalg.inv(T_o2c)
        dirs = d @ T_c2o[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T_c2o[:3, 3], dirs.shape), dirs], 1).astype(np.float32)
        t = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        hit = np.isfinite(t)
        return us[hit], vs[hit], t[hit].astype(np.float64)

    def visible_points(self, T_o2c: np.ndarray, intr: Intrinsics, bbox, step: int = 1) -> np.ndarray:
        """(N, 3) camera-frame points of the model surface seen through the window's pixels."""
        import open3d as o3d
        x0, y0, x1, y1 = bbox
        us, vs = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
        d = np.stack([(us - intr.cx) / intr.fx, (vs - intr.cy) / intr.fy, np.ones_like(us, float)], -1).reshape(-1, 3)
        T_c2o = np.linalg.inv(T_o2c)
        dirs = d @ T_c2o[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T_c2o[:3, 3], dirs.shape), dirs], 1).astype(np.float32)
        t = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        hit = np.isfinite(t)
        return d[hit] * t[hit, None]        # d has z = 1: t is the z-depth in the camera frame


def _grow(bbox, frac: float, W: int, H: int):
    x0, y0, x1, y1 = bbox
    gx, gy = int((x1 - x0) * frac), int((y1 - y0) * frac)
    return max(x0 - gx, 0), max(y0 - gy, 0), min(x1 + gx, W), min(y1 + gy, H)


def refine_pose(obj: RecogObject, T_init: np.ndarray, depth_m: np.ndarray, intr: Intrinsics, bbox,
                caster: ModelRaycaster | None = None, rounds=(0.20, 0.08, 0.03), max_shift: float = 0.5) -> ICPResult:
    """Refine the object-to-camera pose ``T_init`` against ``depth_m`` ((H, W) metres) inside ``bbox``."""
    import open3d as o3d
    reg = o3d.pipelines.registration
    caster = caster or ModelRaycaster(obj)
    H, W = depth_m.shape
    box = _grow(bbox, 0.1, W, H)
    x0, y0, x1, y1 = box
    z = np.nan_to_num(np.asarray(depth_m[y0:y1, x0:x1], np.float64), nan=0.0)
    vv, uu = np.nonzero(z > 0)
    zz = z[vv, uu]
    meas = np.stack([(uu + x0 - intr.cx) / intr.fx * zz, (vv + y0 - intr.cy) / intr.fy * zz, zz], 1)
    T = np.asarray(T_init, float).copy()
    diam = caster.diameter
    step = max(1, int(round(np.sqrt((x1 - x0) * (y1 - y0) / 4000.0))))
    model0 = caster.visible_points(T, intr, box, step)
    if len(model0) < 10 or len(meas) < 10:
        return ICPResult(T, 0.0, float("nan"), False)
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(meas))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    tgt.orient_normals_towards_camera_location(np.zeros(3))

    def score(points: np.ndarray, dist: float) -> tuple[float, float]:
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        ev = reg.evaluate_registration(src, tgt, dist, np.eye(4))
        return float(ev.fitness), float(ev.inlier_rmse)

    fit0, _ = score(model0, rounds[-1] * diam)
    for frac in rounds:
        model = caster.visible_points(T, intr, box, step)
        if len(model) < 10:
            break
        zmin, zmax = model[:, 2].min() - diam, model[:, 2].max() + diam
        keep = (meas[:, 2] > zmin) & (meas[:, 2] < zmax)
        if keep.sum() < 10:
            break
        tg = tgt.select_by_index(np.nonzero(keep)[0])
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model))
        r = reg.registration_icp(src, tg, frac * diam, np.eye(4), reg.TransformationEstimationPointToPlane(),
                                 reg.ICPConvergenceCriteria(max_iteration=30))
        if not np.all(np.isfinite(r.transformation)):
            break
        T = r.transformation @ T
    model = caster.visible_points(T, intr, box, step)
    fit, rmse = score(model, rounds[-1] * diam) if len(model) >= 10 else (0.0, float("nan"))
    moved = float(np.linalg.norm(T[:3, 3] - np.asarray(T_init, float)[:3, 3]))
    if fit < fit0 or moved > max_shift * diam:
        return ICPResult(np.asarray(T_init, float).copy(), fit0, float("nan"), False)
    return ICPResult(T, fit, rmse, True)


def verification_score(caster: ModelRaycaster, T_o2c: np.ndarray, depth_m: np.ndarray, intr: Intrinsics,
                       bbox) -> float:
    """How well the model at ``T_o2c`` explains the window: (fraction of the model's rendered pixels
    *that have a measurement* whose measured depth lies within max(5 mm, 1 % of z) of the model) x
    (IoU of the rendered silhouette's bounding box with the detection window). A model too large
    for the object puts pixels on the background (outliers); one too small fits its points but
    not the window (IoU). Holes do not count against a model: sensors lose an object's rim.

    Chosen on a validation set (120 structure-sensor scans of T-LESS obj_01-06, seed 2000, not
    the benchmark's test set), all six objects verified: 95.8 % correct, against 94.2 % when holes
    count as outliers and 90.8 % for precision x recall of the window's points."""
    H, W = depth_m.shape
    box = _grow(bbox, 0.5, W, H)
    u, v, z = caster.silhouette(T_o2c, intr, box)
    if len(u) < 10:
        return 0.0
    meas = np.nan_to_num(np.asarray(depth_m, np.float64)[v, u], nan=0.0)
    has = meas > 0
    if has.sum() < 10:
        return 0.0
    tol = np.maximum(0.005, 0.01 * z)
    precision = float(np.sum(has & (np.abs(meas - z) < tol)) / has.sum())
    x0, y0, x1, y1 = bbox
    a0, b0, a1, b1 = u.min(), v.min(), u.max() + 1, v.max() + 1
    iw, ih = max(0, min(x1, a1) - max(x0, a0)), max(0, min(y1, b1) - max(y0, b0))
    inter = iw * ih
    union = (x1 - x0) * (y1 - y0) + (a1 - a0) * (b1 - b0) - inter
    return precision * (inter / union if union > 0 else 0.0)
