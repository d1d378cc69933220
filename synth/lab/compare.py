"""Compare a measured depth sequence with a simulated one: the robust ``gap`` and its breakdowns.

Inputs are plain arrays per frame (:class:`~synth.lab.features.FrameObservation`): measured
depth, simulated depth of the same frame, the ideal depth/normals/material ids rendered from the
reference geometry, and the intrinsics. Nothing here depends on the simulator or the renderer.

Definition of the gap
---------------------
Two noisy depth images of the same scene differ pixel by pixel even when the model is perfect,
so the gap compares *statistics* of the errors with respect to the ideal geometry, conditioned
on physical features, plus one spatial term.

Samples. Only pixels with ideal geometry (``ideal > 0``) take part (pixels outside the reference
model cannot be explained by a sensor model; the fraction of them that the sensor still
measures is reported as ``diagnostics.unmodelled_valid_fraction``). Per frame at most
``max_pixels_per_frame`` of them are drawn uniformly without replacement (seeded by
``(seed, frame position)``, the *same* pixels for measured and simulated).

Errors. For a valid pixel (depth > 0) the error is ``e = depth - ideal`` (metres), normalised by
the depth-dependent scale ``s(z) = a + b z^2`` (default a = 1 mm, b = 2 mm/m^2: roughly the
axial noise of a Kinect-class structured-light sensor, so one unit ~ one typical noise level; a
documented alternative is any a, b in :class:`CompareConfig`) and clipped to ``±error_clip``
(default 10) so that a few flying pixels or model-misalignment outliers cannot dominate:
``y = clip(e / s(z), -c, c)``.

Per bin. For every feature f (``distance``, ``incidence``, ``radial``, ``material``,
``edge_distance``, ``edge_shadow`` when a projector offset is known; see
:mod:`synth.lab.features`) the samples are binned by the feature value. In bin b with n_b
samples, invalid fractions p_m, p_s (measured, simulated) and valid normalised errors
{y_m}, {y_s}::

    term_b = w_err * min(1 - p_m, 1 - p_s) * W1({y_m}, {y_s}) + w_inv * |p_m - p_s|

W1 is the exact 1-D Wasserstein-1 distance between the two empirical distributions (the area
between their CDFs; it sees bias, spread and shape differences in units of s(z), and unlike a
KL/chi2 test it needs no histogram and stays finite for disjoint supports). It is weighted by
the fraction of pixels where both images have data and set to 0 when either side has fewer than
``min_valid_count`` valid samples (then the invalid term speaks). Bins with fewer than
``min_bin_count`` samples are left out (term = NaN). Defaults w_err = 1, w_inv = 2: a 10 %
difference in hole rate weighs like a 0.2 s(z) shift of the error distribution.

Per feature. ``T_f = sum_b n_b term_b / sum_b n_b`` (count-weighted mean over bins): the mean
per-pixel disagreement after conditioning on f. Conditioning does not hide a difference (with
equal valid counts per bin, convexity of W1 makes T_f's error part >= the W1 of the unbinned
distributions), and a feature that explains the error structure (e.g. distance for a far-range
bias) raises it; averaging over several features keeps the gap from depending on one binning.

Spatial term. Invalid pixels that are in the wrong *place* (a projector shadow on the wrong side
of an object, holes on the wrong surface) can keep every binned hole rate right. Per frame the
image is tiled into ``spatial_block_px`` blocks (default 8x8); in each block with at least a
quarter of its pixels on geometry, with invalid fractions q_m, q_s among its n geometry pixels::

    d = max(0, |q_m - q_s| - kappa * sqrt(2 q (1 - q) / n)),   q = (q_m + q_s) / 2

i.e. the hole-rate difference beyond what independent per-pixel dropout of the same rate
explains (kappa = 2 binomial standard deviations). ``S = sum n d / sum n`` over all blocks: the
fraction of geometry pixels whose validity is structurally misplaced. This replaces the per-pixel
``|XOR| / union`` of the valid masks, which is dominated by random dropout (two independent 5 %
hole patterns already give ~0.1).

Gap::

    gap = mean_{f in gap features with data} T_f  +  w_sp * S      (w_sp = 2 by default)

Properties (tested in ``tests/test_lab_compare.py``): gap(identical sequences) = 0 exactly;
two independent noise draws of the correct model give nearly the same gap (the floor comes only
from finite-sample W1, ~1/sqrt(bin size)); the gap grows as a simulated bias / noise scale /
hole rate moves away from the measured one; the noise-free ideal model scores worse than a model
with the right noise. The gap is pooled over all frames; ``frame_gaps`` apply the same formula
to each frame alone. Bias and spread per bin (median and IQR/1.349 of the raw errors, metres)
are reported in the breakdowns but do not enter the gap separately (W1 already contains them).

Noise floor. Each bin also reports ``noise_floor``, the term expected from sampling noise alone
when the model is right: ``w_err * min(1-p_m, 1-p_s) * 1.2884 sigma sqrt(1/n_a + 1/n_b) +
w_inv * sqrt(2/pi) sqrt(2 p (1-p) / n)`` (sigma: within-source std of y; p: pooled hole rate).
It does not enter the gap (which would lose strict monotonicity near the optimum) but decides
which bins and image blocks :func:`worst_regions` reports (term > 3x floor).

Cost: per frame, 4 exact distance transforms (edges) on the full image; then one float sort of
the pooled normalised errors and one integer (radix) sort per feature and grouping (pooled and
per frame). 24 VGA frames with the default 20 000 samples per frame: ~1.6 s on a loaded 2-core
machine (``fast``: ~0.6 s; ``exact``, all 7.4 M pixels: tens of seconds). Everything that depends
on the measured depth and the ideal geometry only (the sampled pixels, the distance transforms and
other feature values, the measured errors and block hole counts) can be kept between calls in a
:class:`CompareCache` (``compare(..., cache=...)``): a fit compares the same measured frames with
hundreds of simulations and then pays only for the simulated side (see ``benchmarks/bench_lab.py``).
"""
from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from data_tools.config import config_from_dict, config_to_dict
from data_tools.errors import ConfigError, FormatError, RealgapError
from synth.lab.features import (FEATURES, CategoricalValues, FeatureConfig,
                                FrameFeatures, FrameObservation, make_feature,
                                radial_max_px)

__all__ = ["CompareConfig", "CompareResult", "CompareCache", "Region", "PRESETS", "compare_preset", "compare",
           "error_map", "validity_map", "worst_bins", "worst_blocks", "worst_regions",
           "load_result", "error_scale_m", "wasserstein1", "FrameObservation",
           "VALIDITY_LABELS", "BREAKDOWN_FEATURES"]

BREAKDOWN_FEATURES = ("distance", "incidence", "radial", "material", "edge_distance")
"""Features always present as keys of ``metrics.json`` ``breakdowns`` (others when available)."""

METRICS_FILE = "metrics.json"
CONFIG_FILE = "compare_config.json"


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------

@dataclass
class CompareConfig:
    """How the comparison samples, bins and weighs (see the module docstring for the formula)."""

    max_pixels_per_frame: int | None = 20000
    """Random (seeded) geometry pixels used per frame for the binned terms; None = all pixels."""
    seed: int = 0
    """Seed of the pixel subsets (frame k uses the stream (seed, k))."""
    gap_features: tuple[str, ...] = ("distance", "incidence", "radial", "material",
                                     "edge_distance", "edge_shadow")
    """Features whose terms are averaged into the gap (those without data are skipped)."""
    extra_features: tuple[str, ...] = ("incidence_projector",)
    """Features computed for the breakdowns only."""
    scale_a_m: float = 0.001
    """Constant part a of the error scale s(z) = a + b z^2, metres."""
    scale_b_per_m: float = 0.002
    """Quadratic coefficient b of s(z) = a + b z^2, 1/metre (so b z^2 is metres)."""
    error_clip: float = 10.0
    """Normalised errors e / s(z) are clipped to +-error_clip before W1."""
    weight_error: float = 1.0
    """w_err: weight of the W1 term (units of s(z))."""
    weight_invalid: float = 2.0
    """w_inv: weight of the invalid-fraction difference."""
    weight_spatial: float = 2.0
    """w_sp: weight of the spatial (misplaced holes) term."""
    min_bin_count: int = 20
    """Bins with fewer sampled geometry pixels are left out."""
    min_valid_count: int = 10
    """W1 needs at least this many valid samples on both sides (else it counts 0)."""
    spatial_block_px: int = 8
    """Block size (pixels) of the spatial term."""
    spatial_kappa: float = 2.0
    """Binomial standard deviations of hole-rate difference forgiven per block."""
    features: FeatureConfig = field(default_factory=FeatureConfig)
    """How features are computed and binned."""

    def validate(self) -> "CompareConfig":
        if self.max_pixels_per_frame is not None and int(self.max_pixels_per_frame) < 1:
            raise ConfigError(f"max_pixels_per_frame must be >= 1 or None, got {self.max_pixels_per_frame}")
        for name in (*self.gap_features, *self.extra_features):
            if name not in FEATURES:
                raise ConfigError(f"unknown lab feature {name!r}; known: {', '.join(FEATURES)}")
        if self.scale_a_m < 0 or self.scale_b_per_m < 0 or self.scale_a_m + self.scale_b_per_m <= 0:
            raise ConfigError("error scale s(z) = a + b z^2 needs a, b >= 0, not both 0")
        for name in ("error_clip", "weight_error", "weight_invalid", "weight_spatial", "spatial_kappa"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{name} must be a finite number >= 0, got {v}")
        if self.error_clip <= 0:
            raise ConfigError("error_clip must be > 0")
        if self.min_bin_count < 1 or self.min_valid_count < 1 or self.spatial_block_px < 1:
            raise ConfigError("min_bin_count, min_valid_count and spatial_block_px must be >= 1")
        self.features.validate()
        return self

    def feature_names(self) -> list[str]:
        """Gap and extra features in registry order."""
        wanted = set(self.gap_features) | set(self.extra_features)
        return [n for n in FEATURES if n in wanted]

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "CompareConfig":
        return config_from_dict(cls, d, "compare config")


PRESETS: dict[str, CompareConfig] = {
    "default": CompareConfig(),
    "fast": CompareConfig(max_pixels_per_frame=5000),
    "exact": CompareConfig(max_pixels_per_frame=None),
}
"""Named configurations: ``default`` (20k samples/frame), ``fast`` (5k), ``exact`` (all pixels)."""


def compare_preset(name: str) -> CompareConfig:
    """A fresh copy of a named preset."""
    if name not in PRESETS:
        raise ConfigError(f"unknown compare preset {name!r}; known: {', '.join(PRESETS)}")
    return CompareConfig.from_dict(PRESETS[name].to_dict())


def error_scale_m(z_m: np.ndarray, config: CompareConfig) -> np.ndarray:
    """s(z) = a + b z^2 in metres for ideal depths z (metres)."""
    z = np.asarray(z_m, dtype=np.float64)
    return config.scale_a_m + config.scale_b_per_m * z * z


# --------------------------------------------------------------------------------------------
# Grouped statistics (vectorised over bins)
# --------------------------------------------------------------------------------------------

def wasserstein1(a: np.ndarray, b: np.ndarray) -> float:
    """Exact 1-D Wasserstein-1 distance between two empirical samples (any sizes)."""
    a = np.asarray(a, dtype=np.float64).ravel()
    b = np.asarray(b, dtype=np.float64).ravel()
    if a.size == 0 or b.size == 0:
        raise RealgapError("wasserstein1 needs two non-empty samples")
    w, _, _ = _Pooled(a, np.ones(a.size, bool), b, np.ones(b.size, bool),
                      index_a=np.zeros(a.size, np.int64), index_b=np.zeros(b.size, np.int64)).w1(
        np.zeros(1, np.int64), 1)
    return float(w[0])


def _sort_key_dtype(nkeys: int):
    return np.int16 if nkeys < 32767 else np.int64


class _Pooled:
    """Valid samples of both sources sorted once by value; W1 per group by one integer sort.

    Sample k of source a has value ya[k] and belongs to ``index_a[k]`` (a row of the key array
    passed to :meth:`w1`); same for b.
    """

    def __init__(self, ya, valid_a, yb, valid_b, index_a=None, index_b=None):
        ia = np.flatnonzero(valid_a)
        ib = np.flatnonzero(valid_b)
        vals = np.concatenate([ya[ia], yb[ib]])
        order = np.argsort(vals)  # ties: any order (zero-width steps)
        self.v = vals[order]
        self.src = np.concatenate([np.zeros(ia.size, bool), np.ones(ib.size, bool)])[order]
        rows_a = ia if index_a is None else index_a[ia]
        rows_b = ib if index_b is None else index_b[ib]
        self.row = np.concatenate([rows_a, rows_b])[order]

    def w1(self, keys: np.ndarray, nkeys: int):
        """(W1 per key, valid count a per key, valid count b per key); keys (rows,) int, -1 = out.

        Sorted by (key, value), each element carries the integer weight +n_b (source a) or -n_a
        (source b) of its key, so the running sum is n_a n_b (F_a - F_b) inside a key and returns
        exactly to 0 at its end (integer arithmetic: identical samples give exactly 0); W1 is the
        sum of |F_a - F_b| times the gap to the next value. Keys with an empty side get zero
        weights (their W1 is reported as 0 and masked by the caller).
        """
        dt = _sort_key_dtype(nkeys + 1)
        kk = keys.astype(dt)
        kk[kk < 0] = nkeys                                   # 'out' group, weight 0
        k = kk[self.row]
        perm = np.argsort(k, kind="stable")                 # radix sort for int16
        k = k[perm]
        s = self.src[perm]
        v = self.v[perm]
        nb = np.bincount(k, weights=s, minlength=nkeys + 1).round()
        na = np.bincount(k, minlength=nkeys + 1) - nb
        both = (na > 0) & (nb > 0)
        both[nkeys] = False
        na = na.astype(np.int64)
        nb = nb.astype(np.int64)
        # integer weights n_b (a) and -n_a (b): the running sum is n_a n_b (F_a - F_b); it stays an
        # integer below 2**53 (n_a n_b < 1e15), so float64 holds it exactly
        table = np.zeros(2 * (nkeys + 1))
        table[0::2] = np.where(both, nb, 0)
        table[1::2] = np.where(both, -na, 0)
        idx = k.astype(np.int32)
        idx <<= 1
        idx += s
        w = table[idx]
        if k.size < 2:
            return np.zeros(nkeys), na[:nkeys], nb[:nkeys]
        norm = np.where(both, 1.0 / np.maximum(na * nb, 1), 0.0)
        d = np.cumsum(w)[:-1]
        np.abs(d, out=d)
        d *= norm[k[:-1]]
        d *= np.diff(v)
        d[k[1:] != k[:-1]] = 0.0
        out = np.bincount(k[:-1], weights=d, minlength=nkeys + 1)[:nkeys]
        return out, na[:nkeys], nb[:nkeys]


class _Sorted:
    """Valid raw errors of one source sorted by value, for per-group quantiles."""

    def __init__(self, e, valid):
        rows = np.flatnonzero(valid)
        vals = e[rows]
        order = np.argsort(vals)  # ties: any order (zero-width steps)
        self.v = vals[order]
        self.row = rows[order]

    def quantiles(self, keys, nkeys, qs=(0.25, 0.5, 0.75)) -> np.ndarray:
        """(len(qs), nkeys) linear-interpolated quantiles per key (NaN for empty keys)."""
        kk = keys.astype(_sort_key_dtype(nkeys + 1))
        kk[kk < 0] = nkeys
        k = kk[self.row]
        perm = np.argsort(k, kind="stable")
        k, v = k[perm], self.v[perm]
        n = np.bincount(k, minlength=nkeys + 1)[:nkeys]
        start = np.searchsorted(k, np.arange(nkeys))
        out = np.full((len(qs), nkeys), np.nan)
        ok = n > 0
        if not ok.any():
            return out
        for i, q in enumerate(qs):
            pos = start[ok] + q * (n[ok] - 1)
            lo = np.floor(pos).astype(np.int64)
            hi = np.minimum(lo + 1, start[ok] + n[ok] - 1)
            out[i, ok] = v[lo] + (pos - lo) * (v[hi] - v[lo])
        return out


W1_NULL_CONSTANT = 1.2884
"""E[W1] between two samples (sizes n, m) of one normal distribution of std sigma is
``1.2884 sigma sqrt(1/n + 1/m)`` (sqrt(2/pi) * integral of sqrt(Phi (1 - Phi)); checked by
simulation in the tests)."""


def _noise_floor(n, pm, ps, na, nb, var_w, cfg: CompareConfig):
    """Expected bin term when both images come from the same process (sampling noise only).

    W1 part: ``W1_NULL_CONSTANT * sigma * sqrt(1/n_a + 1/n_b)`` with sigma the within-source
    std of the clipped normalised errors (``var_w``); invalid part: E|p_a - p_b| =
    sqrt(2/pi) sqrt(2 p (1 - p) / n) at the pooled hole rate p.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        w1_ok = (na >= cfg.min_valid_count) & (nb >= cfg.min_valid_count)
        both = np.minimum(1 - pm, 1 - ps)
        e = W1_NULL_CONSTANT * np.sqrt(np.maximum(var_w, 0)) * np.sqrt(1 / np.maximum(na, 1) + 1 / np.maximum(nb, 1))
        p = 0.5 * (pm + ps)
        i = math.sqrt(2 / math.pi) * np.sqrt(2 * p * (1 - p) / n)
    floor = cfg.weight_error * both * np.where(w1_ok, e, 0.0) + cfg.weight_invalid * i
    return np.where(n >= cfg.min_bin_count, floor, np.nan)


def _within_var(keys, nkeys, ym, vm, ys, vs):
    """Pooled within-source variance of the (clipped, normalised) errors per key."""
    out_s = np.zeros(nkeys)
    out_n = np.zeros(nkeys)
    for y, v in ((ym, vm), (ys, vs)):
        sel = v & (keys >= 0)
        k = keys[sel]
        yy = y[sel]
        c = np.bincount(k, minlength=nkeys).astype(np.float64)
        s1 = np.bincount(k, weights=yy, minlength=nkeys)
        s2 = np.bincount(k, weights=yy * yy, minlength=nkeys)
        with np.errstate(invalid="ignore", divide="ignore"):
            out_s += np.where(c > 0, s2 - s1 * s1 / np.maximum(c, 1), 0.0)
        out_n += np.maximum(c - 1, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(out_n > 0, out_s / out_n, np.nan)


def _bin_terms(n, inv_m, inv_s, w1, na, nb, cfg: CompareConfig):
    """Per-bin arrays: p_m, p_s, w1 (NaN where not computed), invalid term, term (NaN = left out)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        pm = inv_m / n
        ps = inv_s / n
    w1_ok = (na >= cfg.min_valid_count) & (nb >= cfg.min_valid_count)
    w1v = np.where(w1_ok, w1, np.nan)
    both = np.minimum(1 - pm, 1 - ps)
    err_term = cfg.weight_error * both * np.where(w1_ok, w1, 0.0)
    inv_term = cfg.weight_invalid * np.abs(pm - ps)
    term = err_term + inv_term
    used = n >= cfg.min_bin_count
    return pm, ps, w1v, np.where(used, err_term, np.nan), np.where(used, inv_term, np.nan), np.where(used, term, np.nan)


def _weighted_mean(term, n):
    ok = np.isfinite(term)
    tot = n[ok].sum()
    return float((term[ok] * n[ok]).sum() / tot) if tot > 0 else float("nan")


# --------------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------------

@dataclass
class _Samples:
    frame: np.ndarray
    z: np.ndarray
    err_m: np.ndarray
    err_s: np.ndarray
    valid_m: np.ndarray
    valid_s: np.ndarray
    values: dict            # feature -> float array (numeric) or int codes (categorical)
    categories: dict        # categorical feature -> list of names
    spatial: np.ndarray     # (F, 2): sum n*d, sum n per frame
    skipped: dict
    diagnostics: dict


def _blocksum(mask: np.ndarray, B: int) -> np.ndarray:
    """Sum of ``mask`` over B x B image blocks (the image zero-padded to whole blocks)."""
    h, w = mask.shape
    H, W = -(-h // B) * B, -(-w // B) * B
    p = np.zeros((H, W), np.int32)
    p[:h, :w] = mask
    return p.reshape(H // B, B, W // B, B).sum(axis=(1, 3))


@dataclass
class _FrameStatic:
    """Everything :func:`compare` derives from one frame's measured depth and ideal geometry
    alone (independent of the simulated depth): the sampled pixels, their ideal depth, measured
    errors and feature values (the edge distance transforms are computed here), and the
    measured side of the spatial term."""

    geom: np.ndarray          # (H, W) bool, ideal > 0
    flat: np.ndarray          # (N,) sampled flat pixel indices (sorted)
    z: np.ndarray             # (N,) ideal depth, metres
    err_m: np.ndarray         # (N,) measured - ideal, metres; NaN where invalid
    values: dict              # feature -> (N,) float array | CategoricalValues | None (unavailable)
    block_n: np.ndarray       # (by, bx) float geometry pixels per spatial block
    block_inv_m: np.ndarray   # (by, bx) int measured holes on geometry per block
    counts: tuple             # (no-geometry px, no-geometry px measured valid, geometry px)


def _frame_static(i: int, o: FrameObservation, cfg: CompareConfig, feats: dict) -> _FrameStatic:
    geom = o.ideal > 0
    vm = o.measured > 0
    ng = ~geom
    B = int(cfg.spatial_block_px)
    flat = np.flatnonzero(geom.ravel())
    m = cfg.max_pixels_per_frame
    if m is not None and flat.size > m:
        rng = np.random.default_rng([int(cfg.seed), i])
        flat = np.sort(rng.choice(flat, size=int(m), replace=False))
    z = o.ideal.reshape(-1)[flat].astype(np.float64)
    me = o.measured.reshape(-1)[flat].astype(np.float64)
    ff = FrameFeatures(o, cfg.features)
    values = {}
    for name, feat in feats.items():
        values[name] = feat.values(ff, flat) if feat.available(ff) else None
    return _FrameStatic(geom, flat, z, np.where(me > 0, me - z, np.nan), values,
                        _blocksum(geom, B).astype(np.float64), _blocksum(geom & ~vm, B),
                        (int(ng.sum()), int((ng & vm).sum()), int(geom.sum())))


class CompareCache:
    """Per-frame cache of what :func:`compare` derives from the measured depth and the ideal
    geometry alone (sampled pixels, feature values incl. the 4 edge distance transforms,
    measured errors, measured block hole counts), for callers that compare the *same* measured
    frames with many simulations (a fit: hundreds of comparisons).

    An entry is keyed by the frame's position in the observation list and the settings that
    shape it (pixel count, seed, features), and is used only when the frame's ``measured``,
    ``ideal``, ``normals`` and ``material_ids`` are the *same array objects* as when it was
    stored (and intrinsics, projector offset and material table are equal); the entry holds
    references to them, so an id cannot be reused while it lives. The arrays must not be
    modified in place while cached (:class:`~synth.lab.measured.MeasuredSequence` never does).
    With or without the cache :func:`compare` returns identical results (tested).

    ``max_entries`` bounds the memory (least recently used entries are dropped; an entry holds
    ~10 arrays of ``max_pixels_per_frame`` values plus an (H, W) mask: ~0.6 MB at 4000 samples
    of a VGA frame, ~2 MB at 20000).
    """

    def __init__(self, max_entries: int = 96):
        from collections import OrderedDict
        self.max_entries = int(max_entries)
        self._entries: OrderedDict = OrderedDict()
        self.hits = 0
        """Lookups served from the cache."""
        self.misses = 0
        """Lookups that computed (and stored) an entry."""

    @staticmethod
    def _settings(cfg: CompareConfig) -> tuple:
        return (cfg.max_pixels_per_frame, int(cfg.seed), int(cfg.spatial_block_px),
                json.dumps(cfg.features.to_dict(), sort_keys=True), tuple(cfg.feature_names()))

    def frame(self, i: int, o: FrameObservation, cfg: CompareConfig, feats: dict) -> _FrameStatic:
        key = (int(i), self._settings(cfg))
        e = self._entries.get(key)
        if e is not None:
            src, static = e
            if (src[0] is o.measured and src[1] is o.ideal and src[2] is o.normals and src[3] is o.material_ids
                    and src[4] == (o.intrinsics, o.projector_offset_m, dict(o.material_names))):
                self._entries.move_to_end(key)
                self.hits += 1
                return static
        static = _frame_static(i, o, cfg, feats)
        self.misses += 1
        self._entries[key] = ((o.measured, o.ideal, o.normals, o.material_ids,
                               (o.intrinsics, o.projector_offset_m, dict(o.material_names))), static)
        self._entries.move_to_end(key)
        while len(self._entries) > self.max_entries:
            self._entries.popitem(last=False)
        return static

    def clear(self) -> None:
        self._entries.clear()

    def __len__(self) -> int:
        return len(self._entries)


def _collect(obs: list[FrameObservation], cfg: CompareConfig, feats: dict,
             cache: CompareCache | None = None) -> _Samples:
    frames, zs, ems, ess, values, cats = [], [], [], [], {k: [] for k in feats}, {}
    cat_index: dict[str, dict[str, int]] = {}
    available = {k: False for k in feats}
    spatial = np.zeros((len(obs), 2))
    unmod = np.zeros(4)
    for i, o in enumerate(obs):
        st = cache.frame(i, o, cfg, feats) if cache is not None else _frame_static(i, o, cfg, feats)
        geom = st.geom
        vs = o.simulated > 0
        # spatial term (module docstring): hole-rate difference per block beyond binomial noise
        n = st.block_n
        with np.errstate(invalid="ignore", divide="ignore"):
            qm, qs = st.block_inv_m / n, _blocksum(geom & ~vs, int(cfg.spatial_block_px)) / n
            q = 0.5 * (qm + qs)
            thr = cfg.spatial_kappa * np.sqrt(2.0 * q * (1.0 - q) / n)
            d = np.maximum(0.0, np.abs(qm - qs) - thr)
        ok = n >= max(1.0, cfg.spatial_block_px ** 2 / 4.0)
        n = np.where(ok, n, 0.0)
        d = np.where(ok, d, 0.0)
        spatial[i] = ((n * d).sum(), n.sum())
        ng_count, ng_vm, geom_count = st.counts
        unmod += (ng_count, ng_vm, int(np.count_nonzero(vs)) - int(np.count_nonzero(vs & geom)), geom_count)
        flat = st.flat
        se = o.simulated.reshape(-1)[flat].astype(np.float64)
        frames.append(np.full(flat.size, i, np.int32))
        zs.append(st.z)
        ems.append(st.err_m)
        ess.append(np.where(se > 0, se - st.z, np.nan))
        for name, feat in feats.items():
            v = st.values[name]
            if v is None:
                values[name].append(np.full(flat.size, -1 if feat.categorical else np.nan))
                continue
            available[name] = True
            if feat.categorical:
                assert isinstance(v, CategoricalValues)
                idx = cat_index.setdefault(name, {})
                lut = np.array([idx.setdefault(s, len(idx)) for s in v.names] + [-1], np.int64)
                values[name].append(lut[np.where(v.codes >= 0, v.codes, len(v.names))])
            else:
                values[name].append(np.asarray(v, dtype=np.float64))
    for name, idx in cat_index.items():
        cats[name] = list(idx)
    skipped = {}
    for name, ok in available.items():
        if not ok:
            reason = ("needs projector_offset_m with an x/y component"
                      if name in ("edge_shadow", "incidence_projector") else "not available for these frames")
            skipped[name] = reason
    diag = {
        "geometry_pixels": int(unmod[3]),
        "no_geometry_pixels": int(unmod[0]),
        "unmodelled_valid_fraction": {
            "measured": float(unmod[1] / unmod[0]) if unmod[0] else 0.0,
            "simulated": float(unmod[2] / unmod[0]) if unmod[0] else 0.0},
    }
    cat = lambda xs, dt: np.concatenate(xs) if xs else np.zeros(0, dt)  # noqa: E731
    em, es = cat(ems, np.float64), cat(ess, np.float64)
    return _Samples(cat(frames, np.int32), cat(zs, np.float64), em, es, np.isfinite(em),
                    np.isfinite(es), {k: cat(v, np.float64) for k, v in values.items()}, cats,
                    spatial, skipped, diag)


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------

def _clean(x):
    """JSON-safe copy: NaN/inf -> None, numpy -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    return x


def _nan(x):
    """Inverse of :func:`_clean` for numeric lists: None -> NaN."""
    if isinstance(x, list):
        return [_nan(v) for v in x]
    return float("nan") if x is None else x


_NUMERIC_STAT_KEYS = ("bias", "std", "invalid_fraction")


@dataclass
class CompareResult:
    """Outcome of :func:`compare`; ``to_json()`` is the content of ``metrics.json``."""

    gap: float
    """The gap (see the module docstring); 0 = statistically indistinguishable."""
    feature_terms: dict[str, float]
    """T_f per computed feature (NaN when no bin had data)."""
    gap_features: list[str]
    """Features whose T_f entered the gap."""
    spatial_term: float
    """S, the fraction of geometry pixels with structurally misplaced validity."""
    breakdowns: dict[str, dict]
    """Per feature: bins, bin labels, measured/simulated statistics per bin, W1, terms."""
    frame_gaps: list[float]
    """Gap of each frame alone (same formula), in input order."""
    frame_indices: list[int]
    """``FrameObservation.index`` of each frame."""
    n_samples: int
    """Number of sampled geometry pixels over all frames."""
    config: dict
    """Effective :class:`CompareConfig` as a dict."""
    diagnostics: dict = field(default_factory=dict)
    """Counts and rates that do not enter the gap (unmodelled geometry, overall hole rates)."""
    skipped_features: dict[str, str] = field(default_factory=dict)
    """Feature -> why it has no data."""
    effects: list[str] = field(default_factory=list)
    """Names of the simulator effects that produced the simulated sequence (for the history)."""
    label: str | None = None
    """Free text describing the run."""

    def to_json(self) -> dict:
        return _clean({
            "gap": self.gap, "spatial_term": self.spatial_term,
            "feature_terms": self.feature_terms, "gap_features": self.gap_features,
            "breakdowns": self.breakdowns, "frame_gaps": self.frame_gaps,
            "frame_indices": self.frame_indices, "n_samples": self.n_samples,
            "diagnostics": self.diagnostics, "skipped_features": self.skipped_features,
            "effects": self.effects, "label": self.label, "config": self.config})

    @classmethod
    def from_json(cls, d: dict, path: str | os.PathLike | None = None) -> "CompareResult":
        if not isinstance(d, dict) or "gap" not in d or "breakdowns" not in d:
            raise FormatError(path, "not a sensor-lab metrics file (needs 'gap' and 'breakdowns')")
        try:
            bd = {}
            for name, b in d["breakdowns"].items():
                b = dict(b)
                if b.get("edges") is not None:
                    e = list(b["edges"])
                    if e and e[0] is None:
                        e[0] = -math.inf
                    if e and e[-1] is None:
                        e[-1] = math.inf
                    b["edges"] = e
                for side in ("measured", "simulated"):
                    b[side] = {k: (_nan(v) if k in _NUMERIC_STAT_KEYS else v) for k, v in b[side].items()}
                for k in ("w1", "error_term", "invalid_term", "term", "noise_floor", "centres"):
                    if k in b:
                        b[k] = _nan(b[k])
                b["feature_term"] = _nan(b.get("feature_term"))
                bd[name] = b
            return cls(
                gap=float(_nan(d["gap"])), feature_terms={k: _nan(v) for k, v in d.get("feature_terms", {}).items()},
                gap_features=list(d.get("gap_features", [])), spatial_term=float(_nan(d.get("spatial_term"))),
                breakdowns=bd, frame_gaps=_nan(list(d.get("frame_gaps", []))),
                frame_indices=[int(x) for x in d.get("frame_indices", [])],
                n_samples=int(d.get("n_samples", 0)), config=d.get("config", {}),
                diagnostics=d.get("diagnostics", {}), skipped_features=d.get("skipped_features", {}),
                effects=list(d.get("effects", [])), label=d.get("label"))
        except (TypeError, ValueError, KeyError, AttributeError) as e:
            raise FormatError(path, f"malformed sensor-lab metrics ({e})") from None

    def save(self, out_dir: str | os.PathLike, header: dict | None = None) -> Path:
        """Write ``out_dir/metrics.json`` (and the effective config as ``compare_config.json``),
        atomically; ``header``: the result header (:mod:`data_tools.results`) written with it."""
        from data_tools.results import atomic_write_json, write_result
        out = Path(out_dir)
        atomic_write_json(out / CONFIG_FILE, _clean(self.config))
        if header is None:
            return atomic_write_json(out / METRICS_FILE, self.to_json(), indent=1, allow_nan=False)
        return write_result(out / METRICS_FILE, header, self.to_json(), indent=1, allow_nan=False)


def load_result(path: str | os.PathLike) -> CompareResult:
    """Read a ``metrics.json`` (or the folder holding it)."""
    p = Path(path)
    if p.is_dir():
        p = p / METRICS_FILE
    try:
        d = json.loads(p.read_text())
    except FileNotFoundError:
        raise FormatError(p, "file not found") from None
    except json.JSONDecodeError as e:
        raise FormatError(p, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    return CompareResult.from_json(d, p)


# --------------------------------------------------------------------------------------------
# The comparison
# --------------------------------------------------------------------------------------------

def _check_observations(observations) -> list[FrameObservation]:
    obs = list(observations)
    if not obs:
        raise RealgapError("compare: no frames given")
    for k, o in enumerate(obs):
        if not isinstance(o, FrameObservation):
            raise RealgapError(f"compare: item {k} is a {type(o).__name__}, not a FrameObservation")
    return obs


def compare(observations: Sequence[FrameObservation], config: CompareConfig | None = None, *,
            effects: Sequence[str] = (), label: str | None = None,
            cache: CompareCache | None = None) -> CompareResult:
    """Compare measured and simulated depth of the same frames; see the module docstring.

    ``cache``: a :class:`CompareCache` to reuse what depends on the measured depth and the ideal
    geometry only (for repeated comparisons of the same measured frames; same result)."""
    cfg = (config or CompareConfig()).validate()
    obs = _check_observations(observations)
    feats = {name: make_feature(name, cfg.features) for name in cfg.feature_names()}
    smp = _collect(obs, cfg, feats, cache)
    nf = len(obs)
    if smp.z.size == 0:
        raise RealgapError("compare: no frame has ideal geometry (ideal depth is 0 everywhere)")

    scale = error_scale_m(smp.z, cfg)
    c = cfg.error_clip
    ym = np.clip(smp.err_m / scale, -c, c)
    ys = np.clip(smp.err_s / scale, -c, c)
    pooled = _Pooled(ym, smp.valid_m, ys, smp.valid_s)
    sorted_m = _Sorted(smp.err_m, smp.valid_m)
    sorted_s = _Sorted(smp.err_s, smp.valid_s)
    inv_m_w = (~smp.valid_m).astype(np.float64)
    inv_s_w = (~smp.valid_s).astype(np.float64)

    breakdowns: dict[str, dict] = {}
    feature_terms: dict[str, float] = {}
    frame_terms: dict[str, np.ndarray] = {}
    skipped = dict(smp.skipped)
    for name, feat in feats.items():
        if name in skipped:
            continue
        vals = smp.values[name]
        if feat.categorical:
            labels = smp.categories.get(name, [])
            binning = None
            b = vals.astype(np.int64)
        else:
            binning = feat.binning()
            labels = list(binning.labels)
            b = binning.assign(vals)
        k = len(labels)
        if k == 0 or not (b >= 0).any():
            skipped[name] = "no pixel falls in any bin"
            continue
        inb = b >= 0
        n = np.bincount(b[inb], minlength=k).astype(np.float64)
        im = np.bincount(b[inb], weights=inv_m_w[inb], minlength=k)
        is_ = np.bincount(b[inb], weights=inv_s_w[inb], minlength=k)
        w1, na, nb = pooled.w1(b, k)
        pm, ps, w1v, et, it, term = _bin_terms(n, im, is_, w1, na, nb, cfg)
        floor = _noise_floor(n, pm, ps, na, nb, _within_var(b, k, ym, smp.valid_m, ys, smp.valid_s), cfg)
        qm = sorted_m.quantiles(b, k)
        qs = sorted_s.quantiles(b, k)
        qm[:, na < cfg.min_valid_count] = np.nan   # no bias/std from a handful of pixels
        qs[:, nb < cfg.min_valid_count] = np.nan
        ft = _weighted_mean(term, n)
        feature_terms[name] = ft
        bd = {
            "title": feat.title, "unit": feat.unit, "categorical": feat.categorical,
            "labels": labels,
            "edges": list(binning.edges) if binning is not None else None,
            "centres": binning.centres.tolist() if binning is not None else None,
            "measured": {"bias": qm[1].tolist(), "std": ((qm[2] - qm[0]) / 1.349).tolist(),
                         "invalid_fraction": pm.tolist(), "count": n.astype(int).tolist(),
                         "valid_count": na.astype(int).tolist()},
            "simulated": {"bias": qs[1].tolist(), "std": ((qs[2] - qs[0]) / 1.349).tolist(),
                          "invalid_fraction": ps.tolist(), "count": n.astype(int).tolist(),
                          "valid_count": nb.astype(int).tolist()},
            "w1": w1v.tolist(), "error_term": et.tolist(), "invalid_term": it.tolist(),
            "term": term.tolist(), "noise_floor": floor.tolist(), "feature_term": ft, "in_gap": False,
        }
        if name == "radial" and len({o.intrinsics for o in obs}) == 1:
            rmax = radial_max_px(obs[0].intrinsics)
            bd["edges_px"] = [e * rmax for e in binning.edges]
        breakdowns[name] = bd
        if name not in cfg.gap_features:
            continue
        # per frame: keys frame * k + bin
        fk = np.where(inb, smp.frame.astype(np.int64) * k + b, -1)
        nkeys = nf * k
        n2 = np.bincount(fk[inb], minlength=nkeys).astype(np.float64)
        im2 = np.bincount(fk[inb], weights=inv_m_w[inb], minlength=nkeys)
        is2 = np.bincount(fk[inb], weights=inv_s_w[inb], minlength=nkeys)
        w12, na2, nb2 = pooled.w1(fk, nkeys)
        t2 = _bin_terms(n2, im2, is2, w12, na2, nb2, cfg)[5].reshape(nf, k)
        n2 = n2.reshape(nf, k)
        frame_terms[name] = np.array([_weighted_mean(t2[i], n2[i]) for i in range(nf)])

    gap_feats = [f for f in cfg.feature_names() if f in cfg.gap_features and f in feature_terms
                 and math.isfinite(feature_terms[f])]
    for f in gap_feats:
        breakdowns[f]["in_gap"] = True
    tot_n = smp.spatial[:, 1].sum()
    spatial = float(smp.spatial[:, 0].sum() / tot_n) if tot_n > 0 else 0.0
    mean_t = float(np.mean([feature_terms[f] for f in gap_feats])) if gap_feats else 0.0
    gap = mean_t + cfg.weight_spatial * spatial

    frame_gaps = []
    for i in range(nf):
        ts = [frame_terms[f][i] for f in gap_feats if math.isfinite(frame_terms[f][i])]
        si = smp.spatial[i, 0] / smp.spatial[i, 1] if smp.spatial[i, 1] > 0 else 0.0
        frame_gaps.append(float(np.mean(ts)) + cfg.weight_spatial * si if ts else float("nan"))

    diag = dict(smp.diagnostics)
    diag["sampled_invalid_fraction"] = {
        "measured": float(1 - smp.valid_m.mean()) if smp.valid_m.size else float("nan"),
        "simulated": float(1 - smp.valid_s.mean()) if smp.valid_s.size else float("nan")}
    return CompareResult(gap=float(gap), feature_terms=feature_terms, gap_features=gap_feats,
                         spatial_term=spatial, breakdowns=breakdowns, frame_gaps=frame_gaps,
                         frame_indices=[o.index for o in obs], n_samples=int(smp.z.size),
                         config=cfg.to_dict(), diagnostics=diag, skipped_features=skipped,
                         effects=[str(e) for e in effects], label=label)


# --------------------------------------------------------------------------------------------
# Maps and worst regions
# --------------------------------------------------------------------------------------------

VALIDITY_BOTH_VALID, VALIDITY_MEASURED_ONLY, VALIDITY_SIMULATED_ONLY, VALIDITY_BOTH_INVALID = 0, 1, 2, 3
VALIDITY_LABELS = ("both valid", "measured valid only", "simulated valid only", "both invalid")
"""Names of the codes of :func:`validity_map`."""


def error_map(obs: FrameObservation) -> np.ndarray:
    """(H, W) float32 measured - simulated depth, metres; NaN where either is invalid."""
    m, s = obs.measured, obs.simulated
    out = (m - s).astype(np.float32)
    out[(m <= 0) | (s <= 0)] = np.nan
    return out


def validity_map(obs: FrameObservation) -> np.ndarray:
    """(H, W) uint8 codes: 0 both valid, 1 measured valid only, 2 simulated valid only, 3 both invalid."""
    vm = obs.measured > 0
    vs = obs.simulated > 0
    out = np.full(obs.shape, VALIDITY_BOTH_INVALID, np.uint8)
    out[vm & vs] = VALIDITY_BOTH_VALID
    out[vm & ~vs] = VALIDITY_MEASURED_ONLY
    out[~vm & vs] = VALIDITY_SIMULATED_ONLY
    return out


@dataclass
class Region:
    """One place where the model fails: a feature bin or an image block."""

    kind: str
    """``"bin"`` (a feature bin) or ``"block"`` (an image block of one frame)."""
    rank: int
    """1 = worst within its kind."""
    score: float
    """Excess of the bin's term (bins) or the block's local gap (blocks) over its noise floor."""
    description: str
    """One sentence saying what is wrong."""
    feature: str | None = None
    """Feature of a bin region."""
    bin_label: str | None = None
    """Label of the bin."""
    frame: int | None = None
    """Position of the frame in the observation list (blocks)."""
    frame_index: int | None = None
    """``FrameObservation.index`` of that frame (blocks)."""
    bbox: tuple[int, int, int, int] | None = None
    """(x0, y0, x1, y1) pixels, end exclusive (blocks)."""
    details: dict = field(default_factory=dict)
    """Numbers behind the sentence (invalid fractions, bias/std in metres, terms)."""

    def to_json(self) -> dict:
        return _clean(asdict(self))


def _mm(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{1000 * x:.1f} mm"


def _diagnose(pm, ps, bm, bs, sm, ss, err_part, inv_part) -> str:
    if inv_part >= err_part:
        if ps > pm:
            return f"the model drops too many pixels ({100 * ps:.0f}% invalid vs {100 * pm:.0f}% measured)"
        return f"the model keeps pixels the sensor loses ({100 * ps:.0f}% invalid vs {100 * pm:.0f}% measured)"
    db = bs - bm if math.isfinite(bs) and math.isfinite(bm) else 0.0
    ds = ss - sm if math.isfinite(ss) and math.isfinite(sm) else 0.0
    if abs(db) >= abs(ds):
        side = "far" if db > 0 else "near"
        return f"the model is {_mm(abs(db))} too {side} (median error {_mm(bs)} vs {_mm(bm)} measured)"
    lvl = "high" if ds > 0 else "low"
    return f"the model's noise is too {lvl} (robust std {_mm(ss)} vs {_mm(sm)} measured)"


SIGNIFICANCE = 3.0
"""A bin or block is reported only when its term exceeds this multiple of its noise floor (the
null term's spread is ~0.37 of the floor, so 3x is ~5 standard deviations: with ~100 bins per
comparison a lower threshold lists sampling noise of a correct model)."""


def worst_bins(result: CompareResult, top: int = 5, min_share: float = 0.005,
               significance: float = SIGNIFICANCE) -> list[Region]:
    """Feature bins of the gap features where the model disagrees most, worst first.

    Candidates: bins holding at least ``min_share`` of the feature's sampled pixels whose term
    exceeds ``significance`` times its noise floor (the term expected from sampling noise alone
    when the model is right). Ranked by the excess ``term - floor`` (per-pixel disagreement
    beyond noise): ranking by the raw contribution ``(n_b / N) term_b / |features|`` would always
    name the biggest bins (e.g. the dominant material) instead of where the failure
    concentrates; the contribution is kept in ``details["contribution"]``. An empty list means
    no bin differs from the measurement beyond sampling noise.
    """
    out = []
    nfeat = max(1, len(result.gap_features))
    for f in result.gap_features:
        b = result.breakdowns[f]
        n = np.asarray(b["measured"]["count"], dtype=np.float64)
        term = np.asarray(b["term"], dtype=np.float64)
        floor = np.asarray(b.get("noise_floor", np.zeros(len(term))), dtype=np.float64)
        floor = np.where(np.isfinite(floor), floor, 0.0)
        ok = np.isfinite(term)
        tot = n[ok].sum()
        if tot <= 0:
            continue
        for i in np.flatnonzero(ok & (n >= min_share * tot) & (term > significance * floor) & (term > 0)):
            contrib = float(n[i] * term[i] / tot / nfeat)
            m, s = b["measured"], b["simulated"]
            vals = [float(x) for x in (m["invalid_fraction"][i], s["invalid_fraction"][i], m["bias"][i],
                                       s["bias"][i], m["std"][i], s["std"][i],
                                       b["error_term"][i], b["invalid_term"][i])]
            label = b["labels"][i]
            unit = {"deg": "°"}.get(b["unit"], b["unit"])
            where = f"{f.replace('_', ' ')} {label}" + (f" {unit}" if unit and not label.endswith(unit) else "")
            share = 100 * contrib / result.gap if result.gap > 0 else 0.0
            desc = (f"{where} ({100 * n[i] / tot:.0f}% of pixels, bin term {term[i]:.3f}, "
                    f"{term[i] / floor[i] if floor[i] > 0 else math.inf:.0f}x the noise floor): "
                    f"{_diagnose(*vals)}; {share:.0f}% of the gap.")
            out.append(Region("bin", 0, float(term[i] - floor[i]), desc, feature=f, bin_label=label, details={
                "count": int(n[i]), "share": float(n[i] / tot), "contribution": contrib,
                "term": float(term[i]), "noise_floor": float(floor[i]),
                "invalid_fraction_measured": vals[0], "invalid_fraction_simulated": vals[1],
                "bias_measured_m": vals[2], "bias_simulated_m": vals[3], "std_measured_m": vals[4],
                "std_simulated_m": vals[5], "error_term": vals[6], "invalid_term": vals[7]}))
    out.sort(key=lambda r: -r.score)
    out = out[:top]
    for k, r in enumerate(out, 1):
        r.rank = k
    return out


def worst_blocks(observations: Sequence[FrameObservation], config: CompareConfig | None = None,
                 top: int = 5, block_px: int = 32, significance: float = SIGNIFICANCE) -> list[Region]:
    """Image blocks (``block_px`` squares, all pixels) with the highest local gap beyond noise.

    Local gap of a block = the per-bin term of the module docstring with the block as the bin
    (W1 of normalised errors weighted by the both-valid fraction + w_inv * hole-rate
    difference). Blocks with less than a quarter of their pixels on geometry, or whose local
    gap is below ``significance`` times its sampling-noise floor, are skipped; the rest are
    ranked by ``local gap - floor``.
    """
    cfg = (config or CompareConfig()).validate()
    obs = _check_observations(observations)
    if block_px < 2:
        raise ConfigError(f"block_px must be >= 2, got {block_px}")
    out = []
    for fi, o in enumerate(obs):
        h, w = o.shape
        nbx = -(-w // block_px)
        nby = -(-h // block_px)
        geom = (o.ideal > 0).ravel()
        rows = np.flatnonzero(geom)
        v, u = np.divmod(rows, w)
        key = (v // block_px) * nbx + (u // block_px)
        nk = nbx * nby
        z = o.ideal.ravel()[rows].astype(np.float64)
        me = o.measured.ravel()[rows].astype(np.float64)
        se = o.simulated.ravel()[rows].astype(np.float64)
        vm, vs = me > 0, se > 0
        em = np.where(vm, me - z, np.nan)
        es = np.where(vs, se - z, np.nan)
        sc = error_scale_m(z, cfg)
        c = cfg.error_clip
        ym, ys = np.clip(em / sc, -c, c), np.clip(es / sc, -c, c)
        pooled = _Pooled(ym, vm, ys, vs)
        w1, na, nb = pooled.w1(key, nk)
        n = np.bincount(key, minlength=nk).astype(np.float64)
        im = np.bincount(key, weights=(~vm).astype(float), minlength=nk)
        is_ = np.bincount(key, weights=(~vs).astype(float), minlength=nk)
        pm, ps, w1v, et, it, term = _bin_terms(n, im, is_, w1, na, nb, cfg)
        floor = _noise_floor(n, pm, ps, na, nb, _within_var(key, nk, ym, vm, ys, vs), cfg)
        floor = np.where(np.isfinite(floor), floor, 0.0)
        term = np.where((n >= block_px * block_px / 4) & (term > significance * floor), term, np.nan)
        qm = _Sorted(em, vm).quantiles(key, nk)
        qs = _Sorted(es, vs).quantiles(key, nk)
        for kk in np.flatnonzero(np.isfinite(term) & (term > 0)):
            by, bx = divmod(int(kk), nbx)
            x0, y0 = bx * block_px, by * block_px
            x1, y1 = min(w, x0 + block_px), min(h, y0 + block_px)
            vals = [float(x) for x in (pm[kk], ps[kk], qm[1, kk], qs[1, kk], (qm[2, kk] - qm[0, kk]) / 1.349,
                                       (qs[2, kk] - qs[0, kk]) / 1.349, et[kk], it[kk])]
            ratio = term[kk] / floor[kk] if floor[kk] > 0 else math.inf
            desc = (f"frame {o.index}, x {x0}–{x1}, y {y0}–{y1} px: {_diagnose(*vals)} "
                    f"(local gap {term[kk]:.3f}, {ratio:.0f}x the noise floor).")
            out.append(Region("block", 0, float(term[kk] - floor[kk]), desc, frame=fi, frame_index=o.index,
                              bbox=(x0, y0, x1, y1), details={
                                  "count": int(n[kk]), "term": float(term[kk]), "noise_floor": float(floor[kk]),
                                  "invalid_fraction_measured": vals[0],
                                  "invalid_fraction_simulated": vals[1], "bias_measured_m": vals[2],
                                  "bias_simulated_m": vals[3], "std_measured_m": vals[4],
                                  "std_simulated_m": vals[5], "error_term": vals[6], "invalid_term": vals[7]}))
    out.sort(key=lambda r: -r.score)
    out = out[:top]
    for k, r in enumerate(out, 1):
        r.rank = k
    return out


def worst_regions(result: CompareResult, observations: Sequence[FrameObservation], *,
                  top_bins: int = 5, top_blocks: int = 5, block_px: int = 32) -> list[Region]:
    """Ranked list: the worst feature bins (by contribution to the gap), then the worst image
    blocks of ``observations`` (by local gap), each with a one-sentence description."""
    cfg = CompareConfig.from_dict(result.config) if result.config else CompareConfig()
    return worst_bins(result, top_bins) + worst_blocks(observations, cfg, top_blocks, block_px)
