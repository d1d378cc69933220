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


def measured_samples(measured, frames=None):
    """Yield, per frame of a :class:`synth.lab.measured.MeasuredSequence` (default every loaded
    frame), ``(k, measured depth, ideal RenderResult, usable)`` with ``usable`` (H, W) bool: the
    ideal geometry is there and, when the sequence has masks, inside the mask (what the lab
    compares). For the effects' closed-form ``fit_start`` estimates."""
    ks = range(len(measured)) if frames is None else frames
    for k in ks:
        m = measured.measured_depth(k)
        r = measured.render(k)
        ok = r.hit & (r.depth > 0)
        mask = measured.mask(k)
        if mask is not None:
            ok &= mask
        yield k, m, r, ok


def robust_std(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation (the std of a normal sample, outliers ignored)."""
    x = np.asarray(x, np.float64)
    if not x.size:
        return float("nan")
    return float(1.4826 * np.median(np.abs(x - np.median(x))))
