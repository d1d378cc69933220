"""Direct model: systematic depth errors (calibration residuals)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from synth.sensor.effects._common import (CENSOR_SDS, depth_noise_sd, locally_flat, measured_depth_range, measured_samples,
                                          robust_std)
from synth.sensor.registry import STAGE_DEPTH, Effect, Signature, param, register_effect


@dataclass
class DepthBiasParams:
    offset_m: float = param(0.0, "m")
    """Constant depth offset, metres."""
    scale: float = param(0.0, "1")
    """Relative depth scale error (z' = (1 + scale) z)."""
    disparity_offset_px: float = param(0.0, "px")
    """Constant disparity error, pixels (-> depth error growing as z^2; triangulation only)."""
    radial_disparity_px: float = param(0.0, "px")
    """Disparity error at the image corner, growing with the squared radius from the centre
    (the Kinect's 'depth distortion' bowl)."""


@register_effect
class DepthBias(Effect):
    """Deterministic depth error: z' = (1 + scale) z(d + e(u, v)) + offset.

    Physics: a device's factory calibration is never perfect. An error in f b or in the
    reference-plane depth gives a disparity offset (depth error ~ z^2); the IR lens and
    reference-image errors give a spatially varying disparity error that grows towards the
    corners (Herrera et al. 2012 model it as a per-pixel disparity distortion); ToF sensors
    have offset and scale errors. No randomness: the same pixel at the same depth always gets
    the same bias.
    """

    name = "depth_bias"
    SIGNATURE = Signature(
        "systematic offset or scale error",
        "The median error moves away from zero steadily with distance (offset, scale, or a "
        "disparity offset that grows with z²).",
        panels=(("distance", "bias"), ("radial", "bias")))
    IDENTITY_PARAMS = {"offset_m": 0.0, "scale": 0.0, "disparity_offset_px": 0.0, "radial_disparity_px": 0.0}
    Params = DepthBiasParams
    FITTABLE = {"offset_m": (-0.1, 0.1), "scale": (-0.1, 0.1), "disparity_offset_px": (-2.0, 2.0),
                "radial_disparity_px": (-2.0, 2.0)}
    stage = STAGE_DEPTH + 1

    def apply(self, state, draw) -> None:
        p = self.params
        z = state.depth.astype(np.float64)
        if (p.disparity_offset_px or p.radial_disparity_px) and state.preset.fb > 0:
            H, W = state.shape
            intr = state.intr
            uu, vv = np.meshgrid(np.arange(W), np.arange(H))
            r2 = ((uu - intr.cx) ** 2 + (vv - intr.cy) ** 2) / (intr.cx ** 2 + intr.cy ** 2)
            e = p.disparity_offset_px + p.radial_disparity_px * r2
            fb = state.preset.fb
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.where(z > 0, 1.0 / (1.0 / z + e / fb), 0.0)
        z = (1.0 + p.scale) * z + p.offset_m
        state.depth = np.where(state.valid, z, 0).astype(np.float32)
        state.valid &= state.depth > 0

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """Offset, scale and disparity errors by least squares on the measured pixels.

        Triangulation (f b > 0): to first order the model gives y = f b (1/z' - 1/z) =
        e + e_r r^2 - s f b / z - o f b / z^2 (e the disparity offset, e_r the radial term at the
        corner, s the scale, o the offset; r the normalised image radius), linear in the four
        unknowns; the disparity residual y has constant noise, so ordinary least squares is right.
        That linearisation is then refined on the model's exact curve (:func:`_exact_refit`): its
        coefficients are e / (1 + s) and s / (1 + s), not e and s, and it has no cross terms of the
        offset with the others.
        ToF: z' - z = o + s z. Residuals beyond 3 px of disparity (5 cm for ToF) are left out
        (mismatches, flying pixels); when the model has edge_fattening only pixels whose ideal depth
        is locally flat are used (within 3 % over 8 px: ``_common.locally_flat``, not beside an edge,
        not on a steep slope - elsewhere the slanted floor's continuous depths are what lets a bias
        of a twentieth of a disparity step show through a coarse quantisation); the least squares is
        trimmed (:func:`_trimmed_lstsq`) and bounded by the fit ranges: pixels that
        block matching gave a nearer depth (fattened edges, steep floors) or that a lens shifted
        across an edge are outliers of the smooth bias and pull it by centimetres (an
        independent-generator pair depth_bias + edge_fattening started at a 0.54 px disparity offset
        and a 4.7 % scale for a 2 cm polynomial bias). When ``config`` carries a lens distortion
        start (started first, :attr:`Effect.START_PRIORITY`), the ideal depth is warped
        by it before the regression: a radial term must not explain what the lens does.

        Censoring at a range limit: the sensor reports no depth beyond its working range, so near
        the farthest (nearest) measured depth only the pixels whose noise made them nearer (farther)
        survive, and their mean error is pulled towards the inside of the range by up to a noise sd.
        That one-sided pull sits at one end of the depth range, where the 1/z^2 (offset) column
        absorbs it and tilts the whole curve (over a narrow far range, e.g. 2-3.3 m, offset, scale and
        disparity offset are correlated at 0.99, and the tilt moves the extrapolated bias at 1 m by
        millimetres while the fit at the data's depths stays within the noise). After a first fit,
        the rows whose predicted measured depth lies within :data:`CENSOR_SDS` noise sd of (or
        beyond) a range limit the data shows (a measured extreme with holes beyond it) are left out
        and the fit repeated (:func:`_uncensored`)."""
        from synth.sensor.effects.lens_distortion import warped_ideal_depth
        fb = float(config.preset.fb)
        rows, ys, zs, hole_rows, hole_zs = [], [], [], [], []
        rng, hole_rng = np.random.default_rng(0), np.random.default_rng(1)
        fattening = "edge_fattening" in config.names(enabled_only=True)
        intr = measured.intrinsics
        frames_used = list(range(len(measured)))

        def columns(z, uu, vv):
            r2 = ((uu - intr.cx) ** 2 + (vv - intr.cy) ** 2) / (intr.cx ** 2 + intr.cy ** 2)
            if fb > 0:
                return np.stack([np.ones_like(z), r2, -fb / z, -fb / z ** 2], 1)
            return np.stack([np.ones_like(z), z], 1)

        for _, m, r, ok in measured_samples(measured, frames_used):
            zi = warped_ideal_depth(config, measured.intrinsics, np.where(r.hit, r.depth, 0))
            ok = ok & (zi > 0) & (locally_flat(zi) if fattening else True)
            vv, uu = np.nonzero(ok & (m > 0))
            hv, hu = np.nonzero(ok & ~(m > 0))       # the holes, sampled at the same rate: the range limits' test
            if vv.size > 20000:
                keep = rng.choice(vv.size, 20000, replace=False)
                hkeep = hole_rng.random(hv.size) < 20000 / vv.size
                vv, uu, hv, hu = vv[keep], uu[keep], hv[hkeep], hu[hkeep]
            z = zi[vv, uu].astype(np.float64)
            zm = m[vv, uu].astype(np.float64)
            if fb > 0:
                y = fb * (1.0 / zm - 1.0 / z)
                good = np.abs(y) < 3.0
            else:
                y = zm - z
                good = np.abs(y) < 0.05
            rows.append(columns(z, uu, vv)[good])
            ys.append(y[good])
            zs.append(z[good])
            zh = zi[hv, hu].astype(np.float64)
            hole_rows.append(columns(zh, hu, hv))
            hole_zs.append(zh)
        if not rows or sum(len(y) for y in ys) < 100:
            return {}
        A, y, z = np.concatenate(rows), np.concatenate(ys), np.concatenate(zs)
        holes = (np.concatenate(hole_rows), np.concatenate(hole_zs))
        lim = cls.FITTABLE
        n = cls.name
        keys = ("disparity_offset_px", "radial_disparity_px", "scale", "offset_m") if fb > 0 else ("offset_m", "scale")
        bounds = [lim[k] for k in keys]
        coef = _trimmed_lstsq(A, y, bounds=bounds)      # inside the fit ranges
        limits = measured_depth_range(measured, frames_used)
        for _ in range(2):              # the censored rows depend on the predicted depth, which the refit moves
            keep = _uncensored(A, y, z, coef, fb, limits, holes, config)
            if keep is None:
                break
            new = _trimmed_lstsq(A[keep], y[keep], bounds=bounds)
            if np.allclose(new, coef, rtol=0.0, atol=1e-9):
                break
            coef = new
        if fb > 0:      # the linearised coefficients -> the model's own curve (see above)
            keep = _uncensored(A, y, z, coef, fb, limits, holes, config)
            rows_ = np.ones(len(y), bool) if keep is None else keep
            coef = _exact_refit(A[rows_], y[rows_], z[rows_], coef, fb, bounds)
            coef = _fewest_terms(A[rows_], y[rows_], z[rows_], coef, fb, bounds)
        return {f"{n}.{k}": float(c) for k, c in zip(keys, coef)}

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """Median error (measured - ideal) in the near, middle and far third of the measured pixels,
        against the current model's.

        Signature present: in some third the measured median differs from the model's by at least
        max(2 mm, 0.25 x the robust noise level of that third)."""
        z, m, sm = ctx.ideal, ctx.measured, ctx.simulated
        v = m > 0
        if v.sum() < 100:
            return ctx.weak("bias signature", gain, "too few measured pixels to estimate a bias")
        q = np.quantile(z[v], [0.0, 1 / 3, 2 / 3, 1.0])
        zc, bm, bs, thr = [], [], [], []
        for a, b in zip(q, q[1:]):
            sel = v & (z >= a) & (z <= b)
            e = m[sel] - z[sel]
            zc.append(float(np.median(z[sel])))
            bm.append(float(np.median(e)))
            ss = sel & (sm > 0)
            bs.append(float(np.median(sm[ss] - z[ss])) if ss.sum() >= 30 else float("nan"))
            iqr = float(np.subtract(*np.quantile(e, [0.75, 0.25])))
            thr.append(max(0.002, 0.25 * iqr / 1.349))
        x = [a - (b if math.isfinite(b) else 0.0) for a, b in zip(bm, bs)]
        big = [abs(xi) >= t for xi, t in zip(x, thr)]
        model = " / ".join(ctx.mm(b) for b in bs)
        numbers = (f"median error {ctx.mm(bm[0])} at {zc[0]:.1f} m, {ctx.mm(bm[1])} in the middle and {ctx.mm(bm[2])} at "
                   f"{zc[2]:.1f} m (current model {model})")
        if not any(big):
            return ctx.weak("bias signature", gain, numbers)
        x1, x3 = x[0], x[2]
        if x1 * x3 < 0 and big[0] and big[2]:
            shape = "changing sign with distance"
        elif abs(x3 - x1) < 0.3 * max(abs(x1), abs(x3), 1e-4):
            shape = "roughly constant"
        else:
            shape = "growing with distance" if abs(x3) > abs(x1) else "shrinking with distance"
        return (f"the measured depth is systematically off: median error {ctx.mm(bm[0])} at {zc[0]:.1f} m, "
                f"{ctx.mm(bm[1])} in the middle and {ctx.mm(bm[2])} at {zc[2]:.1f} m, against {model} in the current "
                f"model (an offset {shape}).")


CENSOR_MIN_HOLES = 50
"""A measured depth extreme is taken for a range limit when at least this many usable hole pixels are
predicted beyond it (and at least as many as measured ones)."""
CENSOR_MIN_SHARE = 0.3
"""Fewer rows than this share of the start's rows left after the censoring cut (or fewer than 100): the
cut is not made (a sequence that lies mostly near its range limit has nothing better to offer)."""


def _exact_refit(A: np.ndarray, y: np.ndarray, z: np.ndarray, coef: np.ndarray, fb: float,
                 bounds: Sequence[tuple[float, float]], k: float = 3.0) -> np.ndarray:
    """Triangulation: (e, e_r, s, o) minimising the squared disparity residuals ``y`` (N,) px about the
    model's exact curve y(z) = f b / ((1 + s) / (1/z + (e + e_r r^2) / f b) + o) - f b / z
    (:meth:`DepthBias.apply`), started at the linearised least squares ``coef`` and within ``bounds``;
    ``A`` (N, 4) the start's columns (r^2 is its second), ``z`` (N,) the ideal depths, m. Rows beyond
    ``k`` robust sd of the linearised fit's residuals are left out (as :func:`_trimmed_lstsq`). The
    linearisation's coefficients are e / (1 + s) and s / (1 + s) to first order (an error of s^2 and
    e s: a -0.4 px offset with a -0.7 % scale, 0.33 m at 3 m, reads 3 mm off there) and it ignores
    the cross terms of the offset with the others."""
    from scipy.optimize import least_squares
    r = y - A @ coef
    ok = np.abs(r - np.median(r)) <= k * max(robust_std(r), 1e-12)
    if ok.sum() < 100:
        return coef
    yy, zz, r2 = y[ok], z[ok], A[ok, 1]
    lo, hi = np.asarray(bounds, np.float64).T

    def residual(p):
        e, er, s, o = p
        zm = (1.0 + s) / (1.0 / zz + (e + er * r2) / fb) + o
        return yy - (fb / np.maximum(zm, 1e-6) - fb / zz)

    x0 = np.clip(coef, lo + 1e-12, hi - 1e-12)
    sol = least_squares(residual, x0, bounds=(lo, hi), x_scale=np.array([0.01, 0.01, 0.001, 0.001]),
                        xtol=1e-12, ftol=1e-12, max_nfev=200)
    return sol.x if sol.success or sol.status == 0 else coef


def _exact_residual(yy: np.ndarray, zz: np.ndarray, r2: np.ndarray, p: np.ndarray, fb: float) -> np.ndarray:
    """(N,) px: disparity residuals ``yy`` about the model's exact curve for (e, e_r, s, o) = ``p`` at
    ideal depths ``zz`` (N,) m and normalised squared radii ``r2`` (N,) (:func:`_exact_refit`)."""
    e, er, s, o = p
    zm = (1.0 + s) / (1.0 / zz + (e + er * r2) / fb) + o
    return yy - (fb / np.maximum(zm, 1e-6) - fb / zz)


def _fewest_terms(A: np.ndarray, y: np.ndarray, z: np.ndarray, coef: np.ndarray, fb: float,
                  bounds: Sequence[tuple[float, float]], k: float = 3.0) -> np.ndarray:
    """Triangulation: the bias start ``coef`` (e, e_r, s, o) reduced to the subset of its four terms
    with the smallest Bayesian information criterion, rss / sd^2 + (terms) ln N, each subset fitted
    on the model's exact curve with the other terms at 0 (``A``, ``y``, ``z``, ``bounds`` as
    :func:`_exact_refit`; sd^2 the full fit's residual variance on its inliers, within ``k`` robust
    sd). Why: over a narrow depth range (e.g. 2-3.3 m) offset, scale and disparity offset are
    0.99-correlated; the full fit then spends the two extra terms on the noise (rss lower by a few
    sd^2, far below the ln N ~ 10 each costs) and their cancelling pair moves the bias extrapolated
    to 1 m by millimetres, while the one term the data ask for extrapolates as the physics does.
    A term the data need lowers the rss by far more than ln N and is kept."""
    from itertools import combinations

    from scipy.optimize import least_squares
    r = _exact_residual(y, z, A[:, 1], coef, fb)
    ok = np.abs(r - np.median(r)) <= k * max(robust_std(r), 1e-12)
    n = int(ok.sum())
    if n < 100:
        return coef
    yy, zz, r2 = y[ok], z[ok], A[ok, 1]
    var = float(np.sum(r[ok] ** 2)) / max(n - len(coef), 1)
    if not var > 0:
        return coef
    lo, hi = np.asarray(bounds, np.float64).T
    best, best_bic = coef, float(np.sum(r[ok] ** 2)) / var + len(coef) * math.log(n)
    scale = np.array([0.01, 0.01, 0.001, 0.001])
    for m in range(1, len(coef)):
        for free in combinations(range(len(coef)), m):
            idx = list(free)

            def residual(q, idx=idx):
                p = np.zeros(len(coef))
                p[idx] = q
                return _exact_residual(yy, zz, r2, p, fb)
            x0 = np.clip(coef[idx], lo[idx] + 1e-12, hi[idx] - 1e-12)
            sol = least_squares(residual, x0, bounds=(lo[idx], hi[idx]), x_scale=scale[idx], xtol=1e-12,
                                ftol=1e-12, max_nfev=200)
            bic = float(np.sum(sol.fun ** 2)) / var + m * math.log(n)
            if bic < best_bic:
                p = np.zeros(len(coef))
                p[idx] = sol.x
                best, best_bic = p, bic
    return best


def _predicted_depth(A: np.ndarray, z: np.ndarray, coef: np.ndarray, fb: float) -> np.ndarray:
    """(N,) metres: the mean measured depth the bias start ``coef`` predicts for ideal depths ``z``
    (N,) with the start's columns ``A`` (N, P) (a disparity residual for f b = ``fb`` > 0, a depth
    residual for ToF)."""
    pred = A @ coef
    if fb > 0:
        return 1.0 / np.maximum(1.0 / z + pred / fb, 1e-6)
    return z + pred


def _uncensored(A: np.ndarray, y: np.ndarray, z: np.ndarray, coef: np.ndarray, fb: float,
                limits: tuple[float, float], holes: tuple[np.ndarray, np.ndarray], config) -> np.ndarray | None:
    """(N,) bool: the rows of the bias start (``A`` (N, P), residual ``y`` (N,): disparity px for
    triangulation, f b = ``fb`` > 0, metres for ToF; ideal depth ``z`` (N,) m) whose measured depth
    is not censored by a range limit, or None when no row is (or too few would stay,
    :data:`CENSOR_MIN_SHARE`).

    The limits are the smallest and largest measured valid depth (``limits``, metres): censoring acts
    on the measured data, so its limits are where the measured depths stop (the model's range limits
    are the preset's until the fit moves them). A limit is one when the data shows it: at least
    :data:`CENSOR_MIN_HOLES` of the usable hole pixels (``holes``: their columns (M, P) and ideal
    depths (M,)) are predicted beyond it, at least as many as the measured rows predicted beyond it
    (a censored pixel beyond the limit is a hole more often than not; where the scene merely ends
    inside the working range, the few pixels predicted beyond its extreme measured depth were
    measured). A row is censored when its predicted mean measured depth (``coef``'s bias applied to
    ``z``) lies within :data:`CENSOR_SDS` sd of a shown limit or beyond it. The sd is the larger of
    the data's and the model's: the robust std of the residuals about ``coef`` (triangulation: a
    disparity noise, z^2 sigma_d / f b in depth) and ``config``'s axial noise law sigma(z) where it
    has one enabled."""
    lo, hi = limits
    if not np.isfinite(hi) or len(y) < 100:
        return None
    sd = robust_std(y - A @ coef)
    zp = _predicted_depth(A, z, coef, fb)
    zh = _predicted_depth(holes[0], holes[1], coef, fb) if len(holes[1]) else np.zeros(0)
    sdz = depth_noise_sd(zp, sd, fb, config)
    keep = np.ones(zp.shape, bool)
    for beyond_rows, beyond_holes, inside in ((zp > hi, zh > hi, zp <= hi - CENSOR_SDS * sdz),
                                              (zp < lo, zh < lo, zp >= lo + CENSOR_SDS * sdz)):
        nh = int(beyond_holes.sum())
        if nh >= CENSOR_MIN_HOLES and nh >= int(beyond_rows.sum()):
            keep &= inside
    if keep.all() or keep.sum() < max(100, CENSOR_MIN_SHARE * len(y)):
        return None
    return keep


def _trimmed_lstsq(A: np.ndarray, y: np.ndarray, k: float = 3.0, iterations: int = 6,
                   bounds: Sequence[tuple[float, float]] | None = None) -> np.ndarray:
    """Least squares of ``y`` (N,) on ``A`` (N, P) refitted on the rows whose residual lies within
    ``k`` robust standard deviations (1.4826 MAD) of the residuals' median, until the kept set stops
    changing (at most ``iterations`` refits). Gaussian noise loses 0.3 % of its rows at k = 3; a
    minority of gross outliers (fattened edges: residuals of 1-3 px against a noise of ~0.1 px) is
    left out after the first refit. ``bounds`` (P pairs): a bounded least squares
    (scipy's ``lsq_linear``) - over a narrow depth range scale and offset are nearly collinear, and
    clipping an unbounded solution afterwards breaks the combination the data asked for."""
    if bounds is not None:
        from scipy.optimize import lsq_linear
        lo, hi = np.asarray(bounds, np.float64).T

        def solve(M, v):
            return lsq_linear(M, v, bounds=(lo, hi), method="bvls").x
    else:
        def solve(M, v):
            return np.linalg.lstsq(M, v, rcond=None)[0]
    keep = np.ones(y.shape, bool)
    coef = solve(A, y)
    for _ in range(iterations):
        r = y - A @ coef
        med = np.median(r[keep])
        sd = robust_std(r[keep])
        new = np.abs(r - med) <= k * max(sd, 1e-12)
        if new.sum() < max(A.shape[1] * 10, 100) or np.array_equal(new, keep):
            break
        keep = new
        coef = solve(A[keep], y[keep])
    return coef
