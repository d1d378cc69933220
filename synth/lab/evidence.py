"""Plain-language evidence for a diagnosed effect, computed from the measured data.

Each sentence is built from statistics of the measured depth against the ideal geometry
(holes beside depth edges, hole rate per incidence angle or material, error per image radius
or distance, discreteness of the disparity), not from the fit alone, so a reader can check the
diagnosis in the data. Functions are registered by effect name in :data:`EVIDENCE`
(``@register_evidence("name")``); effects without one get :func:`generic_evidence`, which names
the comparison feature whose term the fitted effect lowered most.

All functions take an :class:`EvidenceContext` (the measured observations of the diagnosed
frames, the current model's simulation in ``simulated``, the preset) and the candidate's fitted
parameters; they return one sentence.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from synth.lab.features import (FrameObservation, incidence_angle_deg, radial_distance,
                                shadow_edge_distance, signed_edge_distance)

__all__ = ["EvidenceContext", "EVIDENCE", "register_evidence", "evidence_for", "generic_evidence"]


@dataclass
class EvidenceContext:
    """What evidence functions read."""

    observations: Sequence[FrameObservation]
    """Measured (``measured``) and current-model (``simulated``) depth with the ideal geometry."""
    preset: object
    """The sensor preset (focal length, baseline, projector offset)."""
    albedo: dict[int, float] = field(default_factory=dict)
    """Instance id -> material albedo."""
    _cache: dict = field(default_factory=dict)
    """Pooled per-pixel arrays already computed (by name)."""

    def pooled(self, name: str, fn: Callable[[FrameObservation], np.ndarray]) -> np.ndarray:
        """Concatenation over frames of fn(obs)[geometry pixels] (cached by name)."""
        if name not in self._cache:
            self._cache[name] = np.concatenate([np.asarray(fn(o)).reshape(-1)[(o.ideal > 0).reshape(-1)]
                                                for o in self.observations])
        return self._cache[name]

    @property
    def ideal(self) -> np.ndarray:
        return self.pooled("ideal", lambda o: o.ideal).astype(np.float64)

    @property
    def measured(self) -> np.ndarray:
        return self.pooled("measured", lambda o: o.measured).astype(np.float64)

    @property
    def simulated(self) -> np.ndarray:
        return self.pooled("simulated", lambda o: o.simulated).astype(np.float64)


EVIDENCE: dict[str, Callable[[EvidenceContext, dict], str]] = {}
"""Effect name -> evidence function."""


def register_evidence(name: str):
    def deco(fn):
        EVIDENCE[name] = fn
        return fn
    return deco


def _pct(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{100 * x:.0f} %"


def _mm(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{1000 * x:+.1f} mm"


def _rate(mask: np.ndarray, sel: np.ndarray) -> float:
    n = int(sel.sum())
    return float(mask[sel].mean()) if n else float("nan")


@register_evidence("projector_shadow")
def _shadow(ctx: EvidenceContext, params: dict) -> str:
    off = ctx.observations[0].projector_offset_m
    if off is None:
        return "the sensor has no projector offset: no projector shadows can form."
    es = ctx.pooled("edge_shadow", lambda o: shadow_edge_distance(o.ideal, o.intrinsics, off))
    hole_m = ctx.measured <= 0
    hole_s = ctx.simulated <= 0
    near = 6.0
    sh = (es > 0) & (es <= near)
    lit = (es < 0) & (es >= -near)
    n_holes = max(int(hole_m.sum()), 1)
    share = float((hole_m & sh).sum()) / n_holes
    return (f"{_pct(share)} of the measured holes lie within {near:g} px on the projector-shadow side of "
            f"depth edges, where the sensor loses {_pct(_rate(hole_m, sh))} of the pixels "
            f"({_pct(_rate(hole_m, lit))} on the lit side; the current model {_pct(_rate(hole_s, sh))}).")


@register_evidence("edge_fattening")
def _fattening(ctx: EvidenceContext, params: dict) -> str:
    ed = ctx.pooled("edge_distance", lambda o: signed_edge_distance(o.ideal))
    z, m = ctx.ideal, ctx.measured
    band = (ed > 0) & (ed <= 6) & (m > 0)
    nearer = m < 0.95 * z
    farther = m > 1.05 * z
    return (f"within 6 px on the background side of depth edges {_pct(_rate(nearer, band))} of the measured "
            f"depths are more than 5 % nearer than the background (they carry the foreground's depth; "
            f"{_pct(_rate(farther, band))} are farther), against {_pct(_rate(ctx.simulated < 0.95 * z, band & (ctx.simulated > 0)))} "
            f"in the current model.")


@register_evidence("incidence_dropout")
def _incidence(ctx: EvidenceContext, params: dict) -> str:
    ang = ctx.pooled("incidence", lambda o: incidence_angle_deg(o.normals, o.intrinsics))
    hole = ctx.measured <= 0
    ok = np.isfinite(ang)
    rates = []
    for lo, hi in ((0, 40), (40, 60), (60, 70), (70, 80), (80, 90.1)):
        sel = ok & (ang >= lo) & (ang < hi)
        if sel.sum() >= 50:
            rates.append(f"{_pct(_rate(hole, sel))} at {lo:g}-{min(hi, 90):g}°")
    a50 = params.get("incidence_dropout.angle50_deg")
    tail = f" (fitted 50 % angle {a50:.0f}°)" if a50 is not None else ""
    return f"the measured hole rate grows with the incidence angle: {', '.join(rates)}{tail}."


@register_evidence("low_reflectance")
def _reflectance(ctx: EvidenceContext, params: dict) -> str:
    ids = ctx.pooled("ids", lambda o: o.material_ids)
    alb = np.array([ctx.albedo.get(int(i), np.nan) for i in range(int(ids.max()) + 1)])[ids]
    names = {}
    for o in ctx.observations:
        names.update(o.material_names)
    hole = ctx.measured <= 0
    known = np.isfinite(alb)
    if not known.any():
        return "no material albedos are known."
    # dark = the materials in the lowest albedo third present
    cut = 0.2
    dark = known & (alb < cut)
    bright = known & (alb >= cut)
    dark_names = sorted({names.get(int(i), str(i)) for i in np.unique(ids[dark])})
    if not dark.any():
        return f"no material darker than albedo {cut} is in view; bright surfaces lose {_pct(_rate(hole, bright))}."
    return (f"dark materials (albedo < {cut}: {', '.join(dark_names[:4])}) lose {_pct(_rate(hole, dark))} of "
            f"their pixels, brighter ones {_pct(_rate(hole, bright))} (current model: "
            f"{_pct(_rate(ctx.simulated <= 0, dark))} on the dark ones).")


def _robust_abs_err(m, z, sel):
    v = sel & (m > 0)
    if v.sum() < 30:
        return float("nan")
    return float(np.median(np.abs(m[v] - z[v])))


@register_evidence("lens_distortion")
def _lens(ctx: EvidenceContext, params: dict) -> str:
    r = ctx.pooled("radial", lambda o: radial_distance(o.intrinsics)[0])
    z, m = ctx.ideal, ctx.measured
    inner, outer = r < 0.35, r > 0.7
    ei, eo = _robust_abs_err(m, z, inner), _robust_abs_err(m, z, outer)
    hi_, ho = _rate(m <= 0, inner), _rate(m <= 0, outer)
    ratio = eo / ei if ei > 0 and math.isfinite(eo) else float("nan")
    k1 = params.get("lens_distortion.k1")
    tail = f"; fitted k1 = {k1:+.3f}" if k1 is not None else ""
    return (f"the residual grows with the image radius: median |measured - ideal| is {1000 * ei:.1f} mm "
            f"in the image centre and {1000 * eo:.1f} mm in the outer ring (x{ratio:.1f}), hole rate "
            f"{_pct(hi_)} vs {_pct(ho)}{tail}.")


@register_evidence("depth_bias")
def _bias(ctx: EvidenceContext, params: dict) -> str:
    z, m = ctx.ideal, ctx.measured
    v = m > 0
    if v.sum() < 100:
        return "too few measured pixels to estimate a bias."
    q = np.quantile(z[v], [0.0, 1 / 3, 2 / 3, 1.0])
    parts = []
    for a, b in zip(q, q[1:]):
        sel = v & (z >= a) & (z <= b)
        parts.append((float(np.median(z[sel])), float(np.median(m[sel] - z[sel]))))
    (z1, b1), (_, b2), (z3, b3) = parts
    # shape: constant vs growing ~ z^2
    shape = "roughly constant" if abs(b3 - b1) < 0.3 * max(abs(b1), abs(b3), 1e-4) else (
        "growing with distance" if abs(b3) > abs(b1) else "shrinking with distance")
    return (f"the measured depth is systematically off: median error {_mm(b1)} at {z1:.1f} m, {_mm(b2)} in the "
            f"middle and {_mm(b3)} at {z3:.1f} m ({shape}), while the noise is symmetric around it.")


@register_evidence("disparity_quantization")
def _quant(ctx: EvidenceContext, params: dict) -> str:
    pre = ctx.preset
    fb = float(pre.fx * pre.baseline_m)
    if fb <= 0:
        return "the sensor does not triangulate: no disparity levels."
    step = params.get("disparity_quantization.step_px") or float(pre.subpixel_step_px)
    m = ctx.measured
    v = m > 0
    d = fb / m[v]
    conc = float(np.abs(np.mean(np.exp(2j * np.pi * d / step)))) if v.any() else float("nan")
    zs = ctx.simulated
    vs = zs > 0
    conc_s = float(np.abs(np.mean(np.exp(2j * np.pi * (fb / zs[vs]) / step)))) if vs.any() else float("nan")
    return (f"measured disparities f·b/z sit on a grid of {step:.3f} px (circular concentration {conc:.2f}; "
            f"{conc_s:.2f} for the current model's continuous depths), i.e. discrete depth levels spaced "
            f"{1000 * step / fb:.1f} mm at 1 m and {4000 * step / fb:.1f} mm at 2 m, growing with z².")


def generic_evidence(before, after) -> str:
    """Sentence naming the comparison feature whose term the candidate lowered most (from two
    :class:`~synth.lab.compare.CompareResult` of the same frames)."""
    best, drop = None, 0.0
    for f in before.gap_features:
        a = before.feature_terms.get(f, float("nan"))
        b = after.feature_terms.get(f, float("nan"))
        if math.isfinite(a) and math.isfinite(b) and a - b > drop:
            best, drop = f, a - b
    ds = before.spatial_term - after.spatial_term
    if best is None and ds <= 0:
        return "no comparison feature improves with this effect."
    if ds * 2 > drop:
        return (f"the effect mainly moves holes to where the sensor has them (misplaced-hole fraction "
                f"{_pct(before.spatial_term)} -> {_pct(after.spatial_term)}).")
    fa, fb = before.feature_terms[best], after.feature_terms[best]
    return f"the effect mainly explains the errors binned by {best.replace('_', ' ')} (term {fa:.3f} -> {fb:.3f})."


def evidence_for(name: str, ctx: EvidenceContext, params: dict, before=None, after=None) -> str:
    """The evidence sentence of effect ``name`` (registered function, else the generic one)."""
    fn = EVIDENCE.get(name)
    try:
        if fn is not None:
            s = fn(ctx, params)
        elif before is not None and after is not None:
            s = generic_evidence(before, after)
        else:
            s = "no evidence function for this effect."
    except (ValueError, IndexError, ZeroDivisionError, FloatingPointError) as e:  # degenerate data
        s = f"evidence not available ({type(e).__name__}: {e})."
    return s[0].upper() + s[1:] if s else s
