"""What the data constrains in a fit: before the search, the sensitivity screen of every parameter
(:func:`screen_parameters`); after it, the moves the evaluation set does not support put back
(:func:`revert_moves`) and the profile interval of each fitted parameter (model.json's fit record,
the CLI line and the lab report).

The screen: a one-at-a-time sensitivity screen run before the search when the model has more
parameters than the search budget can scan
(:class:`synth.lab.fit.FitConfig` ``screen``; e.g. the 22 of a structured-light physical pipeline,
whose first coarse sweep alone would need 22 x 7 evaluations).

Each parameter is moved alone from the start, to two probe points a fraction ``step`` of its
search range away (one on each side; on the other side twice as far when a bound is in the way:
a term switched off at 0 is probed at two magnitudes), and the gap is scored there. Its
*sensitivity* is the largest change of the gap over those probes, in units of the gap's noise
tau (twice the standard deviation of the start's gap over three simulation seeds, at least 2 %
of it: the level below which two models cannot be told apart by the data, as for the intervals
below). A parameter with sensitivity below 1 is *frozen* at its start:
moving it by a quarter of its range changes nothing the data can see, so fitting it would fit
noise and spend evaluations. The others are fitted in the order of how much a probe lowered the
gap (a decrease within tau counts as none), then of sensitivity: what the data asks to change
most is settled first. A parameter whose two probes both raise the gap by more than tau is
*bracketed*: its optimum lies within a probe step of the start, and the search scans it locally
rather than over its whole range.

Approximation: one parameter at a time from the start - a parameter that only matters once
another has moved (e.g. a speckle filter once the noise is right) can be frozen; the fit report
names every frozen parameter with its sensitivity so a user can fit it alone (``--only``).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np


__all__ = ["profile_intervals", "joint_intervals", "Screen", "screen_parameters", "gap_noise", "revert_moves",
           "seeded_gap_of"]


NOISE_SEEDS = (1009, 2027)
"""Simulation-seed offsets besides the search's own on which the gap's noise (:func:`gap_noise`) and
the revert check (:func:`revert_moves`) score a model again (same frames and pixels)."""


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
    side until the gap exceeds g_best + tau; the end is where a quadratic rise about the best
    through the first step outside reaches tau (kept between the last step inside and that
    step; a linear interpolation underestimated a quadratic bowl's half-width by up to 2x when the
    first step overshot), or is the last step (up to the search bound) when none is outside. Costs about 2 + 2 x steps evaluations per parameter. Approximate: one parameter at
    a time (a coupled pair gets a narrower interval than its joint confidence region)."""
    tau = gap_noise(gap_of, best_x, g_best)
    out = {}
    for sp in specs:
        v0 = float(best_x[sp.key])
        t0 = sp.to_t(v0)
        tlo, thi = sp.t_bounds
        ends = []
        for sign in (-1.0, 1.0):
            step = 1.0 if sp.integer else (thi - tlo) / 32.0
            t_in, end = t0, None
            for _ in range(int(steps)):
                t = min(max(t0 + sign * step, tlo), thi)
                if t == t_in:
                    break                                   # already on the bound
                vals = dict(best_x)
                vals[sp.key] = sp.from_t(t)
                g = float(gap_of(vals))
                if g > g_best + tau:
                    if sp.integer:
                        end = sp.from_t(t_in)
                    else:   # the gap's rise taken as quadratic about the best: (e - t0)^2 / (t - t0)^2 = tau / rise
                        reach = abs(t - t0) * np.sqrt(tau / max(g - g_best, 1e-12))
                        end = sp.from_t(t0 + sign * min(max(reach, abs(t_in - t0)), abs(t - t0)))
                    break
                t_in = t
                step *= 2.0
            ends.append(end if end is not None else sp.from_t(t_in))
        lo, hi = sorted((float(ends[0]), float(ends[1])))
        out[sp.key] = (min(lo, v0), max(hi, v0))
    return out, tau


def joint_intervals(gap_of, specs, best_x: dict, g_best: float, tau: float, profile: dict,
                    ) -> tuple[dict, dict, dict]:
    """Intervals that let the other parameters move too (a coupled pair: sigma0 vs sigma2 over a
    narrow depth range, k1 vs a disparity offset), from a local quadratic model of the gap.

    In each parameter's search coordinate t (scaled by h_i, the half-width of its profile
    interval, at least 1/32 of its range) the gap is evaluated at +-h_i on every axis and at
    (+-h_i, +-h_j) for every pair (the sign of the pair drawn from a fixed seed, the second
    point with j flipped), for the continuous parameters at least h/2 inside their bounds (an
    integer, or a value on a bound - an effect switched off, range_limits' "0 = the device's
    value" - keeps its profile interval, uncoupled: the gap is not quadratic there). A full quadratic
    g = c + b.u + u'Au/2 is fitted to these n(n+1) points and the best by least squares, A's
    curvatures and couplings less than 2 standard errors (of that least-squares fit) from 0 are
    set to 0, and a parameter without a significant positive curvature (or a rise over +-h below
    tau / 4: it changes almost nothing) is left uncoupled (real gaps are rugged); then A's
    eigenvalues are floored at 1e-3 of the largest (a flat direction counts as nearly unconstrained). The inflation factor of parameter i is
    ``sqrt(A_ii (A^-1)_ii)`` (= 1 / sqrt(1 - R_i^2): how much the others can compensate; 1
    for a parameter that trades off with nothing): the joint interval is the profile interval
    widened by it about the fitted value on each side and clipped to the bounds. It is an
    approximation (quadratic gap, curvature structure measured at one scale) of the profile
    with the other parameters re-optimised, which would cost a full search per point.
    Returns (intervals {key: (low, high)}, inflation {key: factor}, correlations
    {"a|b": r} of the pairs with |r| >= 0.3, r = C_ij / sqrt(C_ii C_jj) with C = A^-1: negative
    for a trade-off, one up and the other down leaving the gap alike).
    Costs n(n+1) evaluations for the n coupled parameters; with fewer than two it returns the
    profile intervals unchanged."""
    out = {sp.key: tuple(profile.get(sp.key, (best_x[sp.key], best_x[sp.key]))) for sp in specs}
    factors = {sp.key: 1.0 for sp in specs}
    # the quadratic model holds for continuous parameters inside their bounds; integers (a window
    # radius), values on a bound (an effect switched off, "0 = the device's value") keep their
    # profile interval and are left uncoupled
    coupled = []                                     # (spec, h: twice the profile half-width)
    for sp in specs:
        t0_, (a_, b_) = sp.to_t(float(best_x[sp.key])), sp.t_bounds
        lo, hi = out[sp.key]
        h_ = max(sp.to_t(hi) - sp.to_t(lo), (b_ - a_) / 32.0)
        if not sp.integer and min(t0_ - a_, b_ - t0_) >= 0.5 * h_:
            coupled.append((sp, h_))
    if len(coupled) < 2:
        return out, factors, {}
    specs = [sp for sp, _ in coupled]
    n = len(specs)
    keys = [sp.key for sp in specs]
    t0 = np.array([sp.to_t(float(best_x[sp.key])) for sp in specs])
    tb = np.array([sp.t_bounds for sp in specs])
    h = np.array([h_ for _, h_ in coupled])

    def clip(t):
        return np.minimum(np.maximum(t, tb[:, 0]), tb[:, 1])

    pts = []
    for i in range(n):
        for o in (-h[i], h[i]):
            t = t0.copy()
            t[i] += o
            pts.append(clip(t))
    rng = np.random.default_rng(12345)
    for i in range(n):
        for j in range(i + 1, n):
            si, sj = rng.choice((-1.0, 1.0), size=2)
            for flip in (1.0, -1.0):
                t = t0.copy()
                t[i] += si * h[i]
                t[j] += flip * sj * h[j]
                pts.append(clip(t))
    U = [np.zeros(n)]
    G = [float(g_best)]
    for t in pts:
        vals = dict(best_x)
        for k, sp in enumerate(specs):
            vals[sp.key] = sp.from_t(float(t[k]))
        U.append((np.array([sp.to_t(vals[sp.key]) for sp in specs]) - t0) / h)   # after rounding/clipping
        G.append(float(gap_of(vals)))
    U, G = np.array(U), np.array(G)
    iu = np.triu_indices(n)
    quad = np.stack([U[:, a] * U[:, b] * (0.5 if a == b else 1.0) for a, b in zip(*iu)], axis=1)
    X = np.hstack([np.ones((len(U), 1)), U, quad])
    coef, *_ = np.linalg.lstsq(X, G, rcond=None)
    # keep only what the points show: a coupling (or curvature) whose least-squares estimate is
    # not 2 standard errors from 0 is noise (real data: a rugged gap) and is set to 0
    dof = len(G) - X.shape[1]
    if dof > 0:
        s2 = float(np.sum((X @ coef - G) ** 2)) / dof
        se = np.sqrt(np.maximum(np.diag(np.linalg.pinv(X.T @ X)) * s2, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            tstat = np.where(se > 1e-12 * max(float(np.abs(G).max()), 1e-12), np.abs(coef) / se, np.inf)
    else:
        tstat = np.full(len(coef), np.inf)
    A = np.zeros((n, n))
    A[iu] = np.where(tstat[1 + n:] >= 2.0, coef[1 + n:], 0.0)
    A = A + np.triu(A, 1).T
    # no significant curvature, or one too small to matter (a rise over +-h of less than tau / 4
    # where the profile predicts ~4 tau; e.g. a parameter that changes nothing): uncoupled
    flat = ~(np.diag(A) > 0.5 * float(tau))
    A[flat, :] = 0.0
    A[:, flat] = 0.0
    A[flat, flat] = 1.0
    w, V = np.linalg.eigh(A)
    top = max(float(w.max()), 1e-12)
    w = np.maximum(w, 1e-3 * top)
    A = (V * w) @ V.T
    C = np.linalg.inv(A)
    infl = np.sqrt(np.clip(np.diag(A) * np.diag(C), 1.0, None))
    corr = {}
    for i, sp in enumerate(specs):
        v0 = float(best_x[sp.key])
        lo, hi = out[sp.key]
        a = t0[i] - infl[i] * (t0[i] - sp.to_t(lo))
        b = t0[i] + infl[i] * (sp.to_t(hi) - t0[i])
        out[sp.key] = (min(sp.from_t(max(a, tb[i, 0])), v0), max(sp.from_t(min(b, tb[i, 1])), v0))
        factors[sp.key] = float(infl[i])
        for j in range(i + 1, n):
            r = C[i, j] / np.sqrt(C[i, i] * C[j, j])
            if abs(r) >= 0.3:
                corr[f"{keys[i]}|{keys[j]}"] = round(float(r), 3)
    return out, factors, corr


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
    bracketed: list[str] = field(default_factory=list)
    """Fitted parameters whose every probe raised the gap by more than tau: the start lies within a
    probe step of their optimum, so the search scans them locally (one grid spacing around the
    start) instead of over their whole range."""
    evaluations: int = 0
    """Gap evaluations the screen made."""


def gap_noise(gap_of: Callable, x: dict, g: float) -> float:
    """tau: twice the std of the gap of ``x`` over the search seed and :data:`NOISE_SEEDS` (``gap_of(values,
    seed_offset)``), at least 2 % of the gap (also the noise of :func:`profile_intervals`)."""
    gaps = [float(g)] + [float(gap_of(x, extra)) for extra in NOISE_SEEDS]
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
        else:   # a gain within the noise is no evidence: those are ordered by sensitivity alone
            scored.append((-(gain / res.tau if gain > res.tau else 0.0), -sens, sp.key))
            if len(changes) == 2 and min(changes) > res.tau:
                res.bracketed.append(sp.key)
    res.order = [k for *_, k in sorted(scored)]
    res.evaluations = n0
    return res


def revert_moves(ev, start_cfg, specs: Sequence, best_x: dict, margin: float = 0.0,
                 gap_of: Callable | None = None) -> tuple[dict, list[str], dict]:
    """``FitConfig.revert_check`` of :func:`synth.lab.fit.fit_model`: (values, keys put back, gains) -
    every moved parameter, the largest move (in search units) first, put back at its start value
    unless the move earns its place on the evaluation set ``ev``.

    ``margin`` 0: put back while the gap does not rise at all (each revert against the gap after the
    previous one; ``gains`` empty). ``margin`` > 0: a paired test over simulation seeds. The model with
    this parameter (and those already put back) at the start is scored on the evaluation seed and on
    :data:`NOISE_SEEDS` (``gap_of(values, seed_offset)``: the same frames and pixels; 2 evaluations
    more per moved parameter, 2 for the fitted model), and the rise over the fitted model's gap on
    the same seed is d_i. The move stays when mean(d) > ``margin`` x 2 std(d): the fitted model
    is better on every noise draw by more than the draws' scatter. A gain within that scatter (e.g.
    the noise curve's ``z_offset_m`` lowering the near noise on the search's few pixels, +0.0001 on
    one seed and -0.0006 on the next) is no evidence against the closed-form start, and the start is
    kept; a small gain that holds on every draw (a noise term correcting a start 12 % low: +0.0018,
    +0.0035, +0.0030) is kept. The same-seed differences cancel the simulation noise both models
    share, so this test is sharper than the gap's own noise (:func:`gap_noise`). ``gains``: {key:
    (mean d, 2 std d)} of every moved parameter tested."""
    from synth.lab.params import set_params
    start = {s.key: s.from_t(s.to_t(s.value)) for s in specs}
    moved = [s for s in specs if abs(s.to_t(best_x[s.key]) - s.to_t(start[s.key])) > 1e-12]
    if not moved:
        return best_x, [], {}
    moved.sort(key=lambda s: -abs(s.to_t(best_x[s.key]) - s.to_t(start[s.key])))
    g_fit = g_cur = ev(set_params(start_cfg, best_x))
    if margin > 0:
        if gap_of is None:
            gap_of = seeded_gap_of(ev, start_cfg)
        fit_other = [float(gap_of(best_x, k)) for k in NOISE_SEEDS]
    out, back, gains = dict(best_x), [], {}
    for s in moved:
        trial = dict(out)
        trial[s.key] = start[s.key]
        g = ev(set_params(start_cfg, trial))
        if margin > 0:
            d = np.array([g - g_fit] + [float(gap_of(trial, k)) - f for k, f in zip(NOISE_SEEDS, fit_other)])
            gains[s.key] = (float(d.mean()), float(2.0 * d.std()))
            put_back = d.mean() <= margin * 2.0 * d.std()
        else:
            put_back = g <= g_cur
        if put_back:
            out, g_cur = trial, g
            back.append(s.key)
    return out, back, gains


def seeded_gap_of(obj, base_cfg) -> Callable:
    """The ``gap_of(values, seed_offset=0)`` of the screen and the intervals: ``obj`` (a
    :class:`synth.lab.objective.Objective`) scoring ``base_cfg`` with ``values`` set; with a
    ``seed_offset``, an objective of the same frames, pixels and noise-curve weight whose
    simulation seeds are shifted by it (counted in ``obj.evaluations``)."""
    from synth.lab.params import set_params

    def gap_of(vals, seed_offset: int = 0) -> float:
        if not seed_offset:
            return obj(set_params(base_cfg, vals))
        obj.evaluations += 1
        other = type(obj)(obj.measured, obj.frames, obj.compare_config, obj.seed + seed_offset, obj.noise_weight)
        return other(set_params(base_cfg, vals))
    return gap_of
