"""What the sensor lab needs to know about effects that the effect classes do not (yet) declare.

This is the ONE place where the lab treats effects by name (besides the evidence sentences of
:mod:`synth.lab.evidence` and the data-driven starting values of :data:`synth.lab.fit.STARTERS`).
Each entry says why it exists and which sensor-side declaration would replace it; once
``synth/sensor`` declares it, the lab entry is ignored automatically (an extra parameter steps
aside when the effect's ``FITTABLE`` declares its ``replaced_by`` name), and the entry can be
deleted.

:data:`EXTRA_PARAMETERS`
    Fittable numbers of an effect that are not plain numeric ``Params`` fields listed in
    ``Effect.FITTABLE`` (the lens distortion coefficients are one tuple; the level phase of
    the disparity quantisation is a preset field). The fit (:mod:`synth.lab.fit`) searches them
    like FITTABLE parameters under the key ``"effect.name"``.
:func:`effect_sensor_types`
    Sensor types whose physics an effect models (declared by the effects themselves, as
    ``Effect.sensor_types``); :func:`synth.lab.diagnose.diagnose` does not try an effect on a
    sensor of another type.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["ExtraParameter", "EXTRA_PARAMETERS", "extra_parameters", "effect_sensor_types"]


# ------------------------------------------------------------------------------------------
# Extra fittable parameters
# ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ExtraParameter:
    """A fittable number of an effect that the effect does not declare in ``FITTABLE``."""

    low: float
    """Lower bound (the parameter's units)."""
    high: float
    """Upper bound."""
    get: Callable
    """get(config, effect) -> current value (float)."""
    set: Callable
    """set(config, effect, value) -> a new SensorConfig with the value (every other field of the
    config kept, via ``dataclasses.replace``)."""
    reason: str
    """Why the lab fits it although the effect does not declare it."""
    sensor_side: str
    """The declaration in ``synth/sensor`` that would make this entry unnecessary."""
    replaced_by: str
    """Name of the proposed sensor-side ``FITTABLE`` parameter; when the effect declares it, this
    entry is not used (:func:`extra_parameters`)."""
    applies: Callable | None = None
    """applies(config) -> False when the parameter has no effect for this sensor (then it is
    not searched); None = always."""


def _replace_effect(config, new_effect):
    return dataclasses.replace(config, effects=[new_effect if e.name == new_effect.name else e
                                                for e in config.effects])


def _padded(coeffs) -> list[float]:
    c = [float(x) for x in coeffs]
    return (c + [0.0] * 5)[:max(5, len(c))]


def _lens_get(i):
    def get(config, effect):
        return _padded(effect.coefficients(config.preset))[i] - _padded(config.preset.distortion)[i]
    return get


def _lens_set(i):
    def set_(config, effect, value):
        c = _padded(effect.coefficients(config.preset))
        c[i] = _padded(config.preset.distortion)[i] + float(value)
        return _replace_effect(config, effect.replace(coefficients=tuple(c)))
    return set_


def _quant_applies(config) -> bool:
    pre = config.preset
    return pre.fb > 0 and pre.type == "structured_light"


def _quant_step(config, effect) -> float:
    return float(effect.params.step_px or config.preset.subpixel_step_px)


def _quant_phase_get(config, effect):
    pre = config.preset
    if not _quant_applies(config):
        return 0.0
    r = pre.fb / pre.reference_depth_m / _quant_step(config, effect)
    return float(r - math.floor(r))


def _quant_phase_set(config, effect, value):
    pre = config.preset
    if not _quant_applies(config):
        return config
    step = _quant_step(config, effect)
    n = math.floor(pre.fb / pre.reference_depth_m / step)
    z0 = pre.fb / ((n + min(max(float(value), 0.0), 0.999999)) * step)
    return dataclasses.replace(config, preset=pre.replace(reference_depth_m=float(z0)), effects=list(config.effects))


_LENS_REASON = ("the effect's only parameter is the OpenCV coefficient tuple (k1, k2, p1, p2, k3), "
                "not a number FITTABLE can bound; the lab fits the radial terms k1, k2 as distortion "
                "ADDED to the camera's calibrated one (preset.distortion; zero for undistorted depth, "
                "then they are the lens's k1, k2) by writing the coefficient tuple (the tangential terms "
                "of real lenses are small and poorly constrained by depth alone)")
_LENS_SENSOR_SIDE = ("LensDistortionParams: add `k1: float = 0.0` and `k2: float = 0.0` ('radial "
                     "distortion added to k1, k2 of the base coefficients: `coefficients`, else the "
                     "preset's distortion') and FITTABLE = {'k1': (-0.5, 0.5), 'k2': (-0.5, 0.5)}; "
                     "coefficients(preset) returns the base tuple padded to 5 with k1, k2 added to its "
                     "first two terms (same names and meaning as the lab's, so diagnosis keys stay; "
                     "only a model with explicit `coefficients` differing from the preset's would read "
                     "differently)")

EXTRA_PARAMETERS: dict[str, dict[str, ExtraParameter]] = {
    "lens_distortion": {
        "k1": ExtraParameter(-0.5, 0.5, _lens_get(0), _lens_set(0), _LENS_REASON, _LENS_SENSOR_SIDE, "k1"),
        "k2": ExtraParameter(-0.5, 0.5, _lens_get(1), _lens_set(1), _LENS_REASON, _LENS_SENSOR_SIDE, "k2"),
    },
    "disparity_quantization": {
        "level_phase": ExtraParameter(
            0.0, 1.0, _quant_phase_get, _quant_phase_set,
            reason=("where the disparity levels sit, as a fraction of a step (absolute disparity "
                    "f b / z = (k + phase) step): a structured-light device quantises the disparity "
                    "relative to its reference plane, so its levels are f b / z0 + k step, and the "
                    "preset's reference depth z0 is a nominal value; for flat surfaces the error per "
                    "distance depends on the phase. The lab sets it by moving preset.reference_depth_m "
                    "by less than one step's worth of disparity (~2 % of z0 for Kinect v1 at VGA), "
                    "which the direct model uses only for this quantisation (a physical model's "
                    "stored reference pattern is re-made with it). Structured light only (active "
                    "stereo quantises the absolute disparity)"),
            sensor_side=("DisparityQuantizationParams: add `phase: float = 0.0` ('offset of the levels, "
                         "fraction of a step: the device disparity d (relative to the reference plane for "
                         "structured light, absolute for stereo) is rounded to (k + phase) step') and "
                         "FITTABLE = {'step_px': (0.0, 1.0), 'phase': (0.0, 1.0)}; apply() quantises "
                         "(round(d / s - phase) + phase) * s. Then delete this entry and make the STARTERS "
                         "periodogram return phase = (p - frac(f b / (z0 s))) mod 1 from its absolute "
                         "phase p"),
            replaced_by="phase", applies=_quant_applies),
    },
}
"""Extra fittable parameters by effect name, then parameter name (see the module docstring).
Every entry states ``reason`` and the ``sensor_side`` declaration that would replace it."""


def extra_parameters(config, effect) -> dict[str, ExtraParameter]:
    """The :data:`EXTRA_PARAMETERS` of ``effect`` that apply to ``config`` and whose name or
    ``replaced_by`` the effect's own ``FITTABLE`` does not declare (a sensor-side declaration wins)."""
    out = {}
    for k, x in EXTRA_PARAMETERS.get(effect.name, {}).items():
        if k in effect.FITTABLE or x.replaced_by in effect.FITTABLE:
            continue
        if x.applies is not None and not x.applies(config):
            continue
        out[k] = x
    return out


# ------------------------------------------------------------------------------------------
# Sensor types
# ------------------------------------------------------------------------------------------

def effect_sensor_types(effect_class) -> tuple[str, ...] | None:
    """Sensor types an effect class applies to (None = all): its ``sensor_types`` class
    attribute (:attr:`synth.sensor.registry.Effect.sensor_types`)."""
    declared = getattr(effect_class, "sensor_types", None)
    return None if declared is None else tuple(declared)
