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
