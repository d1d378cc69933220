"""Uncertainty of a fit: the profile interval of each fitted parameter (model.json's fit record,
the CLI line and the lab report)."""
from __future__ import annotations

import numpy as np


__all__ = ["profile_intervals"]


def profile_intervals(gap_of, specs, best_x: dict, g_best: float, steps: int = 4) -> tuple[dict, float]:
    """Profile interval of every fitted parameter: how far it can move (the others at the fit)
    before the gap rises by more than its own noise.

    ``gap_of(values, seed_offset=0)`` scores ``{"effect.param": value}`` on the fit's search frames
    with the simulation seeds shifted by ``seed_offset``. The noise tau is twice the standard
    deviation of the best model's gap over three simulation seeds (the search's and two others),
    at least 2 % of the gap: the gap of one parameter set varies that much with the random draws
    alone, so values whose gap is within tau of the best cannot be told apart by the data. From
    the best value, steps of 1/32 of the search range (in the search coordinate: logarithmic /
    asinh where the search is; one unit for integers) doubling ``steps`` times go outward on each
    side until the gap exceeds g_best + tau; the end is interpolated linearly between the last
    step inside and the first outside, or is the last step (up to the search bound) when none
    is outside. Costs about 2 + 2 x steps evaluations per parameter. Approximate: one parameter at
    a time (a coupled pair gets a narrower interval than its joint confidence region)."""
    gaps = [float(g_best)] + [float(gap_of(best_x, extra)) for extra in (1009, 2027)]
    tau = max(2.0 * float(np.std(gaps)), 0.02 * abs(float(g_best)), 1e-6)
    out = {}
    for sp in specs:
        v0 = float(best_x[sp.key])
        t0 = sp.to_t(v0)
        tlo, thi = sp.t_bounds
        ends = []
        for sign in (-1.0, 1.0):
            step = 1.0 if sp.integer else (thi - tlo) / 32.0
            t_in, g_in, end = t0, float(g_best), None
            for _ in range(int(steps)):
                t = min(max(t0 + sign * step, tlo), thi)
                if t == t_in:
                    break                                   # already on the bound
                vals = dict(best_x)
                vals[sp.key] = sp.from_t(t)
                g = float(gap_of(vals))
                if g > g_best + tau:
                    frac = 0.0 if sp.integer else min(1.0, max(0.0, (g_best + tau - g_in) / max(g - g_in, 1e-12)))
                    end = sp.from_t(t_in + (t - t_in) * frac)
                    break
                t_in, g_in = t, g
                step *= 2.0
            ends.append(end if end is not None else sp.from_t(t_in))
        lo, hi = sorted((float(ends[0]), float(ends[1])))
        out[sp.key] = (min(lo, v0), max(hi, v0))
    return out, tau
