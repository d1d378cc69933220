"""ToF: the periodic 'wiggling' error of a non-sinusoidal modulation."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_DEPTH, Effect, Signature, param, register_effect


@dataclass
class WigglingParams:
    amplitude_m: float = param(0.003, "m")
    """Amplitude of the periodic range error, metres."""
    period_m: float = param(0.47, "m")
    """Period in range, metres (a quarter of the 1.875 m unambiguous range at 80 MHz: odd
    harmonics of the modulation alias onto the 4th harmonic of the phase with 4-tap sampling)."""
    phase_rad: float = param(0.0, "rad")
    """Phase of the error at range 0."""


@register_effect
class Wiggling(Effect):
    """Range error A sin(2 pi r / period + phase), r the distance along the ray.

    Physics: the phase of a continuous-wave ToF camera is computed assuming sinusoidal
    modulation; the real signal has harmonics, which turn into a periodic, distance-dependent
    error ('wiggling', Lindner & Kolb 2006; a few mm for Kinect v2). Deterministic.
    """

    name = "wiggling"
    SIGNATURE = Signature(
        "periodic error over distance",
        "The median error oscillates with distance (ToF phase wiggling).",
        panels=(("distance", "bias"),))
    IDENTITY_PARAMS = {"amplitude_m": 0.0}
    sensor_types = ("tof",)  # phase measurement of continuous-wave time of flight
    Params = WigglingParams
    FITTABLE = {"amplitude_m": (0.0, 0.05), "period_m": (0.05, 5.0), "phase_rad": (-np.pi, np.pi)}
    stage = STAGE_DEPTH + 2

    def apply(self, state, draw) -> None:
        p = self.params
        z = state.depth
        c = state.ray_dirs_cam[..., 2]                          # z / r along each ray
        r = z / np.maximum(c, 1e-6)
        e = p.amplitude_m * np.sin(2 * np.pi * r / p.period_m + p.phase_rad)
        state.depth = np.where(state.valid, z + e * c, 0).astype(np.float32)
