"""The disparity lattice of a triangulating sensor, detected from measured depth alone.

A structured-light device reports an integer disparity code: every measured disparity
d = f b / z lies on a lattice d = (k + phase) * step whatever the noise (the noise moves a pixel
from one level to another, never off the lattice; Kinect v1: step 1/8 px, noise ~0.05-0.07 px, a
step / noise ratio near 2). :func:`detect_lattice` finds (step, phase) from a periodogram of the
measured disparities: the circular concentration R(s) = |sum w exp(2 pi i d / s)| / sum w is 1 on
the lattice's step and its divisors s / k, and for continuous disparities it is what the scene
and the noise give: R_ideal(s) exp(-2 pi^2 sigma^2 / s^2) (R_ideal: the ideal disparities of the
same pixels; sigma: the noise, from the residual d - d_ideal less the quantisation's own s^2 / 12).
The excess of R over that expectation marks the lattice; the largest step whose excess is near the
best one is the step (its divisors have the same R but are not the device's step). R's peak is
about 1 / (levels spanned) wide in relative step (0.1 % for Kinect v1 over 0.6-4 m), so the scan
is coarse on a narrow disparity window (few levels: a wide peak), then fine on every pixel.

Depth storage: a depth PNG stores z in units of ``depth_unit_m`` (1/5000 m for TUM / 7-Scenes),
so f b / z_rounded is off the lattice by up to f b * unit / (2 z^2) (0.004 px at 1 m, 0.04 px at
0.5 m for Kinect v1 at VGA). Each pixel is weighted by its expected coherence
exp(-2 pi^2 sigma_r^2 / s^2) with sigma_r = f b * unit / (sqrt(12) z^2), so near pixels, whose
rounded disparities no longer show a small step, do not wash it out.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Lattice", "detect_lattice", "DEPTH_PNG_UNIT_M"]

DEPTH_PNG_UNIT_M = 1.0 / 5000.0
"""Depth quantum of a TUM-format depth PNG (uint16, 5000 units per metre)."""


@dataclass(frozen=True)
class Lattice:
    """A detected disparity lattice d = (k + phase) * step."""

    step_px: float
    """Step, pixels."""
    phase: float
    """Phase in [0, 1), fraction of a step (absolute disparity)."""
    concentration: float
    """Weighted circular concentration R at the step (1: every disparity on the lattice)."""
    expected: float
    """R that continuous disparities of the same scene and noise would have at that step."""


def _conc(d: np.ndarray, s: float, wr: np.ndarray | None) -> complex:
    z = np.exp(2j * np.pi * d / s)
    if wr is None:
        return complex(z.mean())
    w = np.exp(-2 * np.pi ** 2 * wr / (s * s))
    return complex((w * z).sum() / max(w.sum(), 1e-300))


def detect_lattice(d: np.ndarray, d_ideal: np.ndarray | None = None, *, fb: float | None = None,
                   depth_unit_m: float = DEPTH_PNG_UNIT_M, steps: tuple[float, float] = (0.02, 1.0),
                   min_excess: float = 0.3, max_samples: int = 6000, seed: int = 0,
                   window_px: float = 3.0) -> Lattice | None:
    """(step, phase) of the lattice the measured disparities ``d`` (px, any shape, only finite
    positive ones used) lie on, or None when no step in ``steps`` shows an excess concentration of
    ``min_excess`` (continuous disparities, or too few levels to tell).

    ``d_ideal``: the ideal disparities of the same pixels (same shape): gives the scene's own
    concentration and the noise (without it, continuous disparities are expected at R = 0).
    ``fb``: focal length x baseline (px m) to weight pixels by their depth-storage rounding
    (``depth_unit_m``; 0 or ``fb`` None: no weighting). ``window_px``: width of the disparity
    window around the median of the coarse scan (see the code comment)."""
    d = np.asarray(d, np.float64).ravel()
    di = None if d_ideal is None else np.asarray(d_ideal, np.float64).ravel()
    ok = np.isfinite(d) & (d > 0)
    if di is not None:
        ok &= np.isfinite(di) & (di > 0)
    idx = np.flatnonzero(ok)
    if idx.size < 50:
        return None
    if idx.size > max_samples:
        idx = np.random.default_rng(seed).choice(idx, max_samples, replace=False)
    d = d[idx]
    di = None if di is None else di[idx]
    wr = None
    if fb and depth_unit_m > 0:
        # rounding of z to depth_unit_m: sigma_z = unit / sqrt(12); sigma_d = fb sigma_z / z^2 = d^2 sigma_z / fb
        wr = (d * d * depth_unit_m / np.sqrt(12.0) / float(fb)) ** 2
    var_res = 0.0
    if di is not None:
        r = d - di
        mad = np.median(np.abs(r - np.median(r)))
        var_res = float((1.4826 * mad) ** 2)

    def excess(s: float, sel=slice(None)) -> tuple[float, float, float]:
        w2 = None if wr is None else wr[sel]
        z = _conc(d[sel], s, w2)
        exp_c = 0.0
        if di is not None:
            sig2 = max(var_res - s * s / 12.0, 0.0)
            exp_c = abs(_conc(di[sel], s, w2)) * float(np.exp(-2 * np.pi ** 2 * sig2 / (s * s)))
        return abs(z) - exp_c, float(np.angle(z)), exp_c

    # the peak of R is ~1 / (number of levels spanned) wide in relative step: a coarse scan on the
    # pixels of a narrow disparity window (few levels, a wide peak), then a fine one on all pixels
    med = float(np.median(d))
    win = np.flatnonzero(np.abs(d - med) <= window_px / 2)
    sel = win if win.size >= 200 else slice(None)
    grid = np.geomspace(steps[0], steps[1], 400)      # 1 % apart
    ex = np.array([excess(s, sel)[0] for s in grid])
    if ex.max() < min_excess:
        return None
    high = np.flatnonzero(ex >= 0.75 * ex.max())
    run = high[-1:]                       # the last (largest-step) run of high excess ...
    for j in high[::-1][1:]:
        if j != run[0] - 1:
            break
        run = np.concatenate([[j], run])
    s0 = float(grid[int(run[np.argmax(ex[run])])])     # ... its peak, then all pixels on a fine grid
    fine = s0 * np.linspace(0.98, 1.02, 81)
    fx = [excess(s) for s in fine]
    j = int(np.argmax([f[0] for f in fx]))
    if fx[j][0] < min_excess:
        return None
    # the grid's 0.05 % leaves the phase off: the phase is that of the absolute disparity, so a step
    # off by delta moves it by delta * d / step (a third of a step at 5 px with 0.03 px steps and
    # delta 2e-4); a bounded scalar search on R between the grid neighbours finds the peak to 1e-7
    s = _scalar_max(lambda x: excess(x)[0], float(fine[max(j - 1, 0)]), float(fine[min(j + 1, fine.size - 1)]))
    e, ang, exp_c = excess(s)
    if e < fx[j][0]:
        s, (e, ang, exp_c) = float(fine[j]), fx[j]
    return Lattice(float(s), float((ang / (2 * np.pi)) % 1.0), float(e + exp_c), float(exp_c))


def _scalar_max(f, a: float, b: float, rel_tol: float = 1e-7) -> float:
    """The maximiser of a unimodal ``f`` on [a, b] to about ``rel_tol`` of b: bounded Brent search
    (:func:`scipy.optimize.minimize_scalar`, golden section with parabolic steps, which on R's smooth
    peak need a third of plain golden section's evaluations for the same point)."""
    from scipy.optimize import minimize_scalar
    r = minimize_scalar(lambda x: -f(x), bounds=(a, b), method="bounded", options={"xatol": rel_tol * abs(b)})
    return float(r.x)
