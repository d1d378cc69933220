"""A sub-voxel TSDF ray caster for tracking, as a numba kernel (one ray per pixel, any thread count
gives the same image).

Replaces Open3D's ray cast plus the hit verification and repair of :meth:`slam.tsdf.TSDFVolume.raycast`
for the model view of frame-to-model tracking. Each ray marches the TSDF from a start depth: the
depth a hint image (the last fused frame's depth, whose pose is the pose of the cast) reports
minus three truncation distances, or ``depth_min`` where it has none. Steps: half a block across
unallocated blocks, one voxel across unobserved voxels, 0.8 x the signed distance (at least one
voxel) in observed free space. The first observed + to - change of the nearest-voxel TSDF
brackets the surface; a secant step and five Newton steps on the trilinear TSDF find its zero
(regula falsi between the bracketing samples where Newton leaves the bracket),
which is kept only when all 8 corners of its cell are observed (weight >= the threshold) and the
trilinear TSDF there is within a quarter voxel of zero (the same check as ``raycast(refine=True)``);
otherwise the pixel is a miss. A jump out of an unallocated block that lands behind a surface is
caught by searching back one voxel at a time over the jump.

Approximation: the hint skips the space in front of the last measurement, so a model surface
more than three truncation distances in front of what the camera measured there (an object that
has since moved away) is not seen; a static scene has none.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from slam.backends._p2p_kernel import _numba_config  # noqa: F401  (threading layer choice)


_NEWTON, _MAX_STEP, _WINDOW, _NEWTON_TOL = 5, 2.0, 3.0, 1e-3
"""Newton steps on the trilinear TSDF (at most), the largest step taken (voxels along the ray), how far
the zero may lie from the secant estimate of the bracketing samples (voxels), and the step below
which Newton has converged (voxels: 10 micrometres at 1 cm voxels, far below the sensor noise)."""


@njit(cache=True, nogil=True, inline="always")
def _lin(ix, iy, iz, table, lo0, lo1, lo2, shift, mask):
    """Linear voxel index of integer voxel (ix, iy, iz); -2 = block not allocated."""
    bx = (ix >> shift) - lo0
    by = (iy >> shift) - lo1
    bz = (iz >> shift) - lo2
    if bx < 0 or by < 0 or bz < 0 or bx >= table.shape[0] or by >= table.shape[1] or bz >= table.shape[2]:
        return -2
    buf = table[bx, by, bz]
    if buf < 0:
        return -2
    return (np.int64(buf) << (3 * shift)) + ((ix & mask) + ((iy & mask) << shift) + ((iz & mask) << (2 * shift)))


@njit(cache=True, nogil=True)
def _trilinear(px, py, pz, tsdf, weight, w_min, inv_vs, table, lo0, lo1, lo2, shift, mask):
    """(f, dfdx, dfdy, dfdz per voxel, ok, mean weight) of the trilinear TSDF at world point p."""
    qx, qy, qz = px * inv_vs, py * inv_vs, pz * inv_vs
    bx, by, bz = math.floor(qx), math.floor(qy), math.floor(qz)
    x, y, z = qx - bx, qy - by, qz - bz
    ix, iy, iz = int(bx), int(by), int(bz)
    # the 8 corners as scalars (no per-call array: this runs ~6 times per ray)
    l0 = _lin(ix, iy, iz, table, lo0, lo1, lo2, shift, mask)
    l1 = _lin(ix + 1, iy, iz, table, lo0, lo1, lo2, shift, mask)
    l2 = _lin(ix, iy + 1, iz, table, lo0, lo1, lo2, shift, mask)
    l3 = _lin(ix + 1, iy + 1, iz, table, lo0, lo1, lo2, shift, mask)
    l4 = _lin(ix, iy, iz + 1, table, lo0, lo1, lo2, shift, mask)
    l5 = _lin(ix + 1, iy, iz + 1, table, lo0, lo1, lo2, shift, mask)
    l6 = _lin(ix, iy + 1, iz + 1, table, lo0, lo1, lo2, shift, mask)
    l7 = _lin(ix + 1, iy + 1, iz + 1, table, lo0, lo1, lo2, shift, mask)
    if l0 < 0 or l1 < 0 or l2 < 0 or l3 < 0 or l4 < 0 or l5 < 0 or l6 < 0 or l7 < 0:
        return 0.0, 0.0, 0.0, 0.0, False, 0.0
    w0, w1, w2, w3 = weight[l0], weight[l1], weight[l2], weight[l3]
    w4, w5, w6, w7 = weight[l4], weight[l5], weight[l6], weight[l7]
    if not (w0 >= w_min and w1 >= w_min and w2 >= w_min and w3 >= w_min and w4 >= w_min and w5 >= w_min
            and w6 >= w_min and w7 >= w_min):
        return 0.0, 0.0, 0.0, 0.0, False, 0.0
    c0, c1, c2, c3 = np.float64(tsdf[l0]), np.float64(tsdf[l1]), np.float64(tsdf[l2]), np.float64(tsdf[l3])
    c4, c5, c6, c7 = np.float64(tsdf[l4]), np.float64(tsdf[l5]), np.float64(tsdf[l6]), np.float64(tsdf[l7])
    wsum = (((((((np.float64(w0) + w1) + w2) + w3) + w4) + w5) + w6) + w7)
    d01, d23, d45, d67 = c1 - c0, c3 - c2, c5 - c4, c7 - c6
    c00, c10, c01, c11 = c0 + x * d01, c2 + x * d23, c4 + x * d45, c6 + x * d67
    e0, e1 = c10 - c00, c11 - c01
    f0, f1 = c00 + y * e0, c01 + y * e1
    f = f0 + z * (f1 - f0)
    gx = (d01 + y * (d23 - d01)) * (1 - z) + (d45 + y * (d67 - d45)) * z
    gy = e0 + z * (e1 - e0)
    gz = f1 - f0
    return f, gx, gy, gz, True, wsum / 8.0


@njit(parallel=True, cache=True, nogil=True)
def march(tsdf, weight, table, lo, shift, vs, trunc_mult, w_min, fx, fy, cx, cy, H, W, R, C, hint,
          depth_min, depth_max):
    """Depth (H, W) float32 (0 = miss) and mean corner weight (H, W) float32 of the model seen
    from camera-to-world (R, C) with pinhole (fx, fy, cx, cy); see the module docstring.
    ``tsdf`` / ``weight``: flat voxel attributes; ``table``: dense block -> buffer index map whose
    entry [0, 0, 0] is block ``lo``; ``hint`` (H, W) start depths (<= 0 or NaN = none)."""
    depth = np.zeros((H, W), np.float32)
    wout = np.zeros((H, W), np.float32)
    inv_vs = 1.0 / vs
    trunc = vs * trunc_mult
    mask = (1 << shift) - 1
    half_block = 0.5 * vs * (1 << shift)
    tol = 0.25 / trunc_mult
    lo0, lo1, lo2 = lo[0], lo[1], lo[2]
    for v in prange(H):
        for u in range(W):
            a = (u - cx) / fx
            b = (v - cy) / fy
            dx = R[0, 0] * a + R[0, 1] * b + R[0, 2]
            dy = R[1, 0] * a + R[1, 1] * b + R[1, 2]
            dz = R[2, 0] * a + R[2, 1] * b + R[2, 2]
            dn = math.sqrt(dx * dx + dy * dy + dz * dz)
            vstep = vs / dn                     # depth step of one voxel along this ray
            z = depth_min
            h = hint[v, u]
            if h > 0:
                z = max(depth_min, h - 3.0 * trunc)
            prev_ok = False
            prev_f = 0.0
            prev_z = 0.0
            jumped_from = -1.0                  # depth before the last jump over unallocated space
            za = -1.0
            zb = -1.0
            fa = 0.0
            fb = 0.0
            while z <= depth_max:
                px, py, pz = C[0] + z * dx, C[1] + z * dy, C[2] + z * dz
                li = _lin(int(math.floor(px * inv_vs + 0.5)), int(math.floor(py * inv_vs + 0.5)),
                          int(math.floor(pz * inv_vs + 0.5)), table, lo0, lo1, lo2, shift, mask)
                if li == -2:
                    jumped_from = z
                    prev_ok = False
                    z += half_block / dn
                    continue
                if not weight[li] >= w_min:
                    prev_ok = False
                    jumped_from = -1.0
                    z += vstep
                    continue
                f = np.float64(tsdf[li])
                if f <= 0:
                    if prev_ok and prev_f > 0:
                        za, fa, zb, fb = prev_z, prev_f, z, f
                        break
                    if not prev_ok and jumped_from >= 0:
                        # landed behind a surface after a jump: search back one voxel at a time
                        zz = z - vstep
                        nf = f
                        nz = z
                        while zz > jumped_from:
                            pxx, pyy, pzz = C[0] + zz * dx, C[1] + zz * dy, C[2] + zz * dz
                            lj = _lin(int(math.floor(pxx * inv_vs + 0.5)), int(math.floor(pyy * inv_vs + 0.5)),
                                      int(math.floor(pzz * inv_vs + 0.5)), table, lo0, lo1, lo2, shift, mask)
                            if lj < 0 or not weight[lj] >= w_min:
                                break
                            g = np.float64(tsdf[lj])
                            if g > 0:
                                za, fa, zb, fb = zz, g, nz, nf
                                break
                            nf = g
                            nz = zz
                            zz -= vstep
                        if za >= 0:
                            break
                    prev_ok = True
                    prev_f = f
                    prev_z = z
                    jumped_from = -1.0
                    z += vstep
                    continue
                prev_ok = True
                prev_f = f
                prev_z = z
                jumped_from = -1.0
                z += max(vstep, 0.8 * f * trunc / dn)
            if za < 0:
                continue
            zs = za + fa / (fa - fb) * (zb - za)
            zn = zs
            ok = False
            f = 1.0
            wm = 0.0
            for _ in range(_NEWTON):
                f, gx, gy, gz, ok, wm = _trilinear(C[0] + zn * dx, C[1] + zn * dy, C[2] + zn * dz, tsdf, weight,
                                                    w_min, inv_vs, table, lo0, lo1, lo2, shift, mask)
                if not ok:
                    break
                dfdz = (gx * dx + gy * dy + gz * dz) * inv_vs
                if dfdz < -1e-9:
                    st = -f / dfdz
                    if abs(st) <= _MAX_STEP * vstep:
                        zn += st
                    if abs(st) <= _NEWTON_TOL * vstep:
                        break
            if ok:
                f, gx, gy, gz, ok, wm = _trilinear(C[0] + zn * dx, C[1] + zn * dy, C[2] + zn * dz, tsdf, weight,
                                                    w_min, inv_vs, table, lo0, lo1, lo2, shift, mask)
            if not (ok and abs(f) <= tol and abs(zn - zs) <= _WINDOW * vstep):
                # Newton left the bracket or stalled (edges, non-monotonic cells): regula falsi
                # on the trilinear TSDF between the bracketing samples, when it brackets a zero
                ok = False
                fa_t, _, _, _, oka, _ = _trilinear(C[0] + za * dx, C[1] + za * dy, C[2] + za * dz, tsdf, weight,
                                                   w_min, inv_vs, table, lo0, lo1, lo2, shift, mask)
                fb_t, _, _, _, okb, _ = _trilinear(C[0] + zb * dx, C[1] + zb * dy, C[2] + zb * dz, tsdf, weight,
                                                   w_min, inv_vs, table, lo0, lo1, lo2, shift, mask)
                if oka and okb and fa_t > 0 and fb_t <= 0:
                    lo_z, hi_z, flo, fhi = za, zb, fa_t, fb_t
                    zn = zs
                    for _ in range(12):
                        zn = lo_z + flo / (flo - fhi) * (hi_z - lo_z)
                        f, gx, gy, gz, ok, wm = _trilinear(C[0] + zn * dx, C[1] + zn * dy, C[2] + zn * dz, tsdf,
                                                            weight, w_min, inv_vs, table, lo0, lo1, lo2, shift, mask)
                        if not ok or abs(f) <= 0.05 * tol:
                            break
                        if f > 0:
                            lo_z, flo = zn, f
                            fhi *= 0.5
                        else:
                            hi_z, fhi = zn, f
                            flo *= 0.5
                    zs = zn
            if ok and abs(f) <= tol and abs(zn - zs) <= _WINDOW * vstep and zn > 0:
                depth[v, u] = np.float32(zn)
                wout[v, u] = np.float32(wm)
    return depth, wout


def min_pool(depth: np.ndarray, factor: int) -> np.ndarray:
    """(H, W) depth (0 or NaN = none) -> (H // factor, W // factor): the nearest valid depth of each
    factor x factor block, 0 where none (the start depths of :func:`march` at a lower resolution)."""
    return _min_pool(np.ascontiguousarray(depth, np.float32), int(factor))


@njit(cache=True, nogil=True)
def _min_pool(depth, factor):
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    out = np.zeros((h, w), np.float32)
    for v in range(h):
        for u in range(w):
            m = np.inf
            for dv in range(factor):
                for du in range(factor):
                    d = depth[v * factor + dv, u * factor + du]
                    if d > 0 and d < m:         # False for NaN
                        m = d
            if m < np.inf:
                out[v, u] = m
    return out


def cast_model(volume, intr, pose_c2w: np.ndarray, hint: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) float32 metres, 0 = miss; mean observation weight at the hit (H, W)) of the
    fused surface of ``volume`` (:class:`slam.tsdf.TSDFVolume`) seen from ``pose_c2w`` with
    ``intr``; ``hint``: start depths at this resolution (see :func:`march`)."""
    cfg = volume.config
    lo, table = volume._block_lookup()
    tsdf = volume.vbg.attribute("tsdf").cpu().numpy().reshape(-1)
    weight = volume.vbg.attribute("weight").cpu().numpy().reshape(-1)
    T = np.asarray(pose_c2w, np.float64)
    if hint is None:
        hint = np.zeros(intr.shape, np.float32)
    shift = cfg.block_resolution.bit_length() - 1
    return march(tsdf, weight, np.ascontiguousarray(table, np.int32), lo.astype(np.int64), shift,
                 float(cfg.voxel_size_m), float(cfg.trunc_voxel_multiplier),
                 float(max(cfg.raycast_weight_threshold, 1e-6)), float(intr.fx), float(intr.fy),
                 float(intr.cx), float(intr.cy), int(intr.height), int(intr.width),
                 np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]),
                 np.ascontiguousarray(hint, np.float32), float(cfg.depth_min_m), float(cfg.depth_max_m))
