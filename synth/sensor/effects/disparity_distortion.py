"""Direct model: a learned per-pixel disparity distortion (Herrera et al. 2012, Smisek et al. 2011).

Real Kinect v1 devices show a fixed spatial pattern in their disparity error: a bowl that is
strongest in the image corners, often with vertical stripes, fading with distance. Herrera, Kannala
and Heikkila (2012, "Joint depth and color camera calibration with distortion correction")
correct it per pixel as ``d_corr = d + beta(u, v) exp(a0 - a1 d)`` on the raw disparity code;
Smisek et al. (2011) found the same pattern as the residual of a plane fit. The pattern is data,
not a formula, so this effect's ``beta`` map is a file (``.npy``) that ``sensor fit`` estimates
from measured sequences and stores beside the model JSON.

Model (disparity d = f b / z in pixels, as everywhere in realgap)::

    d' = d + strength * beta(u, v) * exp(-decay_per_px * (d_ref - d)),   d_ref = f b / reference_depth_m
    z' = f b / d'

``beta`` is the disparity error (px) at ``reference_depth_m``; the exponential makes it fade as the
disparity falls (the surface moves away) and grow as it rises (closer). Mapping to Herrera's raw
parameters: the raw Kinect code is an affine, decreasing function of d with 8 codes per pixel, so
Herrera's ``a1`` (per raw code) is ``decay_per_px / 8`` and ``exp(a0)`` is absorbed into ``beta``.

The map is stored on a coarse grid (by default one cell per 8 x 8 pixels of the image it was
fitted on) and bilinearly up-sampled to the image (OpenCV ``INTER_LINEAR``, cell centres
aligned): the coarse grid is the regularisation (the pattern is smooth on that scale in every
published calibration) and keeps the file small (30 kB for VGA). A map fitted on one resolution
applies to another by the same resampling (an approximation for cropped sensors: the map is
stretched over the cropped image, not cut).

``depth_bias.radial_disparity_px`` remains the parametric alternative (a pure r^2 bowl with no
decay); the lab's diagnosis tries both and reports both gains.
"""
from __future__ import annotations

import functools
import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError
from synth.sensor.registry import STAGE_DEPTH, Effect, Signature, param, register_effect

MAP_CELL_PX = 8
"""Side of one cell of a fitted map, pixels of the fitted image."""
MIN_PIXELS_PER_CELL = 12
"""Fewer measured samples in a cell (over all frames): the cell is filled from its neighbours."""
MAX_RESIDUAL_PX = 3.0
"""Disparity residuals larger than this (flying pixels, mismatches at edges) are left out of the fit."""


@dataclass
class DisparityDistortionParams:
    beta_map: str = param("", "")
    """Path of the ``.npy`` map (2-D float, disparity error in px at ``reference_depth_m``, on a
    coarse grid spanning the image); relative paths are relative to the model JSON's folder; empty
    = no map (the effect does nothing). Written by ``sensor fit``."""
    strength: float = param(1.0, "1", 0.0, 3.0)
    """Multiplier of the map (1 = as fitted; the lab refines it)."""
    decay_per_px: float = param(0.0, "1/px", 0.0, 0.2)
    """Fading of the error with the disparity (Herrera's a1 times 8): the error at disparity d is
    beta exp(-decay (d_ref - d)); 0 = the same disparity error at every distance."""
    reference_depth_m: float = param(1.0, "m", 0.2, 10.0)
    """Depth at which the map holds the error as stored."""


@functools.lru_cache(maxsize=16)
def _read_map(path: str, mtime_ns: int) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise ConfigError(f"effect 'disparity_distortion': beta_map {path}: file not found") from None
    except (ValueError, OSError) as e:
        raise ConfigError(f"effect 'disparity_distortion': beta_map {path}: not a numpy .npy array ({e})") from None
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1 or not np.issubdtype(a.dtype, np.floating):
        raise ConfigError(f"effect 'disparity_distortion': beta_map {path}: expected a 2-D float map, "
                          f"got shape {a.shape} {a.dtype}")
    if not np.isfinite(a).all():
        raise ConfigError(f"effect 'disparity_distortion': beta_map {path}: contains NaN or inf")
    a = a.astype(np.float32)
    a.setflags(write=False)
    return a


def load_map(path: str | os.PathLike) -> np.ndarray:
    """The coarse (Hg, Wg) float32 map in ``path`` (px; cached by path and modification time)."""
    p = str(Path(path))
    try:
        mt = os.stat(p).st_mtime_ns
    except FileNotFoundError:
        raise ConfigError(f"effect 'disparity_distortion': beta_map {p}: file not found") from None
    return _read_map(p, mt)


def upsample(grid: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 bilinear up-sampling of a coarse map (cell centres aligned with OpenCV)."""
    import cv2
    H, W = shape
    if grid.shape == (H, W):
        return grid.astype(np.float32, copy=False)
    return cv2.resize(np.ascontiguousarray(grid, np.float32), (int(W), int(H)), interpolation=cv2.INTER_LINEAR)


@functools.lru_cache(maxsize=8)
def _full_map(path: str, mtime_ns: int, shape: tuple[int, int]) -> np.ndarray:
    m = upsample(_read_map(path, mtime_ns), shape)
    m.setflags(write=False)
    return m


def save_map(grid: np.ndarray, folder: str | os.PathLike | None = None) -> Path:
    """Write ``grid`` as ``disparity_distortion-<hash>.npy`` (content-addressed, atomic) in ``folder``
    (default: realgap's folder in the system temp dir) and return the path."""
    grid = np.ascontiguousarray(grid, np.float32)
    h = hashlib.sha1(grid.tobytes() + str(grid.shape).encode()).hexdigest()[:16]
    folder = Path(folder) if folder is not None else Path(tempfile.gettempdir()) / "realgap-maps"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"disparity_distortion-{h}.npy"
    if not path.exists():
        tmp = path.with_suffix(f".tmp{os.getpid()}.npy")
        np.save(tmp, grid)
        os.replace(tmp, path)
    return path


def fill_and_smooth(values: np.ndarray, weight: np.ndarray, known: np.ndarray, smooth_cells: float = 0.7) -> np.ndarray:
    """Fill the cells where ``known`` is False smoothly from the known ones (normalised convolution
    at growing Gaussian scales: each unknown cell takes the weighted mean of its nearest known
    neighbourhood), then smooth the whole map with a Gaussian of ``smooth_cells`` cells.
    ``values``/``weight``: (Hg, Wg) cell estimates and their weights."""
    from scipy.ndimage import gaussian_filter
    v = np.where(known, values, 0.0).astype(np.float64)
    w = np.where(known, weight, 0.0).astype(np.float64)
    if not known.any():
        return np.zeros_like(v, dtype=np.float32)
    out = v.copy()
    todo = ~known
    sigma = 1.0
    while todo.any():
        num = gaussian_filter(v * w, sigma, mode="nearest")
        den = gaussian_filter(w, sigma, mode="nearest")
        ok = todo & (den > 1e-6 * w.max())
        out[ok] = num[ok] / den[ok]
        todo &= ~ok
        sigma *= 2.0
        if sigma > 4 * max(v.shape):
            out[todo] = float(np.average(v[known], weights=w[known]))
            break
    if smooth_cells > 0:
        out = gaussian_filter(out, smooth_cells, mode="nearest")
    return out.astype(np.float32)


def estimate_map(samples, fb: float, shape: tuple[int, int], reference_depth_m: float = 1.0,
                 cell_px: int = MAP_CELL_PX, decays=None) -> tuple[np.ndarray, float, dict]:
    """Least-squares estimate of (beta grid, decay) from disparity residuals.

    ``samples``: iterable of ``(u, v, r_px, d_px)`` arrays (pixel column, row, residual measured
    minus ideal disparity, ideal disparity); ``shape`` the image (H, W). For each decay on a grid
    the per-cell least-squares beta = sum(w r) / sum(w^2), w = exp(-decay (d_ref - d)), has the
    residual sum of squares sum r^2 - sum_cells (sum w r)^2 / sum w^2 in closed form; the decay
    with the least residual wins. Cells with fewer than MIN_PIXELS_PER_CELL samples are filled
    by :func:`fill_and_smooth`; every cell is shrunk towards 0 by a ridge of 2 samples' weight.
    Returns (grid, decay, info)."""
    H, W = shape
    gh, gw = -(-H // cell_px), -(-W // cell_px)
    cells, rs, ds = [], [], []
    for u, v, r, d in samples:
        cells.append((np.asarray(v) // cell_px) * gw + np.asarray(u) // cell_px)
        rs.append(np.asarray(r, np.float64))
        ds.append(np.asarray(d, np.float64))
    if not cells:
        raise ConfigError("disparity_distortion: no measured pixels to estimate the map from")
    c = np.concatenate(cells).astype(np.int64)
    r = np.concatenate(rs)
    d = np.concatenate(ds)
    n = np.bincount(c, minlength=gh * gw)
    d_ref = fb / float(reference_depth_m)
    decays = np.linspace(0.0, 0.2, 41) if decays is None else np.asarray(decays, float)
    sse = []
    for a in decays:
        w = np.exp(np.clip(-a * (d_ref - d), -30.0, 30.0))
        num = np.bincount(c, w * r, minlength=gh * gw)
        den = np.bincount(c, w * w, minlength=gh * gw)
        ok = den > 0
        sse.append(float((r * r).sum() - (num[ok] ** 2 / den[ok]).sum()))
    a = float(decays[int(np.argmin(sse))])
    w = np.exp(np.clip(-a * (d_ref - d), -30.0, 30.0))
    num = np.bincount(c, w * r, minlength=gh * gw)
    den = np.bincount(c, w * w, minlength=gh * gw)
    ridge = 2.0 * (den.sum() / max(n.sum(), 1))          # the weight of two average samples
    beta = num / (den + ridge)
    known = n >= MIN_PIXELS_PER_CELL
    grid = fill_and_smooth(beta.reshape(gh, gw), den.reshape(gh, gw), known.reshape(gh, gw))
    info = {"samples": int(n.sum()), "cells_observed": int(known.sum()), "cells": int(gh * gw),
            "decay_per_px": a, "rss_by_decay": dict(zip([float(x) for x in decays], sse))}
    return grid, a, info


@register_effect
class DisparityDistortion(Effect):
    """A fixed per-pixel disparity error that fades with distance (learned map, see the module
    docstring). No randomness: the same pixel at the same depth always gets the same error."""

    name = "disparity_distortion"
    SIGNATURE = Signature(
        "a fixed spatial pattern of the disparity error",
        "The median error per image block shows the same pattern in every frame (a bowl strongest in "
        "the corners, stripes), largest near the sensor in disparity terms; the current model's map is flat.",
        plot="radial_error_map")
    IDENTITY_PARAMS = {"strength": 0.0}
    Params = DisparityDistortionParams
    FITTABLE = {"strength": (0.0, 3.0), "decay_per_px": (0.0, 0.2)}
    FILE_PARAMS = ("beta_map",)
    sensor_types = ("structured_light", "active_stereo")
    stage = STAGE_DEPTH + 2

    def validate(self) -> None:
        super().validate()
        if self.params.beta_map:
            load_map(self.params.beta_map)       # a missing or bad file is a one-line error now

    def map_for(self, shape: tuple[int, int]) -> np.ndarray | None:
        """(H, W) float32 map (px) up-sampled to ``shape``, None when the model has no map."""
        if not self.params.beta_map:
            return None
        p = str(Path(self.params.beta_map))
        load_map(p)
        return _full_map(p, os.stat(p).st_mtime_ns, tuple(int(x) for x in shape))

    def apply(self, state, draw) -> None:
        p = self.params
        fb = state.preset.fb
        if not p.beta_map or p.strength == 0 or fb <= 0:
            return
        beta = self.map_for(state.shape)
        z = state.depth.astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            d = np.where(z > 0, fb / z, 0.0)
            e = p.strength * beta * np.exp(np.clip(-p.decay_per_px * (fb / p.reference_depth_m - d), -30.0, 30.0))
            d2 = d + e
            z2 = np.where((z > 0) & (d2 > 0), fb / d2, 0.0)
        state.depth = np.where(state.valid, z2, 0).astype(np.float32)
        state.valid &= state.depth > 0

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict:
        """The map and its decay from every loaded frame (not only the search frames: a per-pixel
        estimate needs every sample it can get), by :func:`estimate_map` on the residual disparity
        fb / z_measured - fb / z_ideal of the masked-in pixels; written to a content-addressed file
        in the system temp dir (``sensor fit`` copies it beside the model). Nothing when the
        sensor has no disparity (ToF)."""
        pre = config.preset
        fb = float(pre.fb)
        if fb <= 0 or len(measured) == 0:
            return {}
        try:
            ref = float(config.effect(cls.name).params.reference_depth_m)
        except ConfigError:
            ref = 1.0
        H, W = measured.intrinsics.height, measured.intrinsics.width
        rng = np.random.default_rng(0)

        from synth.sensor.effects._common import measured_samples

        def samples():
            for _, m, render, ok in measured_samples(measured):
                z = render.depth
                vv, uu = np.nonzero(ok & (m > 0))
                if vv.size > 60000:
                    keep = rng.choice(vv.size, 60000, replace=False)
                    vv, uu = vv[keep], uu[keep]
                d = fb / z[vv, uu].astype(np.float64)
                r = fb / m[vv, uu].astype(np.float64) - d
                good = np.abs(r) < MAX_RESIDUAL_PX
                yield uu[good], vv[good], r[good], d[good]
        try:
            grid, decay, _ = estimate_map(samples(), fb, (H, W), ref)
        except ConfigError:
            return {}
        path = save_map(grid)
        return {f"{cls.name}.beta_map": str(path), f"{cls.name}.decay_per_px": float(decay),
                f"{cls.name}.strength": 1.0}

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """How much of the measured per-block median error is a fixed spatial pattern: the spread
        (robust std over 16 px blocks) of the measured block medians against the current model's.

        Signature present: the measured spread exceeds the model's by >= 1 mm and by >= 30 %."""
        from synth.lab.signatures import radial_error_map
        obs = ctx.observations
        mm = radial_error_map(obs, "measured")
        ms = radial_error_map(obs, "simulated")
        a, b = mm[np.isfinite(mm)], ms[np.isfinite(ms)]
        if a.size < 6:
            return ctx.weak("pattern signature", gain, "too few image blocks with measured pixels")

        def spread(x):
            q = np.quantile(x, [0.25, 0.75]) if x.size else np.zeros(2)
            return float(q[1] - q[0]) / 1.349

        sm, ss = spread(a), spread(b)
        numbers = (f"the median error per 16 px block varies by {ctx.mm(sm)} (robust std) over the image, "
                   f"{ctx.mm(ss)} in the current model")
        if sm - ss < 0.001 or sm < 1.3 * ss:
            return ctx.weak("pattern signature", gain, numbers)
        return f"the error has a fixed spatial pattern: {numbers}."
