"""Signatures that decide a diagnosis by themselves, measured from the data without a fit.

A fitted gain says how much an effect lowers the gap; two effects that both make holes (or
both blur the disparity) can gain about the same, and at a small gain any effect that adds a
little noise can beat the right one. Some effects leave a trace in the measurement that no other
effect of the catalog leaves, and that is checked without simulating anything:

* ``disparity_quantization``: the measured disparities f b / z lie on a lattice (step, phase)
  that the current model's simulated disparities do not lie on
  (:func:`synth.sensor.lattice.detect_lattice`);
* ``low_reflectance`` against ``incidence_dropout``: which variable the extra holes follow.
  A dropout by returned signal depends on albedo cos(theta) / r^2, a dropout by incidence on
  theta alone. Among the pixels the current model keeps (not within :data:`EDGE_MARGIN_PX` of a
  depth edge on its background side, where projector shadows and fattening act - the foreground
  side's rims stay: a surface turns grazing at its own silhouette, and a face seen at 79 deg is a
  few pixels wide; not at ideal depths within 3 noise sd of the nearest or farthest measured depth,
  ``_common.censoring_band``: there noise alone makes holes, range limits are not the question),
  the measured holes are explained by the best hole rate falling monotonically with the signal and
  by the best one rising monotonically with theta (isotonic regressions: both dropout laws are
  monotone, neither shape is assumed), and the two Bernoulli log-likelihoods are compared: the
  variable the holes follow explains them better (the other is only a noisy proxy of it). Two
  earlier forms failed on the mystery generator (its laws, computed with its own variables): step
  functions on 32 quantile bins put a sharp cut that holes the weakest 1 % inside their lowest bin
  and read seed 30's true low reflectance as an incidence dropout by e^23 (monotone: low
  reflectance by e^306); the two effects' logistic laws read seed 28's true incidence dropout - a
  probit in the angle, which a logistic in log10(albedo cos / r^2) imitates better than a logistic
  in the angle - as low reflectance by e^2463 (monotone: incidence by e^476). A likelihood ratio of at least e^:data:`MIN_LOG_RATIO`
  decides; otherwise the data cannot separate the two (holes that follow neither clearly, or a
  scene where signal and angle go together: one albedo, a narrow range of distances) and
  :func:`~synth.lab.diagnose.diagnose` names the two as a tie.
* ``lens_distortion`` against a learned per-pixel map (``disparity_distortion``), which on a static
  camera imitates any fixed distortion: the depth residual on smooth sloped surfaces follows the
  radial shift a lens makes, k r^2 times the surface's image gradient along the radius
  (:func:`radial_shift`; at least :data:`MIN_RADIAL_SHARE` of the residual's variance);
* ``edge_fattening`` against the effects that only make holes (``incidence_dropout``,
  ``low_reflectance``, ``projector_shadow``): measured depths on the background side of depth
  edges (within :data:`SPILL_BAND_PX`) that carry the foreground's depth (> 5 % nearer than the
  background), in a share that exceeds the current model's by :data:`MIN_SPILL_EXCESS` and is at
  least twice the share > 5 % farther (plain noise makes both alike). A hole cannot carry a
  depth, so a dropout, however well it scores, does not explain these pixels (a fitted dropout can
  still gain by removing them: on the mystery generator's seed 23 it gained 0.90 against the true
  fattening's 0.81).

Approximations: the signal uses the camera ray for both incidence and range (the projector sits
a baseline away, a few cm: a < 1 deg difference at 1 m); materials without a known albedo are left
out; pixels are treated as independent draws (a real sensor's holes are spatially correlated, which
inflates both likelihoods alike but overstates the ratio's significance).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.lab.evidence import SPILL_BAND_PX   # one band for edge fattening's sentence and decision

__all__ = ["HoleDrivers", "hole_drivers", "foreground_spill", "decisive_signatures", "missing_lattice", "MIN_LOG_RATIO",
           "promote", "EXACT", "HOLE_ONLY", "LEARNED_MAPS", "RadialShift", "radial_shift"]

MIN_LOG_RATIO = 10.0
"""The better variable must explain the holes by a likelihood ratio of at least e^10 (~22000)."""
MIN_HOLES = 20
"""Fewer holes than this among the pixels the statistic uses decide nothing (not even a tie): too
few to explain. A count, not a rate: a dropout confined to one dark face seen at grazing incidence
holes a few tenths of a per cent of a frame, and the likelihood ratio (:data:`MIN_LOG_RATIO`)
already says whether those holes tell the two laws apart."""
CONFOUNDED_RANK_CORR = 0.999
"""When the returned signal and the incidence angle of the pixels the statistic uses are ranked alike
(|Spearman rank correlation| at least this) the two monotone fits are the same fit and the holes
cannot tell the laws apart, whatever their number: e.g. one floor plane seen from a fixed height,
where albedo cos / r^2 = albedo cos^3 / d^2 is a function of the angle alone. The tie sentence then
says so instead of quoting a likelihood ratio of e^0."""
MIN_SPILL_EXCESS = 0.05
"""The measured share of foreground-valued depths in that band must exceed the current model's by
this much (5 points, the evidence sentence's threshold; a rate's sampling noise over a few thousand
band pixels is ~1 point)."""
MIN_SPILL_PIXELS = 200
"""Fewer measured band pixels than this decide nothing."""
EDGE_MARGIN_PX = 3.0
"""Pixels nearer than this to a depth edge are left out (shadows, fattening, flying pixels)."""


@dataclass(frozen=True)
class HoleDrivers:
    """Which variable the holes follow: the returned signal or the incidence angle."""

    ll_signal: float
    """Log-likelihood (nats) of the holes under the best hole rate falling monotonically with the signal."""
    ll_angle: float
    """The same under the best rate rising monotonically with the incidence angle."""
    pixels: int
    """Pixels the statistics use."""
    hole_rate: float
    """Their measured hole rate."""
    holes: int
    """Their measured holes."""
    rank_corr: float = 0.0
    """Spearman rank correlation of the returned signal with the incidence angle over those pixels
    (-1: the signal falls exactly as the angle rises; :data:`CONFOUNDED_RANK_CORR`)."""

    @property
    def confounded(self) -> bool:
        """The signal and the angle order the pixels alike: no hole pattern can tell the laws apart."""
        return abs(self.rank_corr) >= CONFOUNDED_RANK_CORR

    @property
    def log_ratio(self) -> float:
        """ll_signal - ll_angle: > 0 when the signal explains the holes better."""
        return self.ll_signal - self.ll_angle

    @property
    def driver(self) -> str | None:
        """'low_reflectance', 'incidence_dropout' or None (the data cannot tell)."""
        if self.holes < MIN_HOLES or self.confounded:
            return None
        if self.log_ratio >= MIN_LOG_RATIO:
            return "low_reflectance"
        if self.log_ratio <= -MIN_LOG_RATIO:
            return "incidence_dropout"
        return None

    def sentence(self) -> str:
        if self.confounded:
            return (f"the holes ({self.holes}, {100 * self.hole_rate:.2g} % of {self.pixels} pixels the current model "
                    f"keeps) cannot tell the returned signal (albedo·cos/r²) from the incidence angle: on these pixels "
                    f"the signal falls in the same order as the angle rises (rank correlation {self.rank_corr:+.3f}; "
                    f"one surface at one distance, e.g. a floor seen from a fixed height), so both laws explain them "
                    f"alike; surfaces at other distances in range would separate them")
        if self.log_ratio >= 0:
            a, b = "the returned signal (albedo·cos/r²)", "the incidence angle"
        else:
            a, b = "the incidence angle", "the returned signal (albedo·cos/r²)"
        return (f"the holes ({self.holes}, {100 * self.hole_rate:.2g} % of {self.pixels} pixels the current model "
                f"keeps) are explained better by {a} than by {b}: likelihood ratio e^{abs(self.log_ratio):.1f}")


def _monotone_ll(hole: np.ndarray, x: np.ndarray, increasing: bool) -> float:
    """Bernoulli log-likelihood (nats) of ``hole`` under the best hole rate that is monotone in ``x``
    (non-decreasing when ``increasing``): isotonic regression, no shape assumed beyond the monotony
    both dropout laws share, and unchanged by any monotone transform of x (log or not, logistic or
    probit)."""
    from scipy.optimize import isotonic_regression       # pool adjacent violators: for 0/1 data the ML monotone rate
    y = hole.astype(np.float64)
    o = np.argsort(x if increasing else -np.asarray(x), kind="stable")
    p = np.empty_like(y)
    p[o] = isotonic_regression(y[o]).x
    p = np.clip(p, 1e-12, 1 - 1e-12)
    return float(np.sum(y * np.log(p) + (1 - y) * np.log(1 - p)))


def hole_drivers(ctx) -> HoleDrivers | None:
    """The :class:`HoleDrivers` of an :class:`~synth.lab.evidence.EvidenceContext` (None with fewer
    than 500 usable pixels or no known albedo). The censoring band's noise sd
    (``_common.depth_noise_sd``) is the larger robust sd of the measured and of the current model's
    residual (disparity px for triangulation, the preset's f b; metres otherwise)."""
    from data_tools.geometry import pixel_rays
    from synth.sensor.effects._common import censoring_band, depth_noise_sd, residual_sd
    ids = ctx.material_ids()
    if not ctx.albedo:
        return None
    lut = np.full(int(max(ids.max(), max(ctx.albedo))) + 1, np.nan)
    for k, a in ctx.albedo.items():
        lut[int(k)] = a
    alb = lut[ids]
    ang = ctx.incidence_deg()
    norm = ctx.pooled("ray_norm", lambda o: np.linalg.norm(pixel_rays(o.intrinsics, unit=False), axis=-1))
    r = ctx.ideal * norm
    ed = ctx.edge_distance()                  # > 0 background side, < 0 foreground side
    z, m, s = ctx.ideal, ctx.measured, ctx.simulated
    valid, sim = (m > 0) & (z > 0), (s > 0) & (z > 0)
    if int(valid.sum()) < 500:
        return None
    fb = float(getattr(ctx.preset, "fb", 0.0) or 0.0)
    sd = max(residual_sd(m[valid], z[valid], fb), residual_sd(s[sim], z[sim], fb))
    limits = (float(m[valid].min()), float(m[valid].max()))   # where the sensor measures at all (range limits)
    use = (sim & ~censoring_band(z, limits, depth_noise_sd(z, sd, fb)) & np.isfinite(ang) & (ang < 89.5)
           & np.isfinite(alb) & (alb > 0) & (r > 0) & ((ed < 0) | (ed > EDGE_MARGIN_PX)))
    if int(use.sum()) < 500:
        return None
    hole = (m <= 0)[use]
    a = ang[use]
    sig = np.log10(alb[use] * np.cos(np.radians(a)) / r[use] ** 2)
    from scipy.stats import spearmanr
    rho = float(spearmanr(sig, a).statistic) if np.ptp(sig) > 0 and np.ptp(a) > 0 else 0.0
    return HoleDrivers(_monotone_ll(hole, sig, False), _monotone_ll(hole, a, True), int(use.sum()), float(hole.mean()),
                       int(hole.sum()), rho)


def foreground_spill(ctx) -> tuple[float, float, float, int] | None:
    """(measured share > 5 % nearer, measured share > 5 % farther, the current model's share nearer,
    measured pixels) in the band within :data:`SPILL_BAND_PX` on the background side of depth edges
    (:meth:`synth.lab.evidence.EvidenceContext.foreground_spill`, the definition edge fattening's
    evidence sentence uses too); None with fewer than :data:`MIN_SPILL_PIXELS` measured or
    simulated pixels there."""
    sp = ctx.foreground_spill(SPILL_BAND_PX)
    if sp.pixels < MIN_SPILL_PIXELS or sp.model_pixels < MIN_SPILL_PIXELS:
        return None
    return sp.near, sp.far, sp.model_near, sp.pixels


@dataclass(frozen=True)
class RadialShift:
    """The depth residual explained as a radial pixel shift k r^2 (a lens), measured and simulated."""

    k_measured: float
    """Least-squares k of the measured residual on :func:`radial_shift`'s regressor (dimensionless)."""
    se_measured: float
    """Its standard error."""
    k_model: float
    """The same for the current model's simulated residual."""
    se_model: float
    share: float
    """Share of the measured residual's variance the radial shift explains (0-1)."""
    pixels: int

    @property
    def t_measured(self) -> float:
        """The measured k in standard errors."""
        return abs(self.k_measured) / self.se_measured if self.se_measured > 0 else 0.0

    @property
    def t_missing(self) -> float:
        """The part the model lacks, in standard errors of the difference."""
        se = float(np.hypot(self.se_measured, self.se_model))
        return abs(self.k_measured - self.k_model) / se if se > 0 else 0.0


def radial_shift(ctx) -> RadialShift | None:
    """How much of the depth residual a radial image shift explains. A lens moves the pixel at
    normalised image position (x, y), r^2 = x^2 + y^2, by k r^2 (x fx, y fy) pixels (k1 to first
    order), so on a smooth surface the depth read there changes by k R, R = r^2 (x fx dz/du + y fy
    dz/dv) (the ideal depth's image gradient, per pixel): a regressor no per-pixel map needs and no
    other effect of the catalog makes (a depth bias depends on z and r, not on the surface's
    slope). k is fitted by least squares to measured - ideal and to simulated - ideal over the valid
    pixels at least :data:`EDGE_MARGIN_PX` from depth edges (the first-order form needs a smooth
    surface), each residual's median per frame removed. None with fewer than 500 pixels or no
    slope."""
    from synth.lab.feature_maps import signed_edge_distance
    rs, es, ss = [], [], []
    for o in ctx.observations:
        z = np.asarray(o.ideal, np.float64)
        it = o.intrinsics
        h, w = z.shape
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        x, y = (u - it.cx) / it.fx, (v - it.cy) / it.fy
        gv, gu = np.gradient(z)
        R = (x * x + y * y) * (x * it.fx * gu + y * it.fy * gv)
        m, s = np.asarray(o.measured, np.float64), np.asarray(o.simulated, np.float64)
        ok = (z > 0) & (np.abs(signed_edge_distance(z)) >= EDGE_MARGIN_PX) & np.isfinite(R)
        for arr, out in ((m, es), (s, ss)):
            sel = ok & (m > 0) & (s > 0)
            r = np.where(sel, arr - z, np.nan)
            out.append(r[sel] - np.median(r[sel]) if sel.any() else r[sel])
        rs.append(R[ok & (m > 0) & (s > 0)])
    R = np.concatenate(rs) if rs else np.zeros(0)
    if R.size < 500 or not np.any(R != 0):
        return None
    out = []
    for e in (np.concatenate(es), np.concatenate(ss)):
        k = float(np.dot(R, e) / np.dot(R, R))
        res = e - k * R
        sd = 1.4826 * float(np.median(np.abs(res - np.median(res))))      # robust: a few flying pixels
        out += [k, sd / float(np.sqrt(np.dot(R, R)))]
    e = np.concatenate(es)
    share = float(out[0] ** 2 * np.dot(R, R) / max(float(np.dot(e, e)), 1e-30))
    return RadialShift(out[0], out[1], out[2], out[3], share, int(R.size))


def missing_lattice(ctx, fb: float):
    """The :class:`~synth.sensor.lattice.Lattice` of the measured disparities when the current
    model's simulated ones do not show it (no lattice there, or one whose step differs by > 3 %);
    None otherwise."""
    from synth.sensor.lattice import detect_lattice
    ideal, m, s = ctx.ideal, ctx.measured, ctx.simulated
    ok = (m > 0) & (ideal > 0)
    if int(ok.sum()) < 500 or not fb > 0:
        return None
    lat = detect_lattice(fb / m[ok], fb / ideal[ok], fb=fb, max_samples=20000)
    if lat is None:
        return None
    oks = (s > 0) & (ideal > 0)
    if int(oks.sum()) >= 500:
        sim = detect_lattice(fb / s[oks], fb / ideal[oks], fb=fb, max_samples=20000)
        if sim is not None and abs(sim.step_px / lat.step_px - 1.0) <= 0.03:
            return None
    return lat


def decisive_signatures(ctx, candidates) -> tuple[dict[str, str], list[tuple[str, str, str]]]:
    """({effect: why the data decide for it}, [(effect a, effect b, why they are tied)]) for the
    candidate names ``candidates``, from the measured data of ``ctx`` alone."""
    out: dict[str, str] = {}
    ties: list[tuple[str, str, str]] = []
    names = set(candidates)
    if "disparity_quantization" in names:
        lat = missing_lattice(ctx, float(getattr(ctx.preset, "fb", 0.0) or 0.0))
        if lat is not None:
            out["disparity_quantization"] = (f"the measured disparities lie on a lattice of {lat.step_px:.4f} px "
                                             f"(concentration {lat.concentration:.2f} against {lat.expected:.2f} "
                                             f"for continuous ones) that the current model does not make")
    if {"low_reflectance", "incidence_dropout"} <= names:
        hd = hole_drivers(ctx)
        if hd is not None:
            if hd.driver is not None:
                out[hd.driver] = f"the holes follow {'the returned signal' if hd.driver == 'low_reflectance' else 'the incidence angle'}: {hd.sentence()}"
            elif hd.holes >= MIN_HOLES:
                ties.append(("low_reflectance", "incidence_dropout",
                             f"the data cannot tell a signal dropout from an incidence dropout: {hd.sentence()}"))
    if "lens_distortion" in names and names & LEARNED_MAPS:
        rad = radial_shift(ctx)
        if (rad is not None and rad.t_measured >= MIN_RADIAL_T and rad.t_missing >= MIN_RADIAL_T
                and rad.share >= MIN_RADIAL_SHARE):
            out["lens_distortion"] = (f"the depth residual follows a radial image shift k r^2 on sloped surfaces "
                                      f"(k {rad.k_measured:+.3f}, {rad.t_measured:.0f} standard errors, {100 * rad.share:.0f} % of "
                                      f"the residual's variance, over "
                                      f"{rad.pixels} pixels; the current model {rad.k_model:+.3f}): a lens's "
                                      f"structure, which a per-pixel map only imitates")
    if "edge_fattening" in names and names & HOLE_ONLY:
        sp = foreground_spill(ctx)
        if sp is not None and sp[0] >= sp[2] + MIN_SPILL_EXCESS and sp[0] >= 2 * sp[1]:
            out["edge_fattening"] = (f"within {SPILL_BAND_PX:g} px on the background side of depth edges "
                                     f"{100 * sp[0]:.0f} % of {sp[3]} measured depths carry the foreground's depth "
                                     f"(> 5 % nearer; {100 * sp[1]:.0f} % farther) against {100 * sp[2]:.0f} % in the "
                                     f"current model: holes cannot make them")
    return out, ties


LEARNED_MAPS = frozenset({"disparity_distortion"})
"""Learned per-pixel maps: the rivals a lens's radial structure decides against (on a static camera
a map imitates any fixed distortion; the lens explains it with one number)."""
MIN_RADIAL_T = 8.0
"""The radial shift must stand at least this many standard errors from 0 in the measured residual
and from the current model's."""
MIN_RADIAL_SHARE = 0.08
"""... and explain at least this share of the measured residual's variance. The standard errors
treat pixels as independent, so a depth bias, whose error correlates a little with the slope of
the surface, also stands 18-38 standard errors out; the share separates: on both generators'
seeds 21, 22, 25, 26 (160x120, 4 frames) a hidden lens explained 0.16-0.48 of the residual, a
hidden depth bias at most 0.025, an incidence dropout 0."""

HOLE_ONLY = frozenset({"incidence_dropout", "low_reflectance", "projector_shadow"})
"""Effects that only remove measurements: the rivals ``edge_fattening``'s spill decides against."""

EXACT = frozenset({"disparity_quantization"})
"""Effects whose deciding signature is exact (every measured disparity on the lattice): they lead
their rivals even where the gap cannot see them (a step of 1.5-3 x the noise changes the depth
distribution by less than the gap's sampling noise: gains <= 0 on the mystery's 1-raw-unit steps)."""


def promote(ranking: list, decided: dict[str, str], gain_ratio: float, gap_margin: float = 0.1) -> list:
    """``ranking`` (candidates best first) with every candidate the data decide for (``decided``:
    effect -> reason) moved ahead of its rivals: for ``disparity_quantization`` every candidate,
    for low_reflectance / incidence_dropout the other one, for edge_fattening the hole-only effects
    (:data:`HOLE_ONLY`). It passes a rival whose gain is at most 1 / ``gain_ratio`` x its own, or
    who leaves at most ``gap_margin`` (relative) less of the gap (a signature in the data does not
    make a small effect outrank one that explains far more of the gap); it must lower the gap itself unless its signature is exact (:data:`EXACT`: then a negative
    gain, a search that did not place the steps where the lattice is, counts as 0). Sets
    ``decided_by``."""
    out = list(ranking)
    rivals = {"disparity_quantization": None, "low_reflectance": {"incidence_dropout"},
              "incidence_dropout": {"low_reflectance"}, "edge_fattening": set(HOLE_ONLY),
              "lens_distortion": set(LEARNED_MAPS)}
    for name, why in decided.items():
        pos = next((i for i, c in enumerate(out) if c.effect == name), None)
        if pos is None or not (out[pos].gain > 0 or name in EXACT):
            continue
        c = out[pos]
        c.decided_by = why
        riv = rivals.get(name, set())

        g = max(c.gain, 0.0) if name in EXACT else c.gain    # a search that missed the step, not no lattice

        def passes(r) -> bool:
            return ((g > 0 and g >= gain_ratio * r.gain)
                    or (1.0 - g) <= (1.0 - r.gain) * (1.0 + gap_margin))
        ahead = [i for i in range(pos) if (riv is None or out[i].effect in riv) and passes(out[i])]
        if ahead:
            out.pop(pos)
            out.insert(ahead[0], c)
    return out
