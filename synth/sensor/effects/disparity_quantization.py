"""Direct model: the device reports disparity in sub-pixel steps."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_QUANTIZE, ConfigParameter, Effect, Signature, param, register_effect


@dataclass
class DisparityQuantizationParams:
    step_px: float = param(0.0, "px")
    """Disparity step, pixels; 0 = the preset's (Kinect v1: 1/8)."""
    step_source: str = param("search", "", choices=("search", "lattice"))
    """Where ``step_px`` comes from: "search" (the fit searches it within its bounds) or "lattice"
    (``fit_start`` read it off the disparity lattice of the measurement, which fixes the step
    whatever the noise; the fit then searches it only within :data:`LATTICE_WINDOW` of that value)."""


LATTICE_WINDOW = 0.005
"""Relative half-width of the step's search window once the step is read off the measured lattice.
The lattice gives the step to ~1e-5 (every measured disparity lies on it); at a step of 1.5-3 x the
noise the gap barely sees the step, and a free search trades it for noise: with the noise start 13 %
high a search moved a measured 0.03125 px step to 0.007 px (a lattice finer than the noise: no
quantisation), where the gap at the true step and noise was 25 % lower."""


def _phase_applies(config) -> bool:
    pre = config.preset
    return pre.fb > 0 and pre.type == "structured_light"


def _step(config, effect) -> float:
    return float(effect.params.step_px or config.preset.subpixel_step_px)


def _phase_get(config, effect) -> float:
    pre = config.preset
    if not _phase_applies(config):
        return 0.0
    r = pre.fb / pre.reference_depth_m / _step(config, effect)
    return float(r - math.floor(r))


def _phase_set(config, effect, value):
    pre = config.preset
    if not _phase_applies(config):
        return config
    step = _step(config, effect)
    n = math.floor(pre.fb / pre.reference_depth_m / step)
    z0 = pre.fb / ((n + min(max(float(value), 0.0), 0.999999)) * step)
    return dataclasses.replace(config, preset=pre.replace(reference_depth_m=float(z0)), effects=list(config.effects))


LEVEL_PHASE = ConfigParameter(
    0.0, 1.0, _phase_get, _phase_set,
    doc=("where the disparity levels sit, as a fraction of a step (absolute disparity f b / z = (k + phase) "
         "step): a structured-light device quantises the disparity relative to its reference plane, so its "
         "levels are f b / z0 + k step, and the preset's reference depth z0 is a nominal value; for flat "
         "surfaces the error per distance depends on the phase. It is set by moving preset.reference_depth_m "
         "by less than one step's worth of disparity (~2 % of z0 for Kinect v1 at VGA), which the direct "
         "model uses only for this quantisation (a physical model's stored reference pattern is re-made with "
         "it). Structured light only (active stereo quantises the absolute disparity)"),
    applies=_phase_applies, unit="1")


def _concentration(d: np.ndarray, step: float) -> float:
    return float(np.abs(np.mean(np.exp(2j * np.pi * d / step)))) if d.size else float("nan")


@register_effect
class DisparityQuantization(Effect):
    """Depth snaps to the levels of a quantised disparity: z = 1 / (1/z0 + k step / (f b)).

    Physics/device: the correlator's sub-pixel interpolation has a fixed resolution (Kinect v1:
    1/8 px, 11-bit disparity); depth is computed from that integer code, so it takes discrete
    values whose spacing grows with the square of depth: dz ~ z^2 step / (f b) (2.9 mm at 1 m,
    4.6 cm at 4 m for Kinect v1). The physical pipeline quantises inside ``block_matching``;
    applying this effect after it changes nothing (idempotent). No-op for ToF.
    """

    name = "disparity_quantization"
    SIGNATURE = Signature(
        "discrete depth levels growing with z²",
        "Measured depths take only discrete values whose spacing grows with the square of the "
        "distance (one disparity step = z² · step / (f · b)); a continuous model has tiny, "
        "constant spacings.",
        plot="disparity_levels")
    sensor_types = ("structured_light", "active_stereo")  # triangulation
    Params = DisparityQuantizationParams
    START_PRIORITY = -1     # the noise start reads the noise through the levels it finds (axial_noise.fit_start)
    FITTABLE = {"step_px": (0.0, 1.0)}
    START_ONLY_PARAMS = ("step_source",)
    CONFIG_PARAMETERS = {"level_phase": LEVEL_PHASE}
    stage = STAGE_QUANTIZE

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """Step and phase of the disparity lattice the measured disparities d = f b / z lie on,
        found from the measurement alone (:func:`synth.sensor.lattice.detect_lattice`: a periodogram
        of d against the concentration that the ideal disparities of the same pixels and the noise
        would give, the depth PNG's 1/5000 m rounding weighted; recovers the step within 3 % for
        step / noise 1.5-8 on hand-made disparities). Nothing is returned (defaults kept) when no
        lattice shows. The phase is the absolute one of ``level_phase``; the lab drops it where
        that parameter does not apply (active stereo). ``step_source`` "lattice" narrows the step's
        search to :data:`LATTICE_WINDOW` around the detected step (:meth:`search_bounds`)."""
        lat = cls.lattice(measured, config.preset, frames)
        if lat is None:
            return {}
        return {"disparity_quantization.step_px": lat.step_px, "disparity_quantization.level_phase": lat.phase,
                "disparity_quantization.step_source": "lattice"}

    def search_bounds(self, preset) -> dict[str, tuple[float, float]]:
        """The step within :data:`LATTICE_WINDOW` of its value when it was read off the measured lattice
        (``step_source`` "lattice"), else the FITTABLE range."""
        out = dict(self.plausible_bounds(preset))
        step = float(self.params.step_px)
        if self.params.step_source == "lattice" and step > 0:
            out["step_px"] = (step * (1.0 - LATTICE_WINDOW), step * (1.0 + LATTICE_WINDOW))
        return out

    @staticmethod
    def lattice(measured, preset, frames, samples_per_frame: int = 5000):
        """The detected :class:`~synth.sensor.lattice.Lattice` of the measured disparities of kept
        frames ``frames`` (None: no lattice, or the sensor does not triangulate)."""
        from synth.sensor.lattice import detect_lattice
        if preset.fb <= 0:
            return None
        rng = np.random.default_rng(0)
        d, di = [], []
        for k in frames:
            m = measured.measured_depth(k)
            zi = measured.render(k).depth
            sel = np.flatnonzero(((m > 0) & (zi > 0)).ravel())
            if sel.size:
                sel = rng.choice(sel, size=min(sel.size, samples_per_frame), replace=False)
                d.append(preset.fb / m.ravel()[sel].astype(np.float64))
                di.append(preset.fb / zi.ravel()[sel].astype(np.float64))
        if not d:
            return None
        return detect_lattice(np.concatenate(d), np.concatenate(di), fb=preset.fb, max_samples=20000)

    def apply(self, state, draw) -> None:
        from synth.sensor.matching import MatchSetup
        pre = state.preset
        if pre.type == "tof" or pre.fb <= 0:
            state.log[self.name] = {"active": False}
            return
        setup = MatchSetup.for_preset(pre)
        if self.params.step_px:
            setup = dataclasses.replace(setup, step=float(self.params.step_px))
        d = setup.quantize(setup.depth_to_disparity(np.where(state.valid, state.depth, 0)))
        z = setup.disparity_to_depth(d)
        state.depth = np.where(state.valid, z, 0).astype(np.float32)
        state.valid &= state.depth > 0
        state.disparity = np.where(state.valid, d, np.nan).astype(np.float32)
        state.log[self.name] = {"step_px": setup.step}

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """The lattice of the measured disparities d = f b / z detected from the measurement alone
        (:func:`synth.sensor.lattice.detect_lattice`), quoted with the fitted step.

        Signature present: a lattice is detected (its concentration exceeds what continuous
        disparities of the same scene and noise would give by >= 0.3)."""
        pre = ctx.preset
        fb = float(pre.fb)
        if fb <= 0:
            return "the sensor does not triangulate: no disparity levels."
        from synth.sensor.lattice import detect_lattice
        m, zs, zi = ctx.measured, ctx.simulated, ctx.ideal
        ok = (m > 0) & (zi > 0)
        lat = detect_lattice(fb / m[ok], fb / zi[ok], fb=fb, max_samples=20000)
        fitted = params.get("disparity_quantization.step_px") or float(pre.subpixel_step_px)
        if lat is None:
            conc = _concentration(fb / m[m > 0], fitted)
            return ctx.weak("disparity-lattice signature", gain,
                            f"no step in 0.02-1 px puts the measured disparities f·b/z on a lattice "
                            f"(concentration {conc:.2f} at the fitted {fitted:.3f} px)")
        step = lat.step_px
        conc_s = _concentration(fb / zs[zs > 0], step)
        return (f"measured disparities f·b/z lie on a lattice of {step:.4f} px, phase {lat.phase:.2f} "
                f"(found in the measurement alone: circular concentration {lat.concentration:.2f} against "
                f"{lat.expected:.2f} for continuous disparities of this scene and noise, {conc_s:.2f} for the "
                f"current model; fitted step {fitted:.4f} px), i.e. discrete depth levels spaced "
                f"{1000 * step / fb:.1f} mm at 1 m and {4000 * step / fb:.1f} mm at 2 m, growing with z².")
