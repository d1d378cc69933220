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
    CONFIG_PARAMETERS = {"level_phase": LEVEL_PHASE}
    stage = STAGE_QUANTIZE

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """Step and phase of the disparity levels from a periodogram of the measured disparities.

        For a step s the circular concentration R(s) = |mean exp(2 pi i d / s)| of the measured
        disparities d = f b / z is ~1 when d takes values on a grid of spacing s (or a divisor of
        it) and ~0 for continuous disparities - unless the scene itself concentrates them (a wall
        facing the camera gives one disparity to many pixels: R ~ 1 at every step), so the
        concentration of the ideal disparities of the same pixels is subtracted (an independent-
        generator pair with dark materials removed had started at 0.494 px for a 0.442 px step).
        The largest s with R >= 0.75 max R is the step, the
        argument of the mean gives the level phase (the peak of the last run of R >= 0.75 max R):
        the divisors s / k of the step are on the grid too but noise lowers their R (by
        exp(-2 pi^2 sigma^2 k^2 / s^2)), and the side lobes of the true step reach ~0.5 max R when the
        disparities span few levels (a 0.3965 px side lobe at R 0.505 beside the true 0.3609 px step
        at 0.989 had won under the former 0.5 threshold).
        Nothing is returned (defaults kept) when no step in [0.02, 1] px reaches R = 0.3. The
        phase is the absolute one of ``level_phase``; the lab drops it where that parameter does
        not apply (active stereo).
        """
        pre = config.preset
        if pre.fb <= 0:
            return {}
        rng = np.random.default_rng(0)
        d, di = [], []
        for k in frames:
            m = measured.measured_depth(k)
            zi = measured.render(k).depth
            sel = np.flatnonzero(((m > 0) & (zi > 0)).ravel())
            if sel.size:
                sel = rng.choice(sel, size=min(sel.size, 5000), replace=False)
                d.append(pre.fb / m.ravel()[sel].astype(np.float64))
                di.append(pre.fb / zi.ravel()[sel].astype(np.float64))
        if not d:
            return {}
        d, di = np.concatenate(d), np.concatenate(di)
        steps = np.geomspace(0.02, 1.0, 500)
        R = np.empty(steps.size)
        ph = np.empty(steps.size)
        for i, st in enumerate(steps):
            z = np.exp(2j * np.pi * d / st).mean()
            # the scene's own concentration (a wall facing the camera: one disparity for many pixels,
            # R ~ 1 at every step) is in the ideal disparities of the same pixels too: only the excess
            # is the quantisation's
            R[i], ph[i] = abs(z) - abs(np.exp(2j * np.pi * di / st).mean()), np.angle(z)
        if R.max() < 0.3:
            return {}
        high = np.flatnonzero(R >= 0.75 * R.max())
        run = high[-1:]                      # the last (largest-step) run of high concentration ...
        for j in high[::-1][1:]:
            if j != run[0] - 1:
                break
            run = np.concatenate([[j], run])
        i = int(run[np.argmax(R[run])])     # ... and its peak
        phase = (ph[i] / (2 * np.pi)) % 1.0
        return {"disparity_quantization.step_px": float(steps[i]), "disparity_quantization.level_phase": float(phase)}

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
        if not (ctx.ge(conc, 0.3) and ctx.ge(conc, conc_s + 0.2)):
            return ctx.weak("disparity-grid signature", gain,
                         f"the measured disparities f·b/z have a circular concentration of {conc:.2f} on a grid of "
                         f"{step:.3f} px ({conc_s:.2f} for the current model)")
        return (f"measured disparities f·b/z sit on a grid of {step:.3f} px (circular concentration {conc:.2f}; "
                f"{conc_s:.2f} for the current model's depths), i.e. discrete depth levels spaced "
                f"{1000 * step / fb:.1f} mm at 1 m and {4000 * step / fb:.1f} mm at 2 m, growing with z².")
