"""The statistics behind the gap of :mod:`synth.lab.compare`, vectorised over bins: exact 1-D
Wasserstein-1 per group (:class:`Pooled`, one float sort + one integer sort), robust quantiles per
group (:class:`SortedErrors`), the per-bin terms and their sampling-noise floor, and the per-frame
sampling of geometry pixels with its cache (:class:`CompareCache`, :func:`collect_samples`)."""
from __future__ import annotations

import json
import math

from dataclasses import dataclass

import numpy as np

from data_tools.errors import RealgapError
from synth.lab.compare_config import CompareConfig
from synth.lab.features import CategoricalValues, FrameFeatures, FrameObservation

__all__ = ["wasserstein1", "Pooled", "SortedErrors", "W1_NULL_CONSTANT", "bin_terms", "noise_floor",
           "within_var", "weighted_mean", "CompareCache", "collect_samples", "centred_clip", "CLIP_CENTRE_BIN_M"]

CLIP_CENTRE_BIN_M = 0.25
"""Width (metres of ideal depth) of the bins whose simulated median error centres the error clip
(:func:`centred_clip`)."""


def centred_clip(y_m: np.ndarray, y_s: np.ndarray, valid_s: np.ndarray, z: np.ndarray, clip: float,
                 min_count: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Clip normalised errors (N,) of both sides to +-``clip`` about one centre per ideal-depth bin
    (:data:`CLIP_CENTRE_BIN_M`): the median SIMULATED error of the bin (0 in a bin with fewer than
    ``min_count`` valid simulated samples).

    Why: the clip keeps a few flying pixels from dominating W1, but a clip about zero also
    saturates a systematic bias larger than ``clip`` error scales (a disparity offset of 0.4 px is
    13-18 scales at 1.5-3 m): every such error, measured and simulated, sits on the clip and W1
    cannot tell a model with the right bias from one 1 % off in scale. Why the simulated side's
    centre, not the measured one's: a window centred away from a simulation clips the simulation's
    far tail at no cost and rewards its near tail, so more simulated noise alone would lower the gap
    (a model without the bias then fitted its noise to its bound); about the simulation's own centre
    its spread is clipped symmetrically, and a model whose bias is far off meets the measurement on
    the clip (the most W1 can say), one whose bias is close sees the difference unsaturated. A
    sequence without a bias (centre ~ 0: the median of the noise) is clipped as before."""
    centre = np.zeros_like(y_m, dtype=np.float64)
    ok = valid_s & np.isfinite(y_s)
    if ok.any():
        b = np.clip(np.floor(np.asarray(z, np.float64) / CLIP_CENTRE_BIN_M).astype(np.int64), 0, None)
        nb = int(b.max()) + 1
        med = SortedErrors(y_s, ok).quantiles(b, nb, (0.5,))[0]
        med[np.bincount(b[ok], minlength=nb) < max(int(min_count), 1)] = 0.0
        centre = med[b]
    return (centre + np.clip(y_m - centre, -clip, clip), centre + np.clip(y_s - centre, -clip, clip))

# --------------------------------------------------------------------------------------------
# Grouped statistics (vectorised over bins)
# --------------------------------------------------------------------------------------------

def wasserstein1(a: np.ndarray, b: np.ndarray) -> float:
    """Exact 1-D Wasserstein-1 distance between two empirical samples (any sizes)."""
    a = np.asarray(a, dtype=np.float64).ravel()
    b = np.asarray(b, dtype=np.float64).ravel()
    if a.size == 0 or b.size == 0:
        raise RealgapError("wasserstein1 needs two non-empty samples")
    w, _, _ = Pooled(a, np.ones(a.size, bool), b, np.ones(b.size, bool),
                      index_a=np.zeros(a.size, np.int64), index_b=np.zeros(b.size, np.int64)).w1(
        np.zeros(1, np.int64), 1)
    return float(w[0])


def _sort_key_dtype(nkeys: int):
    return np.int16 if nkeys < 32767 else np.int64


class Pooled:
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


class SortedErrors:
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


def noise_floor(n, pm, ps, na, nb, var_w, cfg: CompareConfig):
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


def within_var(keys, nkeys, ym, vm, ys, vs):
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


def bin_terms(n, inv_m, inv_s, w1, na, nb, cfg: CompareConfig):
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


def weighted_mean(term, n):
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


def collect_samples(obs: list[FrameObservation], cfg: CompareConfig, feats: dict,
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
