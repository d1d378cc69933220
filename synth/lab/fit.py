"""Fit the parameters of a sensor model to a measured sequence by minimising the lab's ``gap``.

    ms = MeasuredSequence.load("SEQ", max_frames=24)
    cfg = ms.default_config(["axial_noise", "range_limits", "projector_shadow"])
    res = fit_model(ms, cfg)                       # FitResult
    res.gap_before, res.gap, res.params            # e.g. 0.41 -> 0.12, {"axial_noise.sigma2_per_m": ...}

The objective (:mod:`synth.lab.objective`)
-------------------------------------------
The documented gap of :mod:`synth.lab.compare` between the measured frames and the model's simulation of the
same frames, on fixed frames, seeds and compare pixels (common random numbers), cached by parameter values.

The search (:mod:`synth.lab.descent`)
-------------------------------------
Bounded coordinate descent over the fittable parameters: a coarse grid scan per parameter, golden-section
refinement of the ones that helped, combined in order of their gap, then local sweeps.

Many parameters (``FitConfig.screen``): a sensitivity screen first
(:func:`synth.lab.intervals.screen_parameters`) freezes what the data does not constrain
(``FitResult.frozen`` says which and why) and orders the rest, most useful first. On a planar
target the objective adds the noise-vs-distance term (``FitConfig.noise_curve_weight``).

The budget is a number of evaluations (``max_evaluations``), never a time: the same data, model,
settings and seed give the same fit on any machine under any load. (``max_seconds`` is an
optional safety guard, off by default; a result it cut short says so in ``time_capped``.)
Evaluations are cached by parameter values. Finally the start and the best configuration are both scored on the
evaluation set (``eval_frames`` frames, ``eval_pixels_per_frame`` samples: by default every
loaded frame and the default compare sampling); if the fitted model is not better there (an
over-fit to the search subset), the starting parameters are kept and ``FitResult.kept_start``
says so.

Starting point: the given parameter values, or the data-driven estimates of the effects'
``fit_start`` (e.g. the disparity step from a periodogram of the measured disparities) when
those score better.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

from data_tools.config import config_from_dict, config_to_dict
from data_tools.errors import ConfigError, RealgapError
from data_tools.sequence import spread_indices as spread
from synth.lab.compare import CompareConfig
from synth.lab.descent import search
from synth.lab.objective import Objective
from synth.lab.params import (ParamSpec, _effect, config_parameters, get_params, param_specs, set_params,  # noqa: F401
                              start_values)

__all__ = ["FitConfig", "FitResult", "ParamSpec", "fit_model", "param_specs", "set_params", "get_params",
           "Objective", "search", "config_parameters", "start_values"]

SEARCH_METHODS = ("coordinate", "powell", "differential_evolution")
"""The searches :class:`FitConfig` ``method`` may name."""


# ------------------------------------------------------------------------------------------
# Configuration and result
# ------------------------------------------------------------------------------------------

@dataclass
class FitConfig:
    """How :func:`fit_model` (and :func:`synth.lab.diagnose.diagnose`) search."""

    max_frames: int | None = 4
    """Frames used by the search (evenly spread over the loaded ones); None = all."""
    max_pixels_per_frame: int = 4000
    """Compare samples per frame during the search."""
    eval_frames: int | None = None
    """Frames of the final before/after gaps of :func:`fit_model`; None = all loaded frames."""
    eval_pixels_per_frame: int | None = 20000
    """Compare samples per frame of the final gaps (None = every pixel)."""
    max_evaluations: int = 80
    """Most objective evaluations of the search (deterministic: the same data, model and seed give the
    same result on any machine). A screened search raises it to scan every parameter once (``screen``);
    the start, screen, revert check, intervals and final scores come on top (``FitResult.stages``)."""
    max_seconds: float | None = None
    """Optional wall-clock SAFETY GUARD per search, seconds (checked between evaluations);
    None = off (default). Not a budget: it exists only to bound a pathological run (e.g. an
    effect that ray-casts again on a huge image). When it stops a search the result depends on
    the machine's speed and load, and ``FitResult.time_capped`` / ``Diagnosis.time_capped``
    say so. Set it generously (several times the expected time)."""
    grid_points: int = 7
    """Coarse grid values per parameter in the first sweep."""
    refine_iterations: int = 4
    """Golden-section steps per parameter and sweep."""
    sweeps: int = 2
    """Coordinate sweeps over all parameters."""
    tolerance: float = 0.005
    """A sweep that lowers the gap by less than this fraction ends the search."""
    seed: int = 0
    """Simulation seed (frame k uses seed + its index: common random numbers)."""
    intervals: bool = True
    """Compute an interval per fitted parameter (:func:`synth.lab.intervals.profile_intervals`, then
    :func:`synth.lab.intervals.joint_intervals` when ``joint_intervals``)."""
    interval_steps: int = 4
    """Profile steps outward on each side of each parameter (doubling in size)."""
    joint_intervals: bool = True
    """Widen the profile intervals by how much the other parameters can compensate
    (:func:`synth.lab.intervals.joint_intervals`, n(n+1) more evaluations for n parameters)."""
    revert_check: bool = True
    """After the search, each parameter the search moved away from its start is put back to the start value
    alone and kept there when that does not raise the gap on the evaluation set (``eval_frames`` x
    ``eval_pixels_per_frame``: more frames and pixels than the search sees) by more than the noise of
    that rise (``revert_margin``). A move that only fitted the search sample's noise (e.g. the noise
    curve's offset wandering by 2 cm and lowering the noise 2 %) is undone; one evaluation per moved
    parameter, three with ``revert_margin`` (:func:`synth.lab.intervals.revert_moves`)."""
    revert_margin: float = 1.0
    """How clearly a move must lower the evaluation gap to be kept by the revert check: the rise d_i
    of the gap when the parameter goes back, on the evaluation seed and two other simulation seeds
    (same frames and pixels, paired with the fitted model on each), must have a mean above
    ``revert_margin`` x twice its std - a gain within the noise draws' scatter is no evidence against
    the data-driven start. 0 = put back while the gap on the evaluation seed does not rise at all (no
    extra evaluations)."""
    data_starts: bool = True
    """Try the effects' closed-form ``fit_start`` estimates as the starting point (kept when they
    score better than the given values)."""
    method: str = "coordinate"
    """Search: ``coordinate`` (the bounded coordinate descent of the module docstring), ``powell``
    (``scipy.optimize.minimize(method="Powell")`` with bounds, on the same search coordinates) or
    ``differential_evolution`` (``scipy.optimize.differential_evolution``, seeded, the start in
    its initial population, no polishing). All three share the budget, the cache and the start;
    ``benchmarks/bench_fit_recovery.py --method`` compares them."""
    screen: bool | None = None
    """Screen the parameters first (:func:`synth.lab.intervals.screen_parameters`: each moved alone
    by ``screen_step`` of its range), freeze those whose move the data cannot see (named in
    ``FitResult.frozen``) and search the others, most useful first. None (default) = only when the first sweep's scan of every parameter
    (``grid_points`` each) would not fit in ``max_evaluations`` (e.g. the 22 parameters of a
    structured-light physical pipeline), so a search that could scan them all is unchanged. A
    screened search's budget is raised, when needed, to scan every fitted parameter once
    (``grid_points`` + 1 evaluations each) plus two golden-section refinements."""
    screen_step: float = 0.25
    """Probe distance of the screen, a fraction of each parameter's search range."""
    noise_curve_weight: float = 1.0
    """On a sequence with a planar reference (``data make-reference --plane``): weight of the
    noise-vs-distance term added to the gap (:mod:`synth.lab.calibration`: mean |ln(simulated /
    measured plane-fit std)| over 0.25 m distance bins from 0.5 to 3 m and over those bins split
    into incidence classes), so the fit honours the curve sensor people calibrate first (its
    closed-form start, :func:`synth.lab.calibration.curve_start`, is computed on the evaluation set,
    ``eval_frames``: the search's few frames hold few far or grazing pixels); there the
    effects' ``PLANE_ONLY`` terms (axial noise's incidence term) are fitted too, their search
    budget on top of ``max_evaluations``; 0 = the gap alone. Ignored on other sequences."""
    compare: CompareConfig = field(default_factory=CompareConfig)
    """Comparison settings (its pixel count is replaced by the two counts above)."""

    def validate(self) -> "FitConfig":
        if self.max_frames is not None and int(self.max_frames) < 1:
            raise ConfigError(f"fit: max_frames must be >= 1 or None, got {self.max_frames}")
        if self.eval_frames is not None and int(self.eval_frames) < 1:
            raise ConfigError(f"fit: eval_frames must be >= 1 or None, got {self.eval_frames}")
        if int(self.max_pixels_per_frame) < 100:
            raise ConfigError(f"fit: max_pixels_per_frame must be >= 100, got {self.max_pixels_per_frame}")
        if self.eval_pixels_per_frame is not None and int(self.eval_pixels_per_frame) < 100:
            raise ConfigError(f"fit: eval_pixels_per_frame must be >= 100 or None, got {self.eval_pixels_per_frame}")
        if int(self.max_evaluations) < 1:
            raise ConfigError(f"fit: max_evaluations must be >= 1, got {self.max_evaluations}")
        if self.max_seconds is not None and not float(self.max_seconds) > 0:
            raise ConfigError(f"fit: max_seconds must be > 0 or None (no guard), got {self.max_seconds}")
        if int(self.grid_points) < 2 or int(self.refine_iterations) < 0 or int(self.sweeps) < 1:
            raise ConfigError("fit: need grid_points >= 2, refine_iterations >= 0, sweeps >= 1")
        if not self.tolerance >= 0:
            raise ConfigError(f"fit: tolerance must be >= 0, got {self.tolerance}")
        if not float(self.noise_curve_weight) >= 0:
            raise ConfigError(f"fit: noise_curve_weight must be >= 0, got {self.noise_curve_weight}")
        if not float(self.revert_margin) >= 0:
            raise ConfigError(f"fit: revert_margin must be >= 0, got {self.revert_margin}")
        if not 0 < float(self.screen_step) <= 0.5:
            raise ConfigError(f"fit: screen_step must be in (0, 0.5], got {self.screen_step}")
        if self.method not in SEARCH_METHODS:
            raise ConfigError(f"fit: method must be one of {', '.join(SEARCH_METHODS)}, got {self.method!r}")
        self.compare.validate()
        return self

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "FitConfig":
        return config_from_dict(cls, d, "fit config")

    def compare_config(self, pixels: int | None) -> CompareConfig:
        d = self.compare.to_dict()
        d["max_pixels_per_frame"] = pixels
        return CompareConfig.from_dict(d)


@dataclass
class FitResult:
    """Outcome of :func:`fit_model`."""

    config: object
    """The fitted :class:`~synth.sensor.config.SensorConfig`."""
    gap_before: float
    """Gap of the starting model on the evaluation set (same frames, seeds and pixels as ``gap``)."""
    gap: float
    """Gap of the fitted model on the evaluation set."""
    params: dict[str, float]
    """{"effect.param": value} of the fitted parameters."""
    start_params: dict[str, float] = field(default_factory=dict)
    """Their starting values."""
    evaluations: int = 0
    """Objective evaluations used by every stage (``stages``: start, screen, search, revert, intervals, final)."""
    seconds: float = 0.0
    """Wall-clock time of the fit."""
    search_gap_before: float = float("nan")
    """Gap of the start on the search subset."""
    search_gap: float = float("nan")
    """Gap of the best parameters on the search subset."""
    kept_start: bool = False
    """True when the search's best was not better on the evaluation set (start kept)."""
    frames: list[int] = field(default_factory=list)
    """Sequence indices of the search frames."""
    eval_frames: list[int] = field(default_factory=list)
    """Sequence indices of the evaluation frames."""
    time_capped: bool = False
    """True when the wall-clock guard ``FitConfig.max_seconds`` stopped the search (the result
    then depends on the machine's speed)."""
    bounds: dict = field(default_factory=dict)
    """{"effect.param": (low, high)} search bounds of the fitted parameters."""
    intervals: dict = field(default_factory=dict)
    """{"effect.param": (low, high)}: the interval of each fitted parameter - with
    ``FitConfig.joint_intervals`` (default) the joint one (:func:`synth.lab.intervals.joint_intervals`:
    the profile interval widened by how far the other parameters can compensate), else the profile
    interval (``intervals_one_at_a_time``); an end equal to the search bound means the data does not
    bound the parameter on that side."""
    gap_noise: float = float("nan")
    """The gap's noise level used for the intervals (twice the std of the best model's gap over
    three simulation seeds, at least 2 % of it)."""
    intervals_one_at_a_time: dict = field(default_factory=dict)
    """{"effect.param": (low, high)}: the profile intervals with the other parameters held at the
    fit (``intervals`` are these widened by ``inflation`` when joint intervals are on)."""
    inflation: dict = field(default_factory=dict)
    """{"effect.param": factor >= 1}: how much the joint interval is wider than the one-at-a-time
    one (1 / sqrt(1 - R^2) of the local quadratic gap model)."""
    correlations: dict = field(default_factory=dict)
    """{"a|b": r}: parameter pairs whose estimates are correlated (|r| >= 0.3) in the local
    quadratic gap model; r < 0 = a trade-off (one up, the other down explains the data alike)."""
    reverted: list = field(default_factory=list)
    """Parameters the search moved but :attr:`FitConfig.revert_check` put back at their start value (the
    move did not lower the evaluation set's gap clearly, ``FitConfig.revert_margin``)."""
    frozen: dict = field(default_factory=dict)
    """{"effect.param": reason}: parameters the screen (:attr:`FitConfig.screen`) left at their start
    because the data does not constrain them (their interval is their search bounds)."""
    sensitivity: dict = field(default_factory=dict)
    """{"effect.param": gap change / gap noise} of the screen, every parameter (empty without screen)."""
    noise_curve: dict = field(default_factory=dict)
    """On a sequence with a planar reference: {"weight", "term_before", "term", "bins": [{"bin_m",
    "measured_mm", "simulated_mm", "simulated_mm_before", "ratio", "pixels"}]}: the noise-vs-distance
    curve of the evaluation set (:mod:`synth.lab.calibration`); ``gap_before`` / ``gap`` include
    weight x term. Empty elsewhere."""
    stages: dict = field(default_factory=dict)
    """{stage: {"seconds": s, "evaluations": n}} of the fit's stages (start, screen, search, revert,
    intervals, evaluation): where the time went."""

    @property
    def at_bound(self) -> dict[str, str]:
        """Fitted parameters that ended on a search bound other than 0 (0 switches a term off,
        a normal outcome), with a note: ``{"effect.param": "at upper bound 2.0: the effect may be
        the wrong one"}``. A parameter pinned to its bound explains more than the effect can: a
        user should not read it as a fact about the sensor."""
        out = {}
        for k, v in self.params.items():
            b = self.bounds.get(k)
            if b is None:
                continue
            for side, x in (("lower", b[0]), ("upper", b[1])):
                if x != 0 and math.isclose(float(v), float(x), rel_tol=1e-9, abs_tol=1e-12):
                    out[k] = f"at {side} bound {x:g}: the effect may be the wrong one"
        return out

    @property
    def gain(self) -> float:
        """(gap_before - gap) / gap_before (0 when gap_before is 0)."""
        return (self.gap_before - self.gap) / self.gap_before if self.gap_before > 0 else 0.0

    def to_json(self) -> dict:
        return {"gap_before": self.gap_before, "gap": self.gap, "gain": self.gain, "params": dict(self.params),
                "start_params": dict(self.start_params), "evaluations": self.evaluations,
                "seconds": self.seconds, "search_gap_before": self.search_gap_before,
                "search_gap": self.search_gap, "kept_start": self.kept_start,
                "search_frames": list(self.frames), "eval_frames": list(self.eval_frames),
                "time_capped": self.time_capped, "effects": self.config.names(enabled_only=True),
                "bounds": {k: list(v) for k, v in self.bounds.items()}, "at_bound": self.at_bound,
                "intervals": {k: list(v) for k, v in self.intervals.items()}, "gap_noise": self.gap_noise,
                "intervals_one_at_a_time": {k: list(v) for k, v in self.intervals_one_at_a_time.items()},
                "inflation": dict(self.inflation), "correlations": dict(self.correlations),
                "reverted": list(self.reverted), "frozen": dict(self.frozen),
                "sensitivity": dict(self.sensitivity), "stages": dict(self.stages),
                "noise_curve": dict(self.noise_curve)}


# ------------------------------------------------------------------------------------------
# Objective and search
# ------------------------------------------------------------------------------------------

# ------------------------------------------------------------------------------------------
# The fit
# ------------------------------------------------------------------------------------------

def fit_model(measured, config, *, names: Sequence[str] | None = None, fit_config: FitConfig | None = None,
              progress: bool = False) -> FitResult:
    """Fit the FITTABLE (and config) parameters of the effects ``names`` (default: every enabled
    effect of ``config``) to ``measured`` (a :class:`~synth.lab.measured.MeasuredSequence`).

    Returns a :class:`FitResult` whose ``gap_before``/``gap`` are scored on the evaluation set
    with the same seeds and pixels. ``progress`` shows the evaluations on stderr (:mod:`data_tools.progress`).
    """
    fc = (fit_config or FitConfig()).validate()
    t0 = time.perf_counter()
    stages, mark, ev, calibrated = {}, [t0, 0], None, None

    def stage(name: str) -> None:        # close the stage that ran since the last mark
        n, now = obj.evaluations + (ev.evaluations if ev is not None else 0), time.perf_counter()
        stages[name] = {"seconds": round(now - mark[0], 3), "evaluations": n - mark[1]}
        mark[:] = [now, n]
    plane = bool(fc.noise_curve_weight > 0 and getattr(measured, "has_plane_reference", False))
    specs = param_specs(config, names, plane)      # a planar reference also fits the PLANE_ONLY terms
    extra = len(specs) - len(param_specs(config, names)) if plane else 0
    if extra:       # on top of the budget: a plane-only term does not cut the search of the others
        fc = dataclasses.replace(fc, max_evaluations=int(fc.max_evaluations)
                                 + extra * (int(fc.grid_points) + int(fc.refine_iterations)) * int(fc.sweeps))
    n = len(measured)
    if n == 0:
        raise RealgapError(f"{measured.seq_dir}: no frames to fit")
    frames = spread(n, fc.max_frames)
    eval_frames = spread(n, fc.eval_frames)
    obj = Objective(measured, frames, fc.compare_config(int(fc.max_pixels_per_frame)), fc.seed,
                    fc.noise_curve_weight)
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=fc.max_evaluations, desc="fitting", unit="eval")
    try:
        start_cfg = config
        g_start = obj(config)
        data_start = start_values(measured, config, list(dict.fromkeys(s.key.split(".", 1)[0] for s in specs)),
                                  frames) if fc.data_starts else {}
        if data_start:
            cand = set_params(config, data_start)
            g = obj(cand)
            if g < g_start:
                start_cfg, g_start = cand, g
                specs = param_specs(start_cfg, names, plane)
        if (fc.data_starts and obj.noise_weight > 0        # planar target: the noise curve calibrated first,
                and any(sp.key == "axial_noise.sigma2_per_m" for sp in specs)):
            # on the evaluation set: the few search frames hold few far and grazing pixels (7-Scenes chess)
            from synth.lab.calibration import curve_start
            ev = Objective(measured, eval_frames, fc.compare_config(fc.eval_pixels_per_frame), fc.seed,
                           fc.noise_curve_weight)
            ev.memo = {}
            base_cfg, g_cal = start_cfg, ev(start_cfg)
            for cells in (True, False):     # per incidence cell, and per distance bin alone: the better
                cs = curve_start(base_cfg, ev, specs, cells)
                if cs and (g := ev(cand := set_params(base_cfg, cs))) < g_cal:
                    calibrated, g_cal = cand, g
            if calibrated is not None:
                start_cfg, g_start = calibrated, obj(calibrated)
            specs = param_specs(start_cfg, names, plane)
        stats: dict = {}
        stage("start")
        all_specs, scr = specs, None
        if specs and (fc.screen if fc.screen is not None
                      else len(specs) * int(fc.grid_points) > int(fc.max_evaluations)):
            from synth.lab.intervals import screen_parameters, seeded_gap_of
            scr = screen_parameters(seeded_gap_of(obj, start_cfg), specs, get_params(start_cfg, specs),
                                    g_start, float(fc.screen_step))
            specs = [s for k in scr.order for s in all_specs if s.key == k]
            if bar is not None:
                bar.update(scr.evaluations)
            stage("screen")
        sfc = fc
        if scr is not None:     # enough to scan every fitted parameter once, plus two refinements
            need = len(specs) * (int(fc.grid_points) + 1) + 2 * int(fc.refine_iterations)
            sfc = dataclasses.replace(fc, max_evaluations=max(int(fc.max_evaluations), need))
        if specs:
            best_x, g_best, _ = search(obj, start_cfg, specs, sfc, bar.update if bar else None, start_gap=g_start,
                                       stats=stats, local=frozenset(scr.bracketed) if scr is not None else False)
        else:
            best_x, g_best = {}, g_start
    finally:
        if bar is not None:
            bar.close()
    stage("search")
    stages["search"]["budget"] = int(sfc.max_evaluations) if specs else 0
    if ev is None:
        ev = Objective(measured, eval_frames, fc.compare_config(fc.eval_pixels_per_frame), fc.seed,
                       fc.noise_curve_weight)
        ev.memo = {}
    reverted: list[str] = []
    if fc.revert_check and specs and best_x:
        from synth.lab.intervals import revert_moves
        best_x, reverted, gains = revert_moves(ev, start_cfg, specs, best_x, float(fc.revert_margin))
        if reverted:
            g_best = obj(set_params(start_cfg, best_x))
        stage("revert")
        if gains:
            stages["revert"]["gains"] = {k: [round(m, 6), round(t, 6)] for k, (m, t) in gains.items()}
    best_cfg = set_params(start_cfg, best_x) if specs else start_cfg
    intervals, noise, single, inflation, correlations = {}, float("nan"), {}, {}, {}
    if fc.intervals and specs and best_x:
        from synth.lab.intervals import profile_intervals, seeded_gap_of
        gap_of = seeded_gap_of(obj, start_cfg)
        intervals, noise = profile_intervals(gap_of, specs, best_x, g_best, fc.interval_steps)
        single = dict(intervals)
        if fc.joint_intervals:
            from synth.lab.intervals import joint_intervals
            intervals, inflation, correlations = joint_intervals(gap_of, specs, best_x, g_best, noise, single)
        stage("intervals")
    before = ev(config)
    curve_before = ev.curve(config) if ev.noise_weight > 0 else None
    after = ev(best_cfg) if best_cfg is not config else before
    curve_after = ev.curve(best_cfg) if ev.noise_weight > 0 else None
    if calibrated is not None and best_cfg is not calibrated and (g := ev(calibrated)) < after:
        # the search on its few frames moved away from the noise curve calibrated on all of them
        best_cfg, best_x, after, curve_after = calibrated, get_params(calibrated, specs), g, ev.curve(calibrated)
        stages["start"]["calibration_kept"] = True
    kept = False
    if after > before:
        best_cfg, best_x, after, kept = config, get_params(config, specs), before, True
        curve_after = curve_before
    noise_curve = {}
    if ev.noise_weight > 0 and curve_before is not None and curve_after is not None:
        from synth.lab.calibration import noise_curve_report
        noise_curve = noise_curve_report(ev.noise_weight, curve_before, curve_after,
                                         ev.compare_config.max_pixels_per_frame, ev.seed)
    stage("evaluation")
    frozen = dict(scr.frozen) if scr is not None else {}
    if scr is not None:        # the frozen parameters: reported at their start, interval = their bounds
        for sp in all_specs:
            if sp.key in frozen:
                best_x[sp.key] = get_params(best_cfg, [sp])[sp.key]
                if intervals and not kept:
                    intervals[sp.key] = single[sp.key] = (sp.low, sp.high)
        specs = all_specs
    return FitResult(best_cfg, float(before), float(after), {k: float(v) for k, v in best_x.items()},
                     {s.key: s.value for s in specs}, obj.evaluations + ev.evaluations,
                     time.perf_counter() - t0, float(g_start), float(g_best), kept,
                     [measured.frame_indices[k] for k in frames],
                     [measured.frame_indices[k] for k in eval_frames], bool(stats.get("time_capped", False)),
                     {sp.key: (sp.low, sp.high) for sp in specs}, intervals if not kept else {}, noise,
                     single if not kept else {}, inflation if not kept else {}, correlations if not kept else {},
                     reverted, frozen, dict(scr.sensitivity) if scr is not None else {}, noise_curve, stages)
