"""Where the model fails: error and validity maps of a frame, and the worst feature bins and image
blocks of a comparison (:func:`worst_regions`), each with a one-sentence description."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from data_tools.errors import ConfigError
from data_tools.results import json_safe
from synth.lab.compare import CompareResult, check_observations
from synth.lab.compare_config import CompareConfig, error_scale_m
from synth.lab.features import FrameObservation
from synth.lab.gap_stats import Pooled, SortedErrors, bin_terms, centred_clip, noise_floor, within_var

__all__ = ["Region", "VALIDITY_LABELS", "SIGNIFICANCE", "error_map", "validity_map", "worst_bins",
           "worst_blocks", "worst_regions"]

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
        return json_safe(asdict(self))


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
    obs = check_observations(observations)
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
        ym, ys = centred_clip(em / sc, es / sc, vs, z, cfg.error_clip, cfg.min_valid_count)
        pooled = Pooled(ym, vm, ys, vs)
        w1, na, nb = pooled.w1(key, nk)
        n = np.bincount(key, minlength=nk).astype(np.float64)
        im = np.bincount(key, weights=(~vm).astype(float), minlength=nk)
        is_ = np.bincount(key, weights=(~vs).astype(float), minlength=nk)
        pm, ps, w1v, et, it, term = bin_terms(n, im, is_, w1, na, nb, cfg)
        floor = noise_floor(n, pm, ps, na, nb, within_var(key, nk, ym, vm, ys, vs), cfg)
        floor = np.where(np.isfinite(floor), floor, 0.0)
        term = np.where((n >= block_px * block_px / 4) & (term > significance * floor), term, np.nan)
        qm = SortedErrors(em, vm).quantiles(key, nk)
        qs = SortedErrors(es, vs).quantiles(key, nk)
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
