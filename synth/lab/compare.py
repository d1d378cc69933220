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
(default 10) about a centre ``c_z`` so that a few flying pixels or model-misalignment outliers
cannot dominate: ``y = c_z + clip(e / s(z) - c_z, -c, c)``, ``c_z`` the median simulated normalised
error of the pixel's 0.25 m ideal-depth bin (the same for both sides; ~0 without a systematic bias,
and a bias of more than ``c`` scales is not saturated: :func:`synth.lab.gap_stats.centred_clip`).

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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError, RealgapError
from data_tools.results import json_safe
from synth.lab.compare_config import PRESETS, CompareConfig, compare_preset, error_scale_m
from synth.lab.feature_maps import radial_max_px
from synth.lab.features import FrameObservation, make_feature
from synth.lab.gap_stats import (CompareCache, Pooled, SortedErrors, bin_terms, centred_clip, collect_samples,
                                 noise_floor, wasserstein1, weighted_mean, within_var)

__all__ = ["CompareConfig", "CompareResult", "CompareCache", "PRESETS", "compare_preset", "compare",
           "load_result", "error_scale_m", "wasserstein1", "FrameObservation", "BREAKDOWN_FEATURES",
           "check_observations"]

BREAKDOWN_FEATURES = ("distance", "incidence", "radial", "material", "edge_distance")
"""Features always present as keys of ``metrics.json`` ``breakdowns`` (others when available)."""

METRICS_FILE = "metrics.json"
CONFIG_FILE = "compare_config.json"


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------

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
        return json_safe({
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
        atomic_write_json(out / CONFIG_FILE, json_safe(self.config))
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

def check_observations(observations) -> list[FrameObservation]:
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
    obs = check_observations(observations)
    feats = {name: make_feature(name, cfg.features) for name in cfg.feature_names()}
    smp = collect_samples(obs, cfg, feats, cache)
    nf = len(obs)
    if smp.z.size == 0:
        raise RealgapError("compare: no frame has ideal geometry (ideal depth is 0 everywhere)")

    scale = error_scale_m(smp.z, cfg)
    ym, ys = centred_clip(smp.err_m / scale, smp.err_s / scale, smp.valid_s, smp.z, cfg.error_clip,
                          cfg.min_valid_count)
    pooled = Pooled(ym, smp.valid_m, ys, smp.valid_s)
    sorted_m = SortedErrors(smp.err_m, smp.valid_m)
    sorted_s = SortedErrors(smp.err_s, smp.valid_s)
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
        pm, ps, w1v, et, it, term = bin_terms(n, im, is_, w1, na, nb, cfg)
        floor = noise_floor(n, pm, ps, na, nb, within_var(b, k, ym, smp.valid_m, ys, smp.valid_s), cfg)
        qm = sorted_m.quantiles(b, k)
        qs = sorted_s.quantiles(b, k)
        qm[:, na < cfg.min_valid_count] = np.nan   # no bias/std from a handful of pixels
        qs[:, nb < cfg.min_valid_count] = np.nan
        ft = weighted_mean(term, n)
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
        t2 = bin_terms(n2, im2, is2, w12, na2, nb2, cfg)[5].reshape(nf, k)
        n2 = n2.reshape(nf, k)
        frame_terms[name] = np.array([weighted_mean(t2[i], n2[i]) for i in range(nf)])

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
