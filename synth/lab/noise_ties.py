"""When the gap's own noise cannot order two models (:func:`synth.lab.diagnose.diagnose`).

The gap is scored on a sample of pixels and one simulation draw, so two models whose gaps differ
by less than its noise tau (:func:`synth.lab.intervals.gap_noise`: twice the std over three
simulation seeds, at least 2 % of the gap) are not told apart by it. Two places used to decide on
such a difference alone: a candidate's data-driven start against its defaults, and the ranking of
candidates by gain (a null depth bias with four numbers fitted to the noise led a projector shadow,
both below the noise; a rolling shutter trailed a depth bias by a fifth of the noise).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

__all__ = ["measure_noise", "EvaluationObjective", "start_beats_defaults", "within_noise", "noise_tie"]


def measure_noise(obj, config, gap: float) -> float:
    """tau of ``config`` (gap ``gap`` on the objective ``obj``, a :class:`synth.lab.objective.Objective`):
    :func:`synth.lab.intervals.gap_noise` over the search seed and two others (2 evaluations)."""
    from synth.lab.intervals import gap_noise, seeded_gap_of
    return gap_noise(seeded_gap_of(obj, config), {}, gap)


class EvaluationObjective:
    """``get()`` -> the evaluation set's objective (``fc.eval_frames`` x ``fc.eval_pixels_per_frame``
    of ``measured``), built on the first call: most diagnoses never need it."""

    def __init__(self, measured, fc):
        self.measured, self.fc, self.objective = measured, fc, None

    def __call__(self):
        if self.objective is None:
            from synth.lab.fit import Objective, spread
            fc = self.fc
            self.objective = Objective(self.measured, spread(len(self.measured), fc.eval_frames),
                                       fc.compare_config(fc.eval_pixels_per_frame), fc.seed)
        return self.objective

    @property
    def evaluations(self) -> int:
        """Evaluations of the evaluation set so far (0 when it was never built)."""
        return 0 if self.objective is None else int(self.objective.evaluations)


def start_beats_defaults(noise: float, evaluate: bool, eval_objective: Callable, alt, g_alt: float,
                         default_cfg, g_def: float) -> bool:
    """Does a candidate's data-driven start ``alt`` (search gap ``g_alt``) beat its defaults (``g_def``)?
    On the search gap when the two differ by more than ``noise`` (or the noise is unknown, or
    ``evaluate`` is off); within it the evaluation set (``eval_objective()``: more pixels, less
    sampling noise) decides, and a tie there keeps the start: a closed-form estimate from the data
    is a better guess than the preset's defaults when the gap sees no difference."""
    if not abs(g_alt - g_def) <= noise or not evaluate:
        return g_alt < g_def
    ev = eval_objective()
    return ev(alt) <= ev(default_cfg)


def within_noise(noise: float, g0: float, lead, cands: Sequence) -> list:
    """The candidates (``gap_after``) that lower the base gap ``g0`` and leave a gap within
    ``noise`` of ``lead``'s: the data cannot order them by gain (two gains below the noise, each a fit
    to it; or two real gains the sampled gap cannot tell apart); empty when the noise is unknown."""
    if not noise > 0 or not g0 > 0:
        return []
    return [c for c in cands if c.gap_after < g0 and c.gap_after - lead.gap_after < noise]


def noise_tie(ranking: Sequence, noise: float, g0: float, is_map: Callable) -> list[tuple[str, str, str]]:
    """[(first, rival, sentence)] when the ranking's first candidate leads a rival of larger gain
    (the best parametric one, else the best; ``is_map(c)``: a learned map) only because their gaps
    lie within ``noise`` of each other; else []."""
    if not ranking or not ranking[0].gain > 0:
        return []
    a = ranking[0]
    rivals = sorted((c for c in ranking if c is not a), key=lambda c: (is_map(c), -c.gain))
    if not rivals or not rivals[0].gain > a.gain or not within_noise(noise, g0, a, [rivals[0]]):
        return []
    b = rivals[0]
    return [(a.effect, b.effect, f"their gaps lie within the gap's noise ({noise:.2g}) of each other "
                                 f"({a.gap_after:.4g}, {b.gap_after:.4g}), so the data cannot order them by gain; "
                                 f"the one with fewer free numbers is named first")]
