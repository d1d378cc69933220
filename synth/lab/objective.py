"""The objective of the lab's fits: gap(config) on fixed frames, seeds and compare pixels.

The documented gap of :mod:`synth.lab.compare` between the measured frames and the model's
simulation of the same frames, with three savings that keep it cheap and smooth:

* the ideal geometry is ray-cast once per frame (:class:`~synth.lab.measured.MeasuredSequence`
  caches the renders; effects that re-cast rays themselves, e.g. rolling shutter, still do);
* the search uses a subset of ``FitConfig.max_frames`` frames (evenly spread) and
  ``max_pixels_per_frame`` compare samples per frame (the same seeded pixels every time);
* **common random numbers**: every evaluation simulates frame k with the same seed
  (``seed + frame index``); effects draw their random fields independently of their
  parameters, so two parameter values are compared on the same noise/dropout draws and the
  objective changes smoothly (piecewise constant on a fine scale) instead of jumping by the
  sampling noise of a fresh draw.

Cost: one evaluation = simulate the search frames + :func:`compare`. The comparison reuses the
measured sequence's :class:`~synth.lab.compare.CompareCache` (sampled pixels, the 4 edge distance
transforms and the other feature values, measured errors: computed once per frame), so it pays
only for the simulated side: 4 VGA frames with ``axial_noise, range_limits`` and the defaults
take ~80 ms (~150-190 ms without the cache; measured by ``benchmarks/bench_lab.py
--diagnose``), the preset's direct model ~0.28 s (its simulation dominates); effects that
ray-cast again, rolling shutter and motion blur, cost ~0.1 s per frame more.

"""
from __future__ import annotations

import json
import math
from collections.abc import Sequence

from synth.lab.compare import CompareConfig, compare

__all__ = ["Objective"]


class Objective:
    """gap(config) on fixed frames, seeds and compare pixels (cached by parameter values).

    ``noise_weight`` > 0 on a sequence with a planar reference (``MeasuredSequence.has_plane_reference``)
    adds ``noise_weight`` x the noise-vs-distance term of :mod:`synth.lab.calibration` to the gap:
    the mean |ln(simulated / measured std)| over the distance bins plus the same over the grazing
    (distance bin, incidence class) cells (``GRAZING_EDGES_DEG``: 0 where no cell has enough
    pixels); elsewhere it is ignored."""

    def __init__(self, measured, frames: Sequence[int], compare_config: CompareConfig, seed: int = 0,
                 noise_weight: float = 0.0):
        self.measured = measured
        self.frames = list(frames)
        self.compare_config = compare_config
        self.seed = int(seed)
        self.evaluations = 0
        self.last_result = None
        self.noise_weight = float(noise_weight) if getattr(measured, "has_plane_reference", False) else 0.0
        """Weight of the noise-curve term (0: off, also on sequences without a planar reference)."""
        self.last_curve = None
        """(term, observations, config) of the last evaluation simulated when the noise-curve term is on."""
        self._curve_measured = None
        self.memo: dict | None = None
        """{config key: gap} when a dict: a config scored again is not simulated again (the
        evaluation set of ``fit_model``)."""
        self.cache = getattr(measured, "compare_cache", None)
        """The measured sequence's :class:`~synth.lab.compare.CompareCache` (None: no caching)."""
        self.journal = getattr(measured, "eval_journal", None)
        """An :class:`~synth.lab.journal.EvalJournal` set on the measured sequence by a resumable
        command (None: no journal). Replayed evaluations leave ``last_result`` unchanged."""

    def __call__(self, config) -> float:
        mk = _config_key(config) if self.memo is not None else None
        if mk in (self.memo or {}):
            return self.memo[mk]
        self.evaluations += 1
        key = None
        if self.journal is not None:
            key = self.journal.key(config, [self.measured.frame_indices[k] for k in self.frames],
                                   self.compare_config, self.seed, self.measured.seq_dir,
                                   {"noise_weight": self.noise_weight} if self.noise_weight > 0 else None)
            g = self.journal.get(key)
            if g is not None:
                return g
        g = self._gap(config)
        if key is not None:
            self.journal.put(key, g)
        if mk is not None:
            self.memo[mk] = g
        return g

    def _gap(self, config) -> float:
        sims = self.measured.simulate(config, self.seed, self.frames)
        obs = self.measured.observations(sims, self.frames)
        self.last_result = compare(obs, self.compare_config, cache=self.cache)
        g = float(self.last_result.gap)
        if self.noise_weight > 0:
            from synth.lab.calibration import GRAZING_EDGES_DEG as ge
            from synth.lab.calibration import curve_term, noise_curve
            px = self.compare_config.max_pixels_per_frame
            if self._curve_measured is None:
                self._curve_measured = (noise_curve(obs, "measured", px, self.seed)[0],
                                        noise_curve(obs, "measured", px, self.seed, incidence_edges=ge)[0])
            # the distance curve (what a calibration reports) plus its grazing cells (what separates an
            # incidence term from the distance terms; 0 on a capture without grazing views)
            term = (curve_term(self._curve_measured[0], noise_curve(obs, "simulated", px, self.seed)[0])
                    + curve_term(self._curve_measured[1],
                                 noise_curve(obs, "simulated", px, self.seed, incidence_edges=ge)[0]))
            self.last_curve = (term, obs, _config_key(config))
            g += self.noise_weight * term
        return g if math.isfinite(g) else float("inf")

    def curve(self, config) -> tuple[float, list]:
        """(noise-curve term, observations) of ``config`` (simulated again when its last evaluation
        was replayed from a journal or was of another config)."""
        if self.last_curve is None or self.last_curve[2] != _config_key(config):
            self._gap(config)
        return self.last_curve[:2]


def _config_key(config) -> str:
    return json.dumps(config.to_json(), sort_keys=True, default=str)     # a model's identity
