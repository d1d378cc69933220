"""Helpers shared by several effects (not an effect module: the leading underscore keeps it
out of discovery)."""
from __future__ import annotations

import numpy as np

from data_tools.errors import RealgapError


def sigmoid(x: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-np.clip(x, -30, 30)))).astype(np.float32)


def uniform_draw(rng: np.random.Generator, shape) -> dict:
    """One U(0, 1) float32 variate per pixel."""
    return {"u": rng.random(shape, dtype=np.float32)}


def normal_draw(rng: np.random.Generator, shape) -> dict:
    """One N(0, 1) float32 variate per pixel."""
    return {"n": rng.standard_normal(shape, dtype=np.float32)}


def check_draw(draw, key: str, shape, effect: str) -> np.ndarray:
    if draw is None or key not in draw:
        raise RealgapError(f"sensor effect {effect!r}: replayed draw lacks {key!r}")
    a = draw[key]
    if a.shape != tuple(shape):
        raise RealgapError(f"sensor effect {effect!r}: replayed draw {key!r} has shape {a.shape}, frame is {tuple(shape)}")
    return a


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) a . b of two (H, W, 3) float32 fields, summed in the order x, y, z (element-wise
    float32, no einsum)."""
    out = a[..., 0] * b[..., 0]
    out += a[..., 1] * b[..., 1]
    out += a[..., 2] * b[..., 2]
    return out


def cos_view(view, ray_dirs_cam: np.ndarray) -> np.ndarray:
    """(H, W) cosine between the camera-facing normal and the reversed viewing ray (0 = no hit)."""
    c = -_dot3(view.normals_cam, ray_dirs_cam)
    c[~view.hit] = 0.0
    return np.clip(c, 0.0, 1.0).astype(np.float32)


def cos_incidence(view, source_cam) -> tuple[np.ndarray, np.ndarray]:
    """(cos of incidence from a point light at ``source_cam`` (3,), distance to it) per pixel."""
    L = view.points_cam - np.asarray(source_cam, np.float32)
    r = np.sqrt(_dot3(L, L)).astype(np.float32)
    r = np.maximum(r, 1e-6)
    c = -_dot3(view.normals_cam, L) / r
    c[~view.hit] = 0.0
    return np.clip(c, 0.0, 1.0).astype(np.float32), r


def drop_with_probability(state, p: np.ndarray, u: np.ndarray, name: str) -> None:
    """Invalidate pixels whose uniform variate falls below their drop probability."""
    state.invalidate(u < p, name)
    state.log[name]["mean_drop_probability"] = float(p[state.ideal.hit].mean()) if state.ideal.hit.any() else 0.0


def measured_samples(measured, frames=None, in_range: bool = False):
    """Yield, per frame of a :class:`synth.lab.measured.MeasuredSequence` (default every loaded
    frame), ``(k, measured depth, ideal RenderResult, usable)`` with ``usable`` (H, W) bool: the
    ideal geometry is there and, when the sequence has masks, inside the mask (what the lab
    compares). For the effects' closed-form ``fit_start`` estimates.

    ``in_range``: usable pixels also have an ideal depth between the smallest and the largest measured
    valid depth over those frames (:func:`measured_depth_range`): where the sensor
    measures at all. For the starts of hole-making effects: the pixels beyond a range limit are
    holes too, and they are the far, weak-signal, grazing ones (half of a 160 px frame of the mystery
    generator's scenes: a low-reflectance start read signal50 2-4 x too high from them)."""
    ks = list(range(len(measured)) if frames is None else frames)
    lo, hi = measured_depth_range(measured, ks) if in_range else (0.0, np.inf)
    for k in ks:
        m = measured.measured_depth(k)
        r = measured.render(k)
        ok = r.hit & (r.depth > 0)
        if in_range:
            ok &= (r.depth >= lo) & (r.depth <= hi)
        mask = measured.mask(k)
        if mask is not None:
            ok &= mask
        yield k, m, r, ok


CENSOR_SDS = 3.0
"""Ideal depths within this many noise sd of a range limit are censored: a measured depth there is
cut (a hole) whenever the noise pushes it past the limit, whatever else the sensor does (a normal
error crosses a limit 3 sd away in less than 0.2 % of the draws)."""
UNCENSORED_MIN_HOLES = 20
""":func:`uncensored_samples` leaves the censoring band in when fewer holes than this would stay
outside it (too few to fit a hole law; the plain in-range set is then the better evidence)."""
UNCENSORED_MIN_PIXEL_SHARE = 0.3
"""... or fewer than this share of the in-range pixels (a view that lies mostly near its range
limits has nothing better to offer)."""


def depth_noise_sd(z: np.ndarray, residual_sd: float, fb: float, config=None) -> np.ndarray:
    """(N,) metres: the sd of a measured depth at depth ``z`` (N,) metres, the larger of the data's
    and the model's: ``residual_sd`` - the robust sd of the disparity residual f b (1/z' - 1/z), px,
    for triangulation (``fb`` > 0, f b in px m; z^2 residual_sd / f b in depth), of the depth
    residual z' - z, metres, for ToF - and ``config``'s axial noise law sigma(z) where it has one
    enabled (the model a candidate is fitted on; None: the data's alone)."""
    z = np.asarray(z, np.float64)
    sdz = z ** 2 * residual_sd / fb if fb > 0 else np.full_like(z, residual_sd)
    if config is not None and "axial_noise" in config.names(enabled_only=True):
        sdz = np.maximum(sdz, np.asarray(config.effect("axial_noise").sigma(z), np.float64))
    return sdz


def residual_sd(measured_z: np.ndarray, ideal_z: np.ndarray, fb: float) -> float:
    """Robust sd (:func:`robust_std`) of the residual of measured depths ``measured_z`` (N,) against
    the ideal ``ideal_z`` (N,), metres, both > 0: in disparity px, f b (1/z' - 1/z), for triangulation
    (``fb`` > 0: the noise of a disparity is the same at every depth), in metres for ToF; 0 with no
    pixel. The input of :func:`depth_noise_sd`."""
    m, z = np.asarray(measured_z, np.float64), np.asarray(ideal_z, np.float64)
    if not m.size:
        return 0.0
    return robust_std(fb * (1.0 / m - 1.0 / z) if fb > 0 else m - z)


def censoring_band(z: np.ndarray, limits: tuple[float, float], sdz: np.ndarray, sds: float = CENSOR_SDS) -> np.ndarray:
    """(shape of ``z``) bool: ideal depths ``z`` (metres) within ``sds`` noise sd ``sdz`` (metres,
    same shape; :func:`depth_noise_sd`) of the nearest or the farthest measured depth ``limits``
    (:func:`measured_depth_range`). There a pixel is a hole whenever its noise crosses the limit, so
    its hole rate says nothing about a dropout law: the starts of the hole-making effects and
    :func:`synth.lab.decisive.hole_drivers` leave these pixels out."""
    lo, hi = limits
    return (z < lo + sds * sdz) | (z > hi - sds * sdz)


def uncensored_samples(measured, config, frames=None):
    """:func:`measured_samples` with ``in_range=True`` and, in ``usable``, the :func:`censoring_band`
    left out as well: the in-range pixels whose ideal depth lies within :data:`CENSOR_SDS` noise sd
    of the nearest or the farthest measured depth. Near a range limit noise alone makes holes (the
    farther half of the pixels at the limit are cut), at the bright, far, faced-on signals a dropout
    law does not reach; counted as dropouts they pull a low-reflectance start's signal50 towards
    them (one logistic fitted to both clusters). The noise sd is :func:`depth_noise_sd`'s: the
    larger of the measured disparity residual's robust sd over the in-range valid pixels and
    ``config``'s axial noise sigma(z) (the model the candidate is fitted on). When the band would
    leave fewer than :data:`UNCENSORED_MIN_HOLES` holes or fewer than :data:`UNCENSORED_MIN_PIXEL_SHARE` of
    the in-range pixels, the plain in-range set is yielded (the start's old evidence). The frames
    are read twice (the sd needs all of them first); the sequence caches its renders."""
    ks = list(range(len(measured)) if frames is None else frames)
    samples = list(measured_samples(measured, ks, in_range=True))
    fb = float(getattr(config.preset, "fb", 0.0) or 0.0)
    lim = measured_depth_range(measured, ks)
    if not samples or not np.isfinite(lim[1]):
        yield from samples
        return
    ms, zs = [], []
    for _, m, r, ok in samples:
        v = ok & (m > 0)
        ms.append(m[v])
        zs.append(r.depth[v])
    sd = residual_sd(np.concatenate(ms), np.concatenate(zs), fb)
    keep, n_in, n_keep, h_keep = [], 0, 0, 0
    for _, m, r, ok in samples:
        z = np.where(ok, r.depth, 0.0)
        k_ = ok & ~censoring_band(z, lim, depth_noise_sd(z, sd, fb, config))
        keep.append(k_)
        n_in += int(ok.sum())
        n_keep += int(k_.sum())
        h_keep += int((k_ & ~(m > 0)).sum())
    if h_keep < UNCENSORED_MIN_HOLES or n_keep < UNCENSORED_MIN_PIXEL_SHARE * n_in:
        yield from samples
        return
    for (k, m, r, _), k_ in zip(samples, keep):
        yield k, m, r, k_


def measured_depth_range(measured, frames) -> tuple[float, float]:
    """(low, high) metres: the smallest and the largest measured valid depth of ``frames`` ((0, inf)
    when none is valid)."""
    z = [measured.measured_depth(k) for k in frames]
    z = np.concatenate([a[a > 0].ravel() for a in z]) if z else np.zeros(0)
    if z.size == 0:
        return 0.0, float("inf")
    return float(z.min()), float(z.max())


def locally_flat(depth: np.ndarray, radius_px: int = 8, rel: float = 0.03, min_share: float = 0.3) -> np.ndarray:
    """(H, W) bool: hit pixels of the ideal ``depth`` (H, W, metres; 0 = no hit) whose whole
    (2 radius_px + 1)^2 neighbourhood is hit and stays within +-``rel`` of their own depth: away from
    depth edges and from steeply slanted surfaces. Block matching fattens foregrounds across both (a
    window's nearest depth wins: at grazing incidence the depth changes by several per cent within a
    window), lens shifts and mixed or flying pixels live there too: they are outliers for the
    closed-form starts of smooth errors (noise, biases). When fewer than ``min_share`` of the hit
    pixels stay (a cluttered or steep view) the neighbourhood shrinks to 3 px."""
    import cv2
    z = np.asarray(depth, np.float32)
    hit = z > 0
    out = hit
    for r in (radius_px, min(3, radius_px)):
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        zmin = cv2.erode(z, k, borderType=cv2.BORDER_REPLICATE)       # 0 beside a hole
        zmax = cv2.dilate(z, k, borderType=cv2.BORDER_REPLICATE)
        out = hit & (zmin >= z * (1.0 - rel)) & (zmax <= z * (1.0 + rel))
        if out.sum() >= min_share * max(int(hit.sum()), 1):
            break
    return out


def robust_std(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation (the std of a normal sample, outliers ignored)."""
    x = np.asarray(x, np.float64)
    if not x.size:
        return float("nan")
    return float(1.4826 * np.median(np.abs(x - np.median(x))))
