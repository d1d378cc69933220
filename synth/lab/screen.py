"""Which parameters of a model the data constrains: a one-at-a-time sensitivity screen run before
the search when the model has more parameters than the search budget can scan
(:class:`synth.lab.fit.FitConfig` ``screen``; e.g. the 22 of a structured-light physical pipeline,
whose first coarse sweep alone would need 22 x 7 evaluations).

Each parameter is moved alone from the start, to two probe points a fraction ``step`` of its
search range away (one on each side; on the other side twice as far when a bound is in the way:
a term switched off at 0 is probed at two magnitudes), and the gap is scored there. Its
*sensitivity* is the largest change of the gap over those probes, in units of the gap's noise
tau (twice the standard deviation of the start's gap over three simulation seeds, at least 2 %
of it: the level below which two models cannot be told apart by the data, as for the intervals
of :mod:`synth.lab.intervals`). A parameter with sensitivity below 1 is *frozen* at its start:
moving it by a quarter of its range changes nothing the data can see, so fitting it would fit
noise and spend evaluations. The others are fitted in the order of how much a probe lowered the
gap (then of sensitivity): what the data constrains most is settled first.

Approximation: one parameter at a time from the start - a parameter that only matters once
another has moved (e.g. a speckle filter once the noise is right) can be frozen; the fit report
names every frozen parameter with its sensitivity so a user can fit it alone (``--only``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["Screen", "screen_parameters", "gap_noise"]


@dataclass
class Screen:
    """Outcome of :func:`screen_parameters`."""

    order: list[str] = field(default_factory=list)
    """Keys of the parameters to fit, the most useful first."""
    frozen: dict[str, str] = field(default_factory=dict)
    """{"effect.param": reason} of the parameters left at their start value."""
    sensitivity: dict[str, float] = field(default_factory=dict)
    """{"effect.param": largest |gap change| over the probes / tau}."""
    improvement: dict[str, float] = field(default_factory=dict)
    """{"effect.param": largest gap decrease over the probes} (0 when no probe lowered it)."""
    tau: float = float("nan")
    """The gap's noise level used (see the module docstring)."""
    evaluations: int = 0
    """Gap evaluations the screen made."""


def gap_noise(gap_of: Callable, x: dict, g: float) -> float:
    """tau: twice the std of the gap of ``x`` over the search seed and two others (``gap_of(values,
    seed_offset)``), at least 2 % of the gap (the rule of :func:`synth.lab.intervals.profile_intervals`)."""
    gaps = [float(g)] + [float(gap_of(x, extra)) for extra in (1009, 2027)]
    return max(2.0 * float(np.std(gaps)), 0.02 * abs(float(g)), 1e-6)


def _probes(sp, t0: float, step: float) -> list[float]:
    a, b = sp.t_bounds
    h = max(step * (b - a), 1.0) if sp.integer else step * (b - a)
    lo, hi = t0 - h, t0 + h
    out = []
    if lo >= a and hi <= b:
        out = [lo, hi]
    elif lo < a:                                          # bound below: both probes above
        out = [min(t0 + h, b), min(t0 + 2 * h, b)] if t0 - a < 0.5 * h else [a, min(hi, b)]
    else:                                                 # bound above: both probes below
        out = [max(t0 - h, a), max(t0 - 2 * h, a)] if b - t0 < 0.5 * h else [max(lo, a), b]
    return sorted({t for t in out if abs(t - t0) > 1e-12})


def screen_parameters(gap_of: Callable, specs: Sequence, start: dict, g_start: float, step: float = 0.25,
                      threshold: float = 1.0, tau: float | None = None) -> Screen:
    """The sensitivity screen of the module docstring.

    ``gap_of(values, seed_offset=0)`` scores ``{"effect.param": value}`` on the search frames;
    ``start`` holds every spec's start value and ``g_start`` its gap. ``step``: probe distance as a
    fraction of each parameter's search range (search coordinate: log / asinh where the search
    is). ``threshold``: sensitivity (in tau) below which a parameter is frozen. ``tau``: the gap's
    noise when already known (else 2 evaluations measure it). Costs about 2 evaluations per
    parameter."""
    res = Screen()
    n0 = 0
    if tau is None:
        tau = gap_noise(gap_of, start, g_start)
        n0 = 2
    res.tau = float(tau)
    scored = []
    for sp in specs:
        t0 = sp.to_t(float(start[sp.key]))
        changes = []
        for t in _probes(sp, t0, step):
            v = sp.from_t(t)
            if v == start[sp.key]:
                continue
            trial = dict(start)
            trial[sp.key] = v
            changes.append(float(gap_of(trial)) - float(g_start))
            n0 += 1
        sens = max((abs(c) for c in changes), default=0.0) / res.tau
        gain = max([-c for c in changes] + [0.0])
        res.sensitivity[sp.key] = sens
        res.improvement[sp.key] = gain
        if sens < threshold:
            res.frozen[sp.key] = (f"frozen at its start: moving it by {step:.0%} of its range changes the gap by "
                                  f"{sens:.2f} x its noise ({res.tau:.3g}); the data does not constrain it")
        else:
            scored.append((-gain, -sens, sp.key))
    res.order = [k for *_, k in sorted(scored)]
    res.evaluations = n0
    return res
