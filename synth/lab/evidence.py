"""Plain-language evidence for a diagnosed effect, computed from the measured data.

Each sentence is built from statistics of the measured depth against the ideal geometry
(holes beside depth edges, hole rate per incidence angle or material, error per image radius
or distance, discreteness of the disparity), not from the fit alone, so a reader can check the
diagnosis in the data. Each effect writes its own sentence in its own file
(:meth:`synth.sensor.registry.Effect.evidence`); effects without one get
:func:`generic_evidence`, which names the comparison feature whose term the fitted effect
lowered most.

An effect's ``evidence(ctx, params, gain)`` gets an :class:`EvidenceContext`: the measured
observations of the diagnosed frames, the current model's simulation (``simulated``), the
preset, the pooled per-pixel features (edge distances, incidence, image radius, materials) and
the sentence helpers (:meth:`~EvidenceContext.pct`, :meth:`~EvidenceContext.weak`, ...), so
the effect files need nothing from the lab. It measures the effect's *signature* (e.g. the hole
rate on the projector-shadow side of depth edges) where the effect acts, where it does not (the
contrast region) and in the current model, and decides from the sign and size of the
differences (thresholds in each docstring, mostly :attr:`EvidenceContext.MIN_RATE_EXCESS`)
whether the signature is present. Only then does the sentence claim it ("grows with the image
radius", "lie on a lattice"); otherwise it says that the fit prefers the effect (or not) but the
signature is weak, and gives the numbers.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from synth.lab.feature_maps import incidence_angle_deg, radial_distance, shadow_edge_distance, signed_edge_distance
from synth.lab.features import FrameObservation

__all__ = ["EvidenceContext", "Spill", "evidence_for", "generic_evidence", "has_evidence"]

SPILL_BAND_PX = 6.0
"""Background-side band of depth edges where foreground-valued (fattened) depths are counted, pixels."""


@dataclass(frozen=True)
class Spill:
    """Foreground depth spilled onto the background side of depth edges (:meth:`EvidenceContext.foreground_spill`).

    Each share is taken over the depths that side has in the band (measured: its valid pixels;
    model: the current model's valid pixels), so holes on either side do not dilute it."""

    near: float
    """Share of the measured depths in the band that are > 5 % nearer than the ideal (background) depth."""
    far: float
    """Share of the measured depths in the band that are > 5 % farther (plain noise makes it like ``near``)."""
    model_near: float
    """Share of the current model's depths in the band that are > 5 % nearer."""
    pixels: int
    """Measured valid pixels in the band."""
    model_pixels: int
    """The current model's valid pixels in the band."""


WEAK = "is weak in the measured data"
"""The phrase of every sentence whose signature the data do not show clearly."""

NEGLIGIBLE_GAIN = 0.01
"""Below this gain a sentence that finds the signature adds that the fitted effect barely helps."""


@dataclass
class EvidenceContext:
    """What evidence sentences read: the data, pooled per-pixel features and sentence helpers."""

    observations: Sequence[FrameObservation]
    """Measured (``measured``) and current-model (``simulated``) depth with the ideal geometry."""
    preset: object
    """The sensor preset (focal length, baseline, projector offset)."""
    albedo: dict[int, float] = field(default_factory=dict)
    """Instance id -> material albedo."""
    _cache: dict = field(default_factory=dict)
    """Pooled per-pixel arrays already computed (by name)."""

    MIN_RATE_EXCESS: ClassVar[float] = 0.05
    """A hole-rate signature counts as present when the measured rate where the effect acts
    exceeds both the measured rate where it does not act (the contrast region) and the current
    model's rate there by at least this much (5 percentage points; the sampling noise of a rate
    over the thousands of pixels of a band is ~1 point)."""
    WEAK: ClassVar[str] = WEAK

    def pooled(self, name: str, fn: Callable[[FrameObservation], np.ndarray]) -> np.ndarray:
        """Concatenation over frames of fn(obs)[geometry pixels] (cached by name)."""
        if name not in self._cache:
            self._cache[name] = np.concatenate([np.asarray(fn(o)).reshape(-1)[(o.ideal > 0).reshape(-1)]
                                                for o in self.observations])
        return self._cache[name]

    # -- the data, pooled over the geometry pixels of every frame ----------------------------
    @property
    def ideal(self) -> np.ndarray:
        """Ideal depth, metres."""
        return self.pooled("ideal", lambda o: o.ideal).astype(np.float64)

    @property
    def measured(self) -> np.ndarray:
        """Measured depth, metres (0 = hole)."""
        return self.pooled("measured", lambda o: o.measured).astype(np.float64)

    @property
    def simulated(self) -> np.ndarray:
        """The current model's depth, metres (0 = hole)."""
        return self.pooled("simulated", lambda o: o.simulated).astype(np.float64)

    def shadow_edge_distance(self) -> np.ndarray:
        """Signed distance to the nearest depth edge along the baseline, pixels (> 0 on the
        projector-shadow side); needs a projector offset."""
        off = self.observations[0].projector_offset_m
        return self.pooled("edge_shadow", lambda o: shadow_edge_distance(o.ideal, o.intrinsics, off))

    def edge_distance(self) -> np.ndarray:
        """Signed distance to the nearest depth edge, pixels (> 0 on the background side)."""
        return self.pooled("edge_distance", lambda o: signed_edge_distance(o.ideal))

    def foreground_spill(self, band_px: float = SPILL_BAND_PX) -> Spill:
        """The one definition of edge fattening's signature, used by its evidence sentence and by
        :func:`synth.lab.decisive.foreground_spill`: within ``band_px`` pixels on the background side
        of depth edges (geometry pixels only), the shares of measured and of simulated depths
        carrying a nearer (foreground) depth."""
        ed, z, m, s = self.edge_distance(), self.ideal, self.measured, self.simulated
        band = (ed > 0) & (ed <= band_px) & (z > 0)
        mb, sb = band & (m > 0), band & (s > 0)
        return Spill(self.rate(m < 0.95 * z, mb), self.rate(m > 1.05 * z, mb), self.rate(s < 0.95 * z, sb),
                     int(mb.sum()), int(sb.sum()))

    def incidence_deg(self) -> np.ndarray:
        """Incidence angle of the camera ray on the surface, degrees."""
        return self.pooled("incidence", lambda o: incidence_angle_deg(o.normals, o.intrinsics))

    def radial(self) -> np.ndarray:
        """Distance from the image centre, 0 at the centre and 1 at the corners."""
        return self.pooled("radial", lambda o: radial_distance(o.intrinsics)[0])

    def material_ids(self) -> np.ndarray:
        """Material id of each pixel (names in the observations' ``material_names``)."""
        return self.pooled("ids", lambda o: o.material_ids)

    # -- sentence helpers --------------------------------------------------------------------
    @staticmethod
    def pct(x: float) -> str:
        """A fraction as a percentage: never rounds a non-zero rate to "0 %" or a partial one to "100 %"."""
        if not math.isfinite(x):
            return "n/a"
        if 0 < x < 0.005:
            return "<1 %"
        if 0.995 <= x < 1:
            return ">99 %"
        return f"{100 * x:.0f} %"

    @staticmethod
    def mm(x: float) -> str:
        """Metres as signed millimetres."""
        return "n/a" if not math.isfinite(x) else f"{1000 * x:+.1f} mm"

    @staticmethod
    def rate(mask: np.ndarray, sel: np.ndarray) -> float:
        """Fraction of ``sel`` where ``mask`` holds (NaN for an empty selection)."""
        n = int(sel.sum())
        return float(mask[sel].mean()) if n else float("nan")

    @staticmethod
    def ge(a: float, b: float) -> bool:
        """a >= b for finite numbers (False when either is NaN)."""
        return math.isfinite(a) and math.isfinite(b) and a >= b

    @classmethod
    def weak(cls, what: str, gain: float | None, numbers: str) -> str:
        """The sentence of a candidate whose signature the data do not show clearly: the fit may
        still prefer it, but nothing in the numbers is claimed beyond what they are."""
        if gain is not None and gain > 0:
            head = f"adding it lowers the gap by {cls.pct(gain)}, but the {what} {WEAK}"
        elif gain is not None:
            head = f"adding it does not lower the gap, and the {what} {WEAK}"
        else:
            head = f"the {what} {WEAK}"
        return f"{head}: {numbers}."


def has_evidence(name: str) -> bool:
    """True when effect ``name`` writes its own evidence sentence."""
    from synth.sensor.registry import Effect, effect_class
    return effect_class(name).evidence.__func__ is not Effect.evidence.__func__


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
                f"{EvidenceContext.pct(before.spatial_term)} -> {EvidenceContext.pct(after.spatial_term)}).")
    fa, fb = before.feature_terms[best], after.feature_terms[best]
    return f"the effect mainly explains the errors binned by {best.replace('_', ' ')} (term {fa:.3f} -> {fb:.3f})."


def evidence_for(name: str, ctx: EvidenceContext, params: dict, before=None, after=None,
                 gain: float | None = None) -> str:
    """The evidence sentence of effect ``name`` (its own ``evidence``, else the generic one).

    ``gain``: the candidate's gap reduction (fraction), quoted when the data show its
    signature only weakly."""
    from synth.sensor.registry import effect_class
    fn = effect_class(name).evidence if has_evidence(name) else None
    try:
        if fn is not None:
            s = fn(ctx, params, gain)
        elif before is not None and after is not None:
            s = generic_evidence(before, after)
        else:
            s = "no evidence function for this effect."
        if fn is not None and gain is not None and gain < NEGLIGIBLE_GAIN and WEAK not in s:
            # the data show the signature, but the fitted effect does not explain it
            s = s.rstrip(".") + ("; yet adding the fitted effect lowers the gap by only " + EvidenceContext.pct(gain) if gain > 0
                                 else "; yet adding the fitted effect does not lower the gap") + "."
    except (ValueError, IndexError, ZeroDivisionError, FloatingPointError) as e:  # degenerate data
        s = f"evidence not available ({type(e).__name__}: {e})."
    return s[0].upper() + s[1:] if s else s
