"""The search of the lab's fits: bounded coordinate descent over the fittable parameters (or a
scipy search, :mod:`synth.lab.scipy_search`) on an :class:`~synth.lab.objective.Objective`.

Bounded coordinate descent over the fittable parameters (each effect's ``FITTABLE`` bounds, plus
the ``CONFIG_PARAMETERS`` it declares for numbers that live outside its ``Params``, e.g. the
phase of the disparity levels, which is the preset's reference depth):

1. scan: per parameter, from the current point, a coarse grid of ``grid_points`` values over
   its bounds on the parameter's search scale (:class:`ParamSpec`: logarithmic for positive
   bounds spanning >= 2 decades, asinh for bounds that include 0 - noise levels, offsets and
   distortion coefficients are searched over decades of magnitude, not in equal steps of a
   wide range; integers linear and rounded), plus the current value;
2. every parameter whose scan improved the gap is refined alone from the same point by
   golden-section search (``refine_iterations`` steps, then one parabolic step through the best
   point tried and its two neighbours) in the bracket between the grid
   neighbours of its best grid value (the objective is not assumed unimodal over the whole
   range, only inside that bracket); in the first sweep so is a parameter whose best grid value
   is its starting value (a closed-form start is close, not exact: no grid value beats it, but a
   bracket around it may); the other parameters that did not help cost only their scan;
3. the 1-D optima are combined in order of their gap (Gauss-Southwell rule: of strongly
   coupled parameters, e.g. a constant and a quadratic noise term, the one that explains most
   is settled first), each re-scored at the moving point and kept only while it helps;
4. further sweeps (``sweeps``) scan every parameter in a bracket of one grid spacing around
   its current value, until a sweep improves the gap by less than ``tolerance`` (relative).

Approximations: coordinate descent finds a local optimum of a non-convex objective (strongly
coupled parameters, e.g. a constant and a quadratic noise term, are refined alternately, not
jointly); the grid makes it robust to the flat regions that dropout parameters produce far from
the data.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from synth.lab.params import ParamSpec, set_params

__all__ = ["search"]

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


class _Budget:
    """Evaluation budget of one search, plus the optional wall-clock guard (``FitConfig.max_seconds``)."""

    def __init__(self, max_evals: int, max_seconds: float | None = None):
        self.max_evals = int(max_evals)
        self.deadline = None if max_seconds is None else time.perf_counter() + float(max_seconds)
        self.used = 0
        self.time_capped = False

    @property
    def left(self) -> bool:
        if self.used >= self.max_evals:
            return False
        if self.deadline is not None and time.perf_counter() >= self.deadline:
            self.time_capped = True
            return False
        return True


def search(objective: Callable, config, specs: Sequence[ParamSpec], fit_config: FitConfig,
           progress=None, start_gap: float | None = None, refine_below: float | None = None,
           local: bool | frozenset = False, stats: dict | None = None) -> tuple[dict[str, float], float, int]:
    """Bounded coordinate descent (module docstring). Returns (best values, best gap, evaluations).

    ``start_gap``: the already known gap of the starting values. ``refine_below``: only
    parameters whose scan reached a gap below this value are refined (a candidate effect that
    cannot beat the model without it costs only its scans). ``local``: skip the coarse grid,
    every sweep scans one grid spacing around the current values (polishing a good start); a set
    of keys: only for those parameters.
    ``stats``: a dict that receives ``time_capped`` (True when the wall-clock guard
    ``FitConfig.max_seconds`` stopped the search) and ``evaluations``. Depth-limit parameters
    are searched only where they keep the objective's measured valid depths
    (:func:`synth.lab.guards.bound_for_objective`).
    """
    fc = fit_config
    budget = _Budget(fc.max_evaluations, fc.max_seconds)
    from synth.lab.guards import bound_for_objective
    specs, moved = bound_for_objective(objective, config, specs)   # depth limits keep the measured depths
    if moved:
        start_gap = None
    try:
        if getattr(fc, "method", "coordinate") != "coordinate" and specs:
            from synth.lab.scipy_search import scipy_search
            return scipy_search(lambda vals: objective(set_params(config, vals)), specs, fc, budget, progress,
                                start_gap)
        return _search(objective, config, specs, fc, budget, progress, start_gap, refine_below, local)
    finally:
        if stats is not None:
            stats["time_capped"] = bool(stats.get("time_capped", False) or budget.time_capped)
            stats["evaluations"] = int(stats.get("evaluations", 0)) + budget.used


def _search(objective, config, specs, fc: FitConfig, budget: _Budget, progress, start_gap, refine_below,
            local) -> tuple[dict[str, float], float, int]:
    cache: dict[tuple, float] = {}
    x = {s.key: s.from_t(s.to_t(s.value)) for s in specs}

    def f(vals: dict[str, float]) -> float:
        key = tuple(round(vals[s.key], 12) for s in specs)
        if key in cache:
            return cache[key]
        if not budget.left:
            return float("inf")
        budget.used += 1
        g = objective(set_params(config, vals))
        cache[key] = g
        if progress is not None:
            progress(1)
        return g

    if start_gap is not None:
        cache[tuple(round(x[s.key], 12) for s in specs)] = float(start_gap)
        best = float(start_gap)
    else:
        best = f(x)
    for sweep in range(int(fc.sweeps)):
        sweep_start = best
        # 1. a 1-D scan of every parameter from the current point
        scans = []
        for s in specs:
            if not budget.left:
                break
            a, b = s.t_bounds
            if b <= a:
                continue
            cur_t = s.to_t(x[s.key])
            ga, gb = s.grid_t_bounds
            if sweep == 0 and not (local is True or (local and s.key in local)):
                grid = [min(max(t, a), b) for t in np.linspace(ga, gb, int(fc.grid_points))]
            else:
                h = (gb - ga) / max(int(fc.grid_points) - 1, 1) / 2
                grid = [max(a, cur_t - h), min(b, cur_t + h)]
            grid = sorted(set(grid) | {cur_t})
            vals = []
            for t in grid:
                trial = dict(x)
                trial[s.key] = s.from_t(t)
                vals.append(f(trial))
            i = int(np.argmin(vals))
            scans.append((vals[i], s, grid, i, sweep == 0 and grid[i] == cur_t))
        # 2. every parameter whose scan helped is refined alone from the sweep's start point
        #    (golden section in the bracket of its best grid value), then the 1-D optima are
        #    combined, the best first (Gauss-Southwell order), each re-scored at the moving point
        #    and kept only if it still helps
        x0, best0 = dict(x), best
        singles = []
        for val, s, grid, i, at_start in scans:
            if val >= best0 and not at_start:
                continue
            xs = dict(x0)
            xs[s.key] = s.from_t(grid[i])
            vs = val
            if refine_below is None or val < refine_below:
                vs, xs = _golden(f, xs, s, grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)], val,
                                 int(fc.refine_iterations), budget)
            if vs < best0:
                singles.append((vs, s.key, xs[s.key]))
        singles.sort(key=lambda r: r[0])
        moved = False
        for vs, key, v in singles:
            trial = dict(x)
            trial[key] = v
            if moved:
                if not budget.left:
                    break
                vs = f(trial)
            if vs < best:
                best, x, moved = vs, trial, True
        if not budget.left or best >= sweep_start * (1.0 - fc.tolerance):
            break
    return x, best, budget.used


def _golden(f, x, s: ParamSpec, a: float, b: float, best: float, iters: int, budget: _Budget):
    """Golden-section search of parameter ``s`` in [a, b] (transformed units); keeps the best."""
    if iters <= 0 or b <= a:
        return best, x

    seen = {s.to_t(x[s.key]): best}        # t -> gap of every point tried, for the parabolic step

    def g(t):
        trial = dict(x)
        trial[s.key] = s.from_t(t)
        v = f(trial)
        seen[t] = v
        return v, trial

    c = b - GOLDEN * (b - a)
    d = a + GOLDEN * (b - a)
    fc_, xc = g(c)
    fd, xd = g(d)
    for cand_f, cand_x in ((fc_, xc), (fd, xd)):
        if cand_f < best:
            best, x = cand_f, cand_x
    for _ in range(iters - 1):
        if not budget.left:
            break
        if s.integer and abs(s.from_t(c) - s.from_t(d)) < 1:
            break
        if fc_ <= fd:
            b, d, fd = d, c, fc_
            c = b - GOLDEN * (b - a)
            fc_, xc = g(c)
            if fc_ < best:
                best, x = fc_, xc
        else:
            a, c, fc_ = c, d, fd
            d = a + GOLDEN * (b - a)
            fd, xd = g(d)
            if fd < best:
                best, x = fd, xd
    # one parabolic step through the best point and its two tried neighbours (as Brent's method
    # ends): a narrow valley - a gap that falls steeply towards a lens's k1 - lies between golden
    # points that all miss it, and a coupled parameter whose bracket happened to be wider then wins
    # the Gauss-Southwell order with a worse optimum
    ts = sorted(t for t, v in seen.items() if math.isfinite(v))
    if budget.left and len(ts) >= 3 and not s.integer:
        i = min(range(len(ts)), key=lambda j: seen[ts[j]])
        if 0 < i < len(ts) - 1:
            t0, t1, t2 = ts[i - 1], ts[i], ts[i + 1]
            f0, f1, f2 = seen[t0], seen[t1], seen[t2]
            den = (t1 - t0) * (f1 - f2) - (t1 - t2) * (f1 - f0)
            if den != 0:
                tv = t1 - 0.5 * ((t1 - t0) ** 2 * (f1 - f2) - (t1 - t2) ** 2 * (f1 - f0)) / den
                if t0 < tv < t2 and tv not in seen:
                    fv, xv = g(tv)
                    if fv < best:
                        best, x = fv, xv
    return best, x
