"""Plain-language evidence for a diagnosed effect, computed from the measured data.

Each sentence is built from statistics of the measured depth against the ideal geometry
(holes beside depth edges, hole rate per incidence angle or material, error per image radius
or distance, discreteness of the disparity), not from the fit alone, so a reader can check the
diagnosis in the data. Functions are registered by effect name in :data:`EVIDENCE`
(``@register_evidence("name")``); effects without one get :func:`generic_evidence`, which names
the comparison feature whose term the fitted effect lowered most.

All functions take an :class:`EvidenceContext` (the measured observations of the diagnosed
frames, the current model's simulation in ``simulated``, the preset), the candidate's fitted
parameters and its gain; they return one sentence that states only what its numbers support.
Each function measures the effect's *signature* (e.g. the hole rate on the projector-shadow
side of depth edges) where the effect acts, where it does not (the contrast region) and in the
current model, and decides from the sign and size of the differences (thresholds in each
function's docstring, mostly :data:`MIN_RATE_EXCESS`) whether the signature is present. Only
then does the sentence claim it ("grows with the image radius", "sit on a grid"); otherwise it
says that the fit prefers the effect (or not) but the signature is weak, and gives the numbers.
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


EVIDENCE: dict[str, Callable[[EvidenceContext, dict, float | None], str]] = {}
"""Effect name -> evidence function ``fn(ctx, params, gain) -> sentence``."""


def register_evidence(name: str):
    def deco(fn):
        EVIDENCE[name] = fn
        return fn
    return deco


MIN_RATE_EXCESS = 0.05
"""A hole-rate signature counts as present when the measured rate where the effect acts exceeds
both the measured rate where it does not act (the contrast region) and the current model's rate
there by at least this much (5 percentage points; the sampling noise of a rate over the
thousands of pixels of a band is ~1 point)."""


def _pct(x: float) -> str:
    """A fraction as a percentage: never rounds a non-zero rate to "0 %" or a partial one to "100 %"."""
    if not math.isfinite(x):
        return "n/a"
    if 0 < x < 0.005:
        return "<1 %"
    if 0.995 <= x < 1:
        return ">99 %"
    return f"{100 * x:.0f} %"


def _mm(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{1000 * x:+.1f} mm"


def _rate(mask: np.ndarray, sel: np.ndarray) -> float:
    n = int(sel.sum())
    return float(mask[sel].mean()) if n else float("nan")


def _ge(a: float, b: float) -> bool:
    """a >= b for finite numbers (False when either is NaN)."""
    return math.isfinite(a) and math.isfinite(b) and a >= b


WEAK = "is weak in the measured data"
"""The phrase of every sentence whose signature the data do not show clearly."""

NEGLIGIBLE_GAIN = 0.01
"""Below this gain a sentence that finds the signature adds that the fitted effect barely helps."""


def _weak(what: str, gain: float | None, numbers: str) -> str:
    """The sentence of a candidate whose signature the data do not show clearly: the fit may
    still prefer it, but nothing in the numbers is claimed beyond what they are."""
    if gain is not None and gain > 0:
        head = f"adding it lowers the gap by {_pct(gain)}, but the {what} {WEAK}"
    elif gain is not None:
        head = f"adding it does not lower the gap, and the {what} {WEAK}"
    else:
        head = f"the {what} {WEAK}"
    return f"{head}: {numbers}."


@register_evidence("projector_shadow")
def _shadow(ctx: EvidenceContext, params: dict, gain: float | None = None) -> str:
    """Hole rate within 6 px of depth edges on the projector-shadow side vs the lit side.

    Signature present: the shadow-side rate exceeds the lit-side rate and the current model's
    shadow-side rate by :data:`MIN_RATE_EXCESS` and is at least 1.5x the lit-side rate."""
    off = ctx.observations[0].projector_offset_m
    if off is None:
        return "the sensor has no projector offset: no projector shadows can form."
    es = ctx.pooled("edge_shadow", lambda o: shadow_edge_distance(o.ideal, o.intrinsics, off))
    hole_m = ctx.measured <= 0
    hole_s = ctx.simulated <= 0
    near = 6.0
    sh = (es > 0) & (es <= near)
    lit = (es < 0) & (es >= -near)
    if int(sh.sum()) < 50:
        return _weak("projector-shadow signature", gain,
                     f"only {int(sh.sum())} pixels lie within {near:g} px on the projector-shadow side of depth edges")
    r_sh, r_lit, r_mod = _rate(hole_m, sh), _rate(hole_m, lit), _rate(hole_s, sh)
    share = float((hole_m & sh).sum()) / max(int(hole_m.sum()), 1)
    numbers = (f"within {near:g} px of depth edges the sensor loses {_pct(r_sh)} of the pixels on the "
               f"projector-shadow side and {_pct(r_lit)} on the lit side (current model: {_pct(r_mod)} on the "
               f"shadow side)")
    strong = (_ge(r_sh, r_lit + MIN_RATE_EXCESS) and _ge(r_sh, 1.5 * r_lit)
              and _ge(r_sh, r_mod + MIN_RATE_EXCESS))
    if not strong:
        return _weak("projector-shadow signature", gain, numbers)
    return (f"within {near:g} px of depth edges the sensor loses {_pct(r_sh)} of the pixels on the "
            f"projector-shadow side against {_pct(r_lit)} on the lit side (current model: {_pct(r_mod)} on the "
            f"shadow side); these shadow-side holes are {_pct(share)} of all measured holes.")


@register_evidence("edge_fattening")
def _fattening(ctx: EvidenceContext, params: dict, gain: float | None = None) -> str:
    """Share of measured depths within 6 px on the background side of depth edges that are > 5 %
    nearer than the background.

    Signature present: that share exceeds the current model's by :data:`MIN_RATE_EXCESS` and is
    at least twice the share that is > 5 % farther (plain noise makes both alike)."""
    ed = ctx.pooled("edge_distance", lambda o: signed_edge_distance(o.ideal))
    z, m, sm = ctx.ideal, ctx.measured, ctx.simulated
    band = (ed > 0) & (ed <= 6) & (m > 0)
    if int(band.sum()) < 50:
        return _weak("edge-fattening signature", gain,
                     f"only {int(band.sum())} measured pixels lie within 6 px on the background side of depth edges")
    r_n, r_f = _rate(m < 0.95 * z, band), _rate(m > 1.05 * z, band)
    r_s = _rate(sm < 0.95 * z, band & (sm > 0))
    numbers = (f"within 6 px on the background side of depth edges {_pct(r_n)} of the measured depths are more "
               f"than 5 % nearer than the background and {_pct(r_f)} more than 5 % farther (current model: "
               f"{_pct(r_s)} nearer)")
    if not (_ge(r_n, r_s + MIN_RATE_EXCESS) and _ge(r_n, 2 * r_f)):
        return _weak("edge-fattening signature", gain, numbers)
    return (f"within 6 px on the background side of depth edges {_pct(r_n)} of the measured depths are more "
            f"than 5 % nearer than the background (they carry the foreground's depth; {_pct(r_f)} are farther), "
            f"against {_pct(r_s)} in the current model.")


@register_evidence("incidence_dropout")
def _incidence(ctx: EvidenceContext, params: dict, gain: float | None = None) -> str:
    """Measured hole rate per incidence-angle band (bands with >= 50 pixels).

    Signature present: the rate above 60° exceeds the rate below 40° and the current model's
    rate above 60° by :data:`MIN_RATE_EXCESS`."""
    ang = ctx.pooled("incidence", lambda o: incidence_angle_deg(o.normals, o.intrinsics))
    hole = ctx.measured <= 0
    ok = np.isfinite(ang)
    rates = []
    for lo, hi in ((0, 40), (40, 60), (60, 70), (70, 80), (80, 90.1)):
        sel = ok & (ang >= lo) & (ang < hi)
        if sel.sum() >= 50:
            rates.append(f"{_pct(_rate(hole, sel))} at {lo:g}-{min(hi, 90):g}°")
    low, high = ok & (ang < 40), ok & (ang >= 60)
    a50 = params.get("incidence_dropout.angle50_deg")
    tail = f" (fitted 50 % angle {a50:.0f}°)" if a50 is not None else ""
    if int(high.sum()) < 50:
        return _weak("incidence signature", gain, f"fewer than 50 pixels are seen at more than 60° incidence "
                                                  f"({', '.join(rates) or 'no angle band with data'})")
    r_hi, r_lo, r_mod = _rate(hole, high), _rate(hole, low), _rate(ctx.simulated <= 0, high)
    numbers = f"measured hole rate {', '.join(rates)} (current model: {_pct(r_mod)} above 60°)"
    if not (_ge(r_hi, r_lo + MIN_RATE_EXCESS) and _ge(r_hi, r_mod + MIN_RATE_EXCESS)):
        return _weak("incidence signature", gain, numbers)
    return (f"the measured hole rate rises at grazing incidence: {', '.join(rates)}, against "
            f"{_pct(r_mod)} above 60° in the current model{tail}.")


@register_evidence("low_reflectance")
def _reflectance(ctx: EvidenceContext, params: dict, gain: float | None = None) -> str:
    """Measured hole rate on dark (albedo < 0.2) vs brighter materials.

    Signature present: the dark-material rate exceeds the brighter materials' rate and the
    current model's dark-material rate by :data:`MIN_RATE_EXCESS` and is at least 1.5x the
    brighter materials' rate."""
    ids = ctx.pooled("ids", lambda o: o.material_ids)
    alb = np.array([ctx.albedo.get(int(i), np.nan) for i in range(int(ids.max()) + 1)])[ids]
    names = {}
    for o in ctx.observations:
        names.update(o.material_names)
    hole = ctx.measured <= 0
    known = np.isfinite(alb)
    if not known.any():
        return _weak("reflectance signature", gain, "no material albedos are known")
    cut = 0.2
    dark = known & (alb < cut)
    bright = known & (alb >= cut)
    if not dark.any():
        return _weak("reflectance signature", gain,
                     f"no material darker than albedo {cut} is in view; bright surfaces lose {_pct(_rate(hole, bright))}")
    dark_names = sorted({names.get(int(i), str(i)) for i in np.unique(ids[dark])})
    r_d, r_b, r_mod = _rate(hole, dark), _rate(hole, bright), _rate(ctx.simulated <= 0, dark)
    numbers = (f"dark materials (albedo < {cut}: {', '.join(dark_names[:4])}) lose {_pct(r_d)} of their pixels, "
               f"brighter ones {_pct(r_b)} (current model: {_pct(r_mod)} on the dark ones)")
    if not (_ge(r_d, r_b + MIN_RATE_EXCESS) and _ge(r_d, 1.5 * r_b) and _ge(r_d, r_mod + MIN_RATE_EXCESS)):
        return _weak("reflectance signature", gain, numbers)
    return (f"dark materials (albedo < {cut}: {', '.join(dark_names[:4])}) lose {_pct(r_d)} of their pixels, "
            f"more than brighter ones ({_pct(r_b)}) and than the current model on the dark ones ({_pct(r_mod)}).")


def _robust_abs_err(m, z, sel):
    v = sel & (m > 0)
    if v.sum() < 30:
        return float("nan")
    return float(np.median(np.abs(m[v] - z[v])))


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else float("nan")


@register_evidence("lens_distortion")
def _lens(ctx: EvidenceContext, params: dict, gain: float | None = None) -> str:
    """Median |measured - ideal| and hole rate in the image centre (r < 0.35) vs the outer ring
    (r > 0.7), against the same numbers of the current model.

    Signature present when either (a) the measured outer/centre error ratio is >= 1.25 and
    >= 1.2x the current model's ratio (the model's ratio carries the radial change of depth and
    noise that has nothing to do with the lens), or (b) the outer ring's hole rate exceeds the
    model's there by :data:`MIN_RATE_EXCESS` more than in the centre."""
    r = ctx.pooled("radial", lambda o: radial_distance(o.intrinsics)[0])
    z, m, sm = ctx.ideal, ctx.measured, ctx.simulated
    inner, outer = r < 0.35, r > 0.7
    ei, eo = _robust_abs_err(m, z, inner), _robust_abs_err(m, z, outer)
    si, so = _robust_abs_err(sm, z, inner), _robust_abs_err(sm, z, outer)
    hi_, ho = _rate(m <= 0, inner), _rate(m <= 0, outer)
    hsi, hso = _rate(sm <= 0, inner), _rate(sm <= 0, outer)
    rm, rs = _ratio(eo, ei), _ratio(so, si)
    k1 = params.get("lens_distortion.k1")
    tail = f"; fitted k1 = {k1:+.3f}" if k1 is not None else ""
    err_growth = _ge(rm, 1.25) and _ge(rm, 1.2 * rs)
    hole_growth = _ge((ho - hso) - (hi_ - hsi), MIN_RATE_EXCESS)
    err_txt = (f"median |measured - ideal| {1000 * ei:.1f} mm in the image centre and {1000 * eo:.1f} mm in the "
               f"outer ring (x{rm:.1f}; current model x{rs:.1f})")
    hole_txt = f"hole rate {_pct(hi_)} vs {_pct(ho)} (current model {_pct(hsi)} vs {_pct(hso)})"
    if err_growth:
        return f"the residual grows with the image radius: {err_txt}, {hole_txt}{tail}."
    if hole_growth:
        return (f"the outer ring loses more pixels than the current model explains: {hole_txt}; "
                f"{err_txt}{tail}.")
    return _weak("radial signature", gain, f"{err_txt}, {hole_txt}")


@register_evidence("depth_bias")
def _bias(ctx: EvidenceContext, params: dict, gain: float | None = None) -> str:
    """Median error (measured - ideal) in the near, middle and far third of the measured pixels,
    against the current model's.

    Signature present: in some third the measured median differs from the model's by at least
    max(2 mm, 0.25 x the robust noise level of that third)."""
    z, m, sm = ctx.ideal, ctx.measured, ctx.simulated
    v = m > 0
    if v.sum() < 100:
        return _weak("bias signature", gain, "too few measured pixels to estimate a bias")
    q = np.quantile(z[v], [0.0, 1 / 3, 2 / 3, 1.0])
    zc, bm, bs, thr = [], [], [], []
    for a, b in zip(q, q[1:]):
        sel = v & (z >= a) & (z <= b)
        e = m[sel] - z[sel]
        zc.append(float(np.median(z[sel])))
        bm.append(float(np.median(e)))
        ss = sel & (sm > 0)
        bs.append(float(np.median(sm[ss] - z[ss])) if ss.sum() >= 30 else float("nan"))
        iqr = float(np.subtract(*np.quantile(e, [0.75, 0.25])))
        thr.append(max(0.002, 0.25 * iqr / 1.349))
    x = [a - (b if math.isfinite(b) else 0.0) for a, b in zip(bm, bs)]
    big = [abs(xi) >= t for xi, t in zip(x, thr)]
    model = " / ".join(_mm(b) for b in bs)
    numbers = (f"median error {_mm(bm[0])} at {zc[0]:.1f} m, {_mm(bm[1])} in the middle and {_mm(bm[2])} at "
               f"{zc[2]:.1f} m (current model {model})")
    if not any(big):
        return _weak("bias signature", gain, numbers)
    x1, x3 = x[0], x[2]
    if x1 * x3 < 0 and big[0] and big[2]:
        shape = "changing sign with distance"
    elif abs(x3 - x1) < 0.3 * max(abs(x1), abs(x3), 1e-4):
        shape = "roughly constant"
    else:
        shape = "growing with distance" if abs(x3) > abs(x1) else "shrinking with distance"
    return (f"the measured depth is systematically off: median error {_mm(bm[0])} at {zc[0]:.1f} m, "
            f"{_mm(bm[1])} in the middle and {_mm(bm[2])} at {zc[2]:.1f} m, against {model} in the current "
            f"model (an offset {shape}).")


def _concentration(d: np.ndarray, step: float) -> float:
    return float(np.abs(np.mean(np.exp(2j * np.pi * d / step)))) if d.size else float("nan")


@register_evidence("disparity_quantization")
def _quant(ctx: EvidenceContext, params: dict, gain: float | None = None) -> str:
    """Circular concentration R = |mean exp(2 pi i d / step)| of the measured disparities
    d = f b / z at the fitted (else the preset's) step: ~1 for disparities on a grid of that
    step, ~0 for continuous ones.

    Signature present: R >= 0.3 and R exceeds the current model's by >= 0.2."""
    pre = ctx.preset
    fb = float(pre.fb)
    if fb <= 0:
        return "the sensor does not triangulate: no disparity levels."
    step = params.get("disparity_quantization.step_px") or float(pre.subpixel_step_px)
    m, zs = ctx.measured, ctx.simulated
    conc = _concentration(fb / m[m > 0], step)
    conc_s = _concentration(fb / zs[zs > 0], step)
    if not (_ge(conc, 0.3) and _ge(conc, conc_s + 0.2)):
        return _weak("disparity-grid signature", gain,
                     f"the measured disparities f·b/z have a circular concentration of {conc:.2f} on a grid of "
                     f"{step:.3f} px ({conc_s:.2f} for the current model)")
    return (f"measured disparities f·b/z sit on a grid of {step:.3f} px (circular concentration {conc:.2f}; "
            f"{conc_s:.2f} for the current model's depths), i.e. discrete depth levels spaced "
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


def evidence_for(name: str, ctx: EvidenceContext, params: dict, before=None, after=None,
                 gain: float | None = None) -> str:
    """The evidence sentence of effect ``name`` (registered function, else the generic one).

    ``gain``: the candidate's gap reduction (fraction), quoted when the data show its
    signature only weakly."""
    fn = EVIDENCE.get(name)
    try:
        if fn is not None:
            s = fn(ctx, params, gain)
        elif before is not None and after is not None:
            s = generic_evidence(before, after)
        else:
            s = "no evidence function for this effect."
        if fn is not None and gain is not None and gain < NEGLIGIBLE_GAIN and WEAK not in s:
            # the data show the signature, but the fitted effect does not explain it
            s = s.rstrip(".") + ("; yet adding the fitted effect lowers the gap by only " + _pct(gain) if gain > 0
                                 else "; yet adding the fitted effect does not lower the gap") + "."
    except (ValueError, IndexError, ZeroDivisionError, FloatingPointError) as e:  # degenerate data
        s = f"evidence not available ({type(e).__name__}: {e})."
    return s[0].upper() + s[1:] if s else s
