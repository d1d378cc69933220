"""Projective point-to-plane Gauss-Newton step as a numba kernel with a fixed-order reduction.

Open3D's ``compute_odometry_result_point_to_plane`` sums the normal equations over the pixels
on all its threads in the order the threads finish, so the same registration differs in its
last bits from run to run unless it is pinned to one thread. This kernel splits the image into
fixed bands of ``_ROWS`` rows (independent of the thread count), sums each band sequentially in
float64 on whichever thread runs it, and adds the band sums in band order: the result is
bit-identical for any number of threads, and both cores do the work.

Same association and residual as Open3D's kernel: every finite source vertex p is moved by T
(source-to-target), projected with the target's (fx, fy, cx, cy) and paired with the target
pixel at the rounded coordinates; r = (T p - t) . n, pairs with |r| > ``max_dist`` rejected;
Jacobian [T p x n, n] for a left-multiplied twist (rotation w, translation t).
"""
from __future__ import annotations

import math

import numpy as np
from numba import config as _numba_config
from numba import njit, prange

# numba's own work queue first: its idle threads sleep (OpenMP's spin and, on a busy 2-core
# machine, doubled the CPU time of a call), and the installed TBB is too old for numba
_numba_config.THREADING_LAYER_PRIORITY = ["workqueue", "omp", "tbb"]

_ROWS = 4
"""Image rows per reduction band (the unit of work of one thread; fixed for reproducibility)."""
_NACC = 29
"""Accumulators per band: 21 of the upper triangle of J^T W J, 6 of J^T W r, inlier count,
sum of squared unweighted residuals."""


def _band_sums_py(src_v, tgt_v, tgt_n, fx, fy, cx, cy, T, max_dist, huber):
    H, W = src_v.shape[0], src_v.shape[1]
    Ht, Wt = tgt_v.shape[0], tgt_v.shape[1]
    nb = (H + _ROWS - 1) // _ROWS
    out = np.zeros((nb, _NACC))
    for b in prange(nb):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        a4 = 0.0
        a5 = 0.0
        a6 = 0.0
        a7 = 0.0
        a8 = 0.0
        a9 = 0.0
        a10 = 0.0
        a11 = 0.0
        a12 = 0.0
        a13 = 0.0
        a14 = 0.0
        a15 = 0.0
        a16 = 0.0
        a17 = 0.0
        a18 = 0.0
        a19 = 0.0
        a20 = 0.0
        a21 = 0.0
        a22 = 0.0
        a23 = 0.0
        a24 = 0.0
        a25 = 0.0
        a26 = 0.0
        a27 = 0.0
        a28 = 0.0
        for y in range(b * _ROWS, min(H, (b + 1) * _ROWS)):
            for x in range(W):
                px = np.float64(src_v[y, x, 0])
                if not math.isfinite(px):
                    continue
                py = np.float64(src_v[y, x, 1])
                pz = np.float64(src_v[y, x, 2])
                qx = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
                qy = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
                qz = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
                if not qz > 0:
                    continue
                uf = fx * qx / qz + cx
                vf = fy * qy / qz + cy
                if not (uf > -0.5 and vf > -0.5 and uf < Wt - 0.5 and vf < Ht - 0.5):
                    continue
                ut = int(math.floor(uf + 0.5))
                vt = int(math.floor(vf + 0.5))
                if ut >= Wt or vt >= Ht:
                    continue
                tx = np.float64(tgt_v[vt, ut, 0])
                nx = np.float64(tgt_n[vt, ut, 0])
                if not (math.isfinite(tx) and math.isfinite(nx)):
                    continue
                ty = np.float64(tgt_v[vt, ut, 1])
                tz = np.float64(tgt_v[vt, ut, 2])
                ny = np.float64(tgt_n[vt, ut, 1])
                nz = np.float64(tgt_n[vt, ut, 2])
                r = (qx - tx) * nx + (qy - ty) * ny + (qz - tz) * nz
                if not abs(r) <= max_dist:
                    continue
                w = 1.0 if abs(r) <= huber else huber / abs(r)
                j0 = qy * nz - qz * ny
                j1 = qz * nx - qx * nz
                j2 = qx * ny - qy * nx
                w0, w1, w2, w3, w4, w5 = w * j0, w * j1, w * j2, w * nx, w * ny, w * nz
                a0 += w0 * j0
                a1 += w0 * j1
                a2 += w0 * j2
                a3 += w0 * nx
                a4 += w0 * ny
                a5 += w0 * nz
                a6 += w1 * j1
                a7 += w1 * j2
                a8 += w1 * nx
                a9 += w1 * ny
                a10 += w1 * nz
                a11 += w2 * j2
                a12 += w2 * nx
                a13 += w2 * ny
                a14 += w2 * nz
                a15 += w3 * nx
                a16 += w3 * ny
                a17 += w3 * nz
                a18 += w4 * ny
                a19 += w4 * nz
                a20 += w5 * nz
                a21 += w0 * r
                a22 += w1 * r
                a23 += w2 * r
                a24 += w3 * r
                a25 += w4 * r
                a26 += w5 * r
                a27 += 1.0
                a28 += r * r
        out[b, 0] = a0
        out[b, 1] = a1
        out[b, 2] = a2
        out[b, 3] = a3
        out[b, 4] = a4
        out[b, 5] = a5
        out[b, 6] = a6
        out[b, 7] = a7
        out[b, 8] = a8
        out[b, 9] = a9
        out[b, 10] = a10
        out[b, 11] = a11
        out[b, 12] = a12
        out[b, 13] = a13
        out[b, 14] = a14
        out[b, 15] = a15
        out[b, 16] = a16
        out[b, 17] = a17
        out[b, 18] = a18
        out[b, 19] = a19
        out[b, 20] = a20
        out[b, 21] = a21
        out[b, 22] = a22
        out[b, 23] = a23
        out[b, 24] = a24
        out[b, 25] = a25
        out[b, 26] = a26
        out[b, 27] = a27
        out[b, 28] = a28
    return out


_band_sums = njit(parallel=True, cache=True, nogil=True)(_band_sums_py)
_band_sums_serial = njit(cache=True, nogil=True)(_band_sums_py)
"""The same bands on the calling thread only: identical sums (the same per-band code and order),
for small images where waking the worker threads costs more than the work."""
_PARALLEL_MIN_PIXELS = 40000
"""Source images with fewer pixels are summed on the calling thread."""


@njit(cache=True, nogil=True)
def _ordered_sum(parts):
    tot = np.zeros(parts.shape[1])
    for b in range(parts.shape[0]):
        for k in range(parts.shape[1]):
            tot[k] += parts[b, k]
    return tot


def normal_equations(src_v: np.ndarray, tgt_v: np.ndarray, tgt_n: np.ndarray, K: np.ndarray, T: np.ndarray,
                     max_dist: float, huber: float) -> tuple[np.ndarray, np.ndarray, int, float]:
    """(A (6, 6), b (6,), inliers, sum of squared residuals) of one projective point-to-plane
    linearisation. ``src_v`` (H, W, 3) float32 source vertices (NaN = invalid), ``tgt_v`` /
    ``tgt_n`` (Ht, Wt, 3) float32 target vertices and (possibly weight-scaled) normals, ``K``
    (3, 3) target intrinsics, ``T`` (4, 4) source-to-target; metres."""
    fn = _band_sums if src_v.shape[0] * src_v.shape[1] >= _PARALLEL_MIN_PIXELS else _band_sums_serial
    tot = _ordered_sum(fn(src_v, tgt_v, tgt_n, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]),
                                  float(K[1, 2]), np.ascontiguousarray(T, np.float64), float(max_dist), float(huber)))
    A = np.zeros((6, 6))
    A[np.triu_indices(6)] = tot[:21]
    A = A + np.triu(A, 1).T
    return A, tot[21:27], int(tot[27]), float(tot[28])


def twist_to_transform(x: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform of a twist x = (w (3,) rotation vector, t (3,)) (Rodrigues)."""
    w, t = x[:3], x[3:]
    th = float(np.linalg.norm(w))
    D = np.eye(4)
    if th > 0:
        k = w / th
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        D[:3, :3] = np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * (Kx @ Kx)
    D[:3, 3] = t
    return D
