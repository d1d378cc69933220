"""Image pyramids and projective (dense, image-space) registration loops shared by backends.

Both online backends register a *source* frame to a *target* view by projective data
association: every valid source pixel is moved by the current estimate of the
source-to-target transform, projected into the target image with the target intrinsics, and
paired with the target pixel it lands on (rounded to the nearest pixel, pixel centres at
integer coordinates). A kernel linearises one Gauss-Newton step (point-to-plane:
:mod:`slam.backends._p2p_kernel`; hybrid RGB-D: Open3D's ``compute_odometry_result_hybrid``); the coarse-to-fine loop, the pyramids (built once per frame and reused
when a frame becomes the next target), convergence and the statistics are ours.

Pyramid level 0 is the full image; level l is downsampled by 2^l with a 2x2 block mean over
the valid depths that lie within ``max_diff_m`` of the block's nearest depth (so that
foreground and background are not averaged into flying pixels). Intrinsics follow with
:meth:`Intrinsics.scaled` (2x2 means move the sample centre by half a pixel).

Reproducibility: Open3D's odometry kernels sum the normal equations over pixels on all its
threads, in an order set by the thread schedule, so a registration differs in the last bits
from run to run. The point-to-plane ICP here (:func:`icp_point_to_plane`, the ``icp``
backend) uses :mod:`slam.backends._p2p_kernel` instead, whose sums have a fixed order: the same
bits on any number of threads, both cores used. The RGB-D odometry kernels of
:func:`rgbd_hybrid` (the ``rgbd_odometry`` backend) still run on one Open3D thread
(:func:`_odometry_kernels`). TSDF integration and ray casting write independent voxels and
pixels and are deterministic on any number of threads.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.geometry import rotation_angle_rad
from slam.tsdf import o3d_quiet


class _OneThreadKernels:
    """``open3d.t.pipelines.odometry`` whose functions run with Open3D limited to one thread (the
    previous limit is restored after each call): bit-reproducible sums, see the module docstring."""

    def __getattr__(self, name: str):
        o3d = o3d_quiet()
        fn = getattr(o3d.t.pipelines.odometry, name)

        def one_thread(*args, **kwargs):
            before = o3d.utility.get_max_threads()
            o3d.utility.set_max_threads(1)
            try:
                return fn(*args, **kwargs)
            finally:
                o3d.utility.set_max_threads(before)
        return one_thread


def _odometry_kernels() -> _OneThreadKernels:
    """Open3D's odometry kernels, each call on one thread."""
    return _OneThreadKernels()


def downsample_depth(depth: np.ndarray, max_diff_m: float) -> np.ndarray:
    """(H, W) float32 metres with NaN = invalid -> (H//2, W//2): mean of the valid pixels of
    each 2x2 block that lie within ``max_diff_m`` of the block's smallest valid depth."""
    h, w = depth.shape
    h2, w2 = h // 2 * 2, w // 2 * 2
    quad = (depth[0:h2:2, 0:w2:2], depth[0:h2:2, 1:w2:2], depth[1:h2:2, 0:w2:2], depth[1:h2:2, 1:w2:2])
    dmin = np.fmin(np.fmin(quad[0], quad[1]), np.fmin(quad[2], quad[3]))   # NaN where all are NaN
    lim = dmin + np.float32(max_diff_m)
    total = np.zeros(dmin.shape, np.float32)
    count = np.zeros(dmin.shape, np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        for x in quad:
            ok = x <= lim                                   # False for NaN
            total += np.where(ok, x, np.float32(0.0))
            count += ok
        out = total / count                                 # 0 / 0 = NaN where nothing is valid
    return out.astype(np.float32, copy=False)


def downsample_image(img: np.ndarray) -> np.ndarray:
    """2x2 block mean of a float image (H, W) -> (H//2, W//2)."""
    h, w = img.shape[:2]
    h2, w2 = h // 2 * 2, w // 2 * 2
    x = np.asarray(img, np.float32)
    return ((x[0:h2:2, 0:w2:2] + x[0:h2:2, 1:w2:2]) + (x[1:h2:2, 0:w2:2] + x[1:h2:2, 1:w2:2])) * np.float32(0.25)


def vertex_map(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (H, W, 3) float32 from z-depth (NaN = invalid stays NaN)."""
    h, w = depth.shape
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    x = (u - np.float32(K[0, 2])) / np.float32(K[0, 0]) * depth
    y = (v - np.float32(K[1, 2])) / np.float32(K[1, 1]) * depth
    return np.stack([x, y, depth], axis=-1).astype(np.float32)


def _stencil_normals(V: np.ndarray, s: int, max_diff_m: float) -> np.ndarray:
    """Unit normals (H, W, 3) of a vertex map from the cross product of central differences
    ``s`` pixels to either side; NaN at the border, where a neighbour is missing or where the
    second difference of the depth exceeds ``max_diff_m`` (a discontinuity; a slanted plane
    has none). Oriented towards the camera. Computed per component in the input precision."""
    n = np.full_like(V, np.nan)
    x, y, z = V[..., 0], V[..., 1], V[..., 2]
    c = (slice(s, -s), slice(s, -s))
    r, l = (slice(s, -s), slice(2 * s, None)), (slice(s, -s), slice(None, -2 * s))
    d, u = (slice(2 * s, None), slice(s, -s)), (slice(None, -2 * s), slice(s, -s))
    ax, ay, az = x[r] - x[l], y[r] - y[l], z[r] - z[l]            # d/du
    bx, by, bz = x[d] - x[u], y[d] - y[u], z[d] - z[u]            # d/dv
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    zc = z[c]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        inv = 1.0 / np.sqrt(cx * cx + cy * cy + cz * cz)
        ddx = np.abs(z[r] - 2 * zc + z[l])
        ddy = np.abs(z[d] - 2 * zc + z[u])
        bad = ~np.isfinite(inv) | (ddx > max_diff_m) | (ddy > max_diff_m)
        # orient towards the camera (the point itself is the viewing ray)
        inv = np.where(cx * x[c] + cy * y[c] + cz * zc > 0, -inv, inv)
    inv[bad] = np.nan
    n[c + (0,)] = cx * inv
    n[c + (1,)] = cy * inv
    n[c + (2,)] = cz * inv
    return n


def normal_map(vertex: np.ndarray, max_diff_m: float) -> np.ndarray:
    """Unit normals (H, W, 3) float32 from a vertex map by central differences; NaN where a
    neighbour is missing or at a depth discontinuity (second difference of the depth above
    ``max_diff_m``). Normals point towards the camera."""
    return _stencil_normals(vertex, 1, max_diff_m)


def smooth_normal_map(depth: np.ndarray, K: np.ndarray, max_diff_m: float, stencil: int = 2,
                      sigma_depth_m: float = 0.03, sigma_px: float = 2.0) -> np.ndarray:
    """Normals (H, W, 3) from a depth map (NaN = invalid) after an edge-preserving bilateral
    filter, by central differences ``stencil`` pixels apart (less noise than 1-pixel
    differences); NaN near holes and depth discontinuities; oriented towards the camera."""
    import cv2
    d = np.nan_to_num(depth, nan=0.0).astype(np.float32)
    sm = cv2.bilateralFilter(d, 2 * stencil + 1, sigma_depth_m, sigma_px)
    sm[~np.isfinite(depth)] = np.nan
    return _stencil_normals(vertex_map(sm, K), stencil, max_diff_m)


def _t(a: np.ndarray):
    o3d = o3d_quiet()
    return o3d.core.Tensor(np.ascontiguousarray(a, dtype=np.float32))


@dataclass
class Level:
    """One pyramid level: depth (NaN = invalid) and lazily built Open3D tensors."""

    depth: np.ndarray
    """(H, W) float32 metres, NaN where invalid or outside [depth_min, depth_max]."""
    intr: Intrinsics
    gray: np.ndarray | None = None
    """(H, W) float32 intensity in [0, 1], or None without colour."""
    cache: dict = field(default_factory=dict)

    @property
    def valid(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.depth)))

    def K(self):
        if "K" not in self.cache:
            o3d = o3d_quiet()
            self.cache["K"] = o3d.core.Tensor(self.intr.K, dtype=o3d.core.float64)
        return self.cache["K"]

    def vertex_np(self) -> np.ndarray:
        if "vertex_np" not in self.cache:
            self.cache["vertex_np"] = vertex_map(self.depth, self.intr.K)
        return self.cache["vertex_np"]

    def vertex(self):
        if "vertex" not in self.cache:
            self.cache["vertex"] = _t(self.vertex_np())
        return self.cache["vertex"]

    def normal(self, max_diff_m: float = 0.05):
        if "normal" not in self.cache:
            self.cache["normal"] = _t(normal_map(self.vertex_np(), max_diff_m))
        return self.cache["normal"]

    def depth_t(self):
        if "depth_t" not in self.cache:
            self.cache["depth_t"] = _t(self.depth[..., None])
        return self.cache["depth_t"]

    def gray_t(self):
        if "gray_t" not in self.cache:
            self.cache["gray_t"] = _t(self.gray[..., None])
        return self.cache["gray_t"]

    def _sobel(self, key: str, img: np.ndarray):
        if key not in self.cache:
            o3d = o3d_quiet()
            gx, gy = o3d.t.geometry.Image(_t(img[..., None])).filter_sobel()
            self.cache[key] = (gx.as_tensor(), gy.as_tensor())
        return self.cache[key]

    def depth_grad(self):
        return self._sobel("depth_grad", self.depth)

    def gray_grad(self):
        return self._sobel("gray_grad", self.gray)


class Pyramid:
    """Multi-resolution view of one RGB-D frame (level 0 = full resolution)."""

    def __init__(self, depth_m: np.ndarray, intr: Intrinsics, n_levels: int, depth_min_m: float,
                 depth_max_m: float, rgb: np.ndarray | None = None, max_diff_m: float = 0.1):
        d = np.asarray(depth_m, dtype=np.float32).copy()
        with np.errstate(invalid="ignore"):
            d[~np.isfinite(d) | (d < depth_min_m) | (d > depth_max_m)] = np.nan
        gray = None
        if rgb is not None:
            import cv2
            gray = cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
        self.levels: list[Level] = [Level(d, intr, gray)]
        for _ in range(1, n_levels):
            prev = self.levels[-1]
            self.levels.append(Level(downsample_depth(prev.depth, max_diff_m), prev.intr.scaled(0.5),
                                     None if prev.gray is None else downsample_image(prev.gray)))

    def __getitem__(self, level: int) -> Level:
        return self.levels[level]

    def __len__(self) -> int:
        return len(self.levels)


# --------------------------------------------------------------------------------------------
# Gauss-Newton loops


@dataclass
class SolveResult:
    """Outcome of a coarse-to-fine projective registration."""

    transformation: np.ndarray
    """(4, 4) source-to-target transform."""
    inliers: int
    """Inlier correspondences at the finest level (evaluated at the final transform)."""
    valid: int
    """Valid source pixels at the finest level."""
    inlier_rmse: float
    """RMS point-to-plane residual of the inliers at the finest level, metres (NaN if none)."""
    iterations: int
    ok: bool = True
    message: str = ""

    @property
    def fitness(self) -> float:
        return self.inliers / self.valid if self.valid else 0.0


def _step_small(D: np.ndarray, eps: float) -> bool:
    return np.linalg.norm(D[:3, 3]) < eps and rotation_angle_rad(D[:3, :3]) < eps


def point_to_plane_stats(src_vertex, tgt_vertex, tgt_normal, K, T: np.ndarray, max_dist_m: float
                         ) -> tuple[int, float]:
    """(inlier count, RMS point-to-plane residual in metres) of projective correspondences at
    ``T`` (source-to-target); uses Open3D's kernel with a Huber width equal to the
    rejection distance, so every inlier is in the quadratic part: loss = r^2 / 2."""
    o3d = o3d_quiet()
    od = _odometry_kernels()
    src_vertex_shape = src_vertex.shape
    n_px = int(src_vertex_shape[0]) * int(src_vertex_shape[1])
    try:
        r = od.compute_odometry_result_point_to_plane(
            src_vertex, tgt_vertex, tgt_normal, K, o3d.core.Tensor(T), float(max_dist_m), float(max_dist_m) * 10)
    except RuntimeError:  # Open3D raises when no correspondence at all is found
        return 0, float("nan")
    count = int(round(r.fitness * n_px))
    return count, float(np.sqrt(max(2.0 * r.inlier_rmse, 0.0)))


def _np(a) -> np.ndarray:
    """float32 numpy array of an Open3D tensor or array."""
    return np.ascontiguousarray(a.numpy() if hasattr(a, "numpy") else a, dtype=np.float32)


def icp_point_to_plane(src: list, tgt: list, init: np.ndarray, iterations: list[int],
                       max_dist_m: list[float], huber_delta_m: float = 0.0, eps: float = 1e-6,
                       stats_target: tuple | None = None, stage_times: list | None = None) -> SolveResult:
    """Coarse-to-fine projective point-to-plane ICP (KinectFusion's tracking step).

    ``src[k]`` is the source :class:`Level` and ``tgt[k]`` a (vertex, normal, K) tuple (numpy
    arrays or Open3D tensors) for stage k (coarse to fine; the target may have another
    resolution than the source: the source points are projected with the target's K).
    ``max_dist_m[k]`` rejects pairs whose point-to-plane distance is larger; ``huber_delta_m`` >
    0 down-weights residuals above it (0 = plain truncated least squares). Target normals may be
    scaled by the square root of per-point weights (weighted least squares); ``stats_target`` is
    then the finest target with unit normals, for the statistics (default ``tgt[-1]``). A stage
    ends early when a step moves less than ``eps`` (metres and radians). The normal equations
    come from :mod:`slam.backends._p2p_kernel` (fixed-order sums: the same result on any number
    of threads). ``stage_times``, when given, receives the seconds spent per stage (one entry
    per stage, then one for the statistics). Returns the source-to-target transform.
    """
    from slam.backends._p2p_kernel import normal_equations, twist_to_transform
    import time
    T = np.asarray(init, dtype=np.float64).copy()
    its = 0
    for k, (lvl, (tv, tn, tK)) in enumerate(zip(src, tgt)):
        t0 = time.perf_counter()
        huber = huber_delta_m if huber_delta_m > 0 else max_dist_m[k] * 10
        sv, tv_np, tn_np = lvl.vertex_np(), _np(tv), _np(tn)
        K = np.asarray(tK.numpy() if hasattr(tK, "numpy") else tK, np.float64)
        for _ in range(iterations[k]):
            A, b, n, _ = normal_equations(sv, tv_np, tn_np, K, T, max_dist_m[k], huber)
            if n < 6:
                return SolveResult(T, 0, src[-1].valid, float("nan"), its, False,
                                   f"no correspondences at stage {k} ({n} pairs)")
            try:
                x = np.linalg.solve(A, -b)
            except np.linalg.LinAlgError:
                return SolveResult(T, 0, src[-1].valid, float("nan"), its, False, "degenerate normal equations")
            D = twist_to_transform(x)
            if not np.all(np.isfinite(D)):
                return SolveResult(T, 0, src[-1].valid, float("nan"), its, False, "solver diverged (NaN)")
            T = D @ T
            its += 1
            if _step_small(D, eps):
                break
        if stage_times is not None:
            stage_times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    tv, tn, tK = tgt[-1] if stats_target is None else stats_target
    K = np.asarray(tK.numpy() if hasattr(tK, "numpy") else tK, np.float64)
    _, _, inl, ssr = normal_equations(src[-1].vertex_np(), _np(tv), _np(tn), K, T, max_dist_m[-1], max_dist_m[-1] * 10)
    if stage_times is not None:
        stage_times.append(time.perf_counter() - t0)
    rmse = float(np.sqrt(ssr / inl)) if inl else float("nan")
    return SolveResult(T, inl, src[-1].valid, rmse, its, inl > 0, "" if inl > 0 else "no inliers")


def rgbd_hybrid(src: Pyramid, tgt: Pyramid, init: np.ndarray, iterations: list[int],
                levels: list[int], depth_diff_m: float, depth_huber_m: float,
                intensity_huber: float, method: str = "hybrid", eps: float = 1e-6) -> SolveResult:
    """Coarse-to-fine dense RGB-D odometry with Open3D's kernels (Park et al. 2017 hybrid loss:
    photometric + depth, or ``point_to_plane`` / ``intensity`` only), on the pyramid levels
    ``levels`` (coarse to fine, e.g. [2, 1, 0]). Returns the source-to-target transform; the
    statistics are point-to-plane ones at the finest level used."""
    o3d = o3d_quiet()
    od = _odometry_kernels()
    T = np.asarray(init, dtype=np.float64).copy()
    its = 0
    for k, l in enumerate(levels):
        s, t = src[l], tgt[l]
        for _ in range(iterations[k]):
            try:
                if method == "hybrid":
                    ddx, ddy = t.depth_grad()
                    gdx, gdy = t.gray_grad()
                    r = od.compute_odometry_result_hybrid(
                        s.depth_t(), t.depth_t(), s.gray_t(), t.gray_t(), ddx, ddy, gdx, gdy,
                        s.vertex(), t.K(), o3d.core.Tensor(T), depth_diff_m, depth_huber_m, intensity_huber)
                elif method == "intensity":
                    gdx, gdy = t.gray_grad()
                    r = od.compute_odometry_result_intensity(
                        s.depth_t(), t.depth_t(), s.gray_t(), t.gray_t(), gdx, gdy, s.vertex(), t.K(),
                        o3d.core.Tensor(T), depth_diff_m, intensity_huber)
                else:
                    r = od.compute_odometry_result_point_to_plane(
                        s.vertex(), t.vertex(), t.normal(depth_diff_m), t.K(), o3d.core.Tensor(T),
                        depth_diff_m, depth_huber_m)
            except RuntimeError as e:
                return SolveResult(T, 0, src[levels[-1]].valid, float("nan"), its, False,
                                   f"no correspondences at level {l} ({str(e).splitlines()[0][:80]})")
            D = r.transformation.numpy()
            if not np.all(np.isfinite(D)):
                return SolveResult(T, 0, src[levels[-1]].valid, float("nan"), its, False, "solver diverged (NaN)")
            T = D @ T
            its += 1
            if _step_small(D, eps):
                break
    f = levels[-1]
    inl, rmse = point_to_plane_stats(src[f].vertex(), tgt[f].vertex(), tgt[f].normal(depth_diff_m),
                                     tgt[f].K(), T, depth_diff_m)
    return SolveResult(T, inl, src[f].valid, rmse, its, inl > 0, "" if inl > 0 else "no inliers")
