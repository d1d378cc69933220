"""The scipy searches of :class:`synth.lab.fit.FitConfig` ``method`` (``powell``,
``differential_evolution``), measured against the coordinate descent on the recovery benchmark
(``benchmarks/bench_fit_recovery.py --method``): at the same budget the coordinate descent
recovers more parameters (README), so it stays the default; these remain for comparison."""
from __future__ import annotations

import numpy as np


__all__ = ["scipy_search"]


def scipy_search(gap_of, specs, fc, budget, progress, start_gap
                  ) -> tuple[dict[str, float], float, int]:
    """``method`` powell / differential_evolution (``fc``, a FitConfig) on the search coordinates t
    of ``specs`` (bounded; integers rounded by ``from_t``), under the same budget and cache as the
    coordinate descent; ``gap_of(values)`` scores ``{"effect.param": value}``. Returns (best values,
    best gap, evaluations)."""
    from scipy import optimize
    cache: dict[tuple, float] = {}
    best = {"g": float("inf"), "x": {s.key: s.from_t(s.to_t(s.value)) for s in specs}}

    class _Out(Exception):
        pass

    def vals_of(t) -> dict[str, float]:
        return {s.key: s.from_t(float(np.clip(ti, *s.t_bounds))) for s, ti in zip(specs, t)}

    def f(t) -> float:
        vals = vals_of(t)
        key = tuple(round(vals[s.key], 12) for s in specs)
        if key in cache:
            return cache[key]
        if not budget.left:
            raise _Out
        budget.used += 1
        g = float(gap_of(vals))
        cache[key] = g
        if progress is not None:
            progress(1)
        if g < best["g"]:
            best["g"], best["x"] = g, vals
        return g

    t0 = np.array([s.to_t(s.value) for s in specs])
    if start_gap is not None:
        cache[tuple(round(best["x"][s.key], 12) for s in specs)] = float(start_gap)
        best["g"] = float(start_gap)
    bounds = [s.t_bounds for s in specs]
    try:
        if fc.method == "powell":
            optimize.minimize(f, t0, method="Powell", bounds=bounds,
                              options={"maxfev": int(fc.max_evaluations), "xtol": 1e-3, "ftol": fc.tolerance})
        else:
            pop = 5
            iters = max(1, int(fc.max_evaluations) // (pop * len(specs)) - 1)
            optimize.differential_evolution(f, bounds, x0=t0, popsize=pop, maxiter=iters, seed=int(fc.seed),
                                            polish=False, tol=fc.tolerance, init="latinhypercube")
    except _Out:
        pass
    return best["x"], best["g"], budget.used
