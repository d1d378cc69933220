"""The sensor lab: compare measured depth with simulated depth, see where the model fails, fit it.

Plain-array inputs (:class:`FrameObservation`), so the comparison does not depend on the
simulator or the renderer::

    from synth.lab import FrameObservation, compare, write_report, append_history
    result = compare(frames)                       # CompareResult: gap + breakdowns
    append_history(out, ["noise", "shadow"], result.gap)
    write_report(result, frames[:3], out)          # out/report.html, metrics.json

Measured sequences, fitting and diagnosis::

    from synth.lab import MeasuredSequence, fit_model, diagnose
    ms = MeasuredSequence.load("SEQ", max_frames=24)
    fit = fit_model(ms, ms.default_config(["axial_noise", "range_limits"]))
    diag = diagnose(ms, fit.config)                # which effect is missing?

Modules: :mod:`~synth.lab.features` (per-pixel features, registry), :mod:`~synth.lab.compare`
(the gap; its configuration in :mod:`~synth.lab.compare_config`, statistics in
:mod:`~synth.lab.gap_stats`), :mod:`~synth.lab.regions` (error maps, worst regions),
:mod:`~synth.lab.report` (report.html + PNGs), :mod:`~synth.lab.signatures` (diagnosis.html: effect
signature figures), :mod:`~synth.lab.history` (gap per step), :mod:`~synth.lab.measured` (measured sequence + cached
ideal renders), :mod:`~synth.lab.model` (model JSON), :mod:`~synth.lab.fit` (parameter fit; its objective in
:mod:`~synth.lab.objective`, its search in :mod:`~synth.lab.descent`),
:mod:`~synth.lab.diagnose` (rank missing effects), :mod:`~synth.lab.evidence` (the context
effects write their evidence sentences with), :mod:`~synth.lab.runs` (the simulate / compare /
diagnose / fit runs of the ``realgap sensor`` commands). What the lab knows about each effect
(signature, evidence, fittable parameters, starting values, sensor types) is declared in the
effect's own file (:mod:`synth.sensor.registry`).
Fits and diagnoses are deterministic (evaluation-count budgets): the same data, model, settings
and seed give the same result on any machine.
"""
from synth.lab.compare import (PRESETS, CompareCache, CompareConfig, CompareResult, compare, compare_preset,
                               load_result)
from synth.lab.diagnose import Candidate, DiagnoseConfig, Diagnosis, diagnose
from synth.lab.features import (FEATURES, Feature, FeatureConfig, FrameObservation,
                                material_table_from_scene, register_feature)
from synth.lab.fit import FitConfig, FitResult, fit_model
from synth.lab.history import append_history, load_history
from synth.lab.measured import MeasuredSequence
from synth.lab.model import load_model, save_model
from synth.lab.regions import Region, error_map, validity_map, worst_bins, worst_blocks, worst_regions
from synth.lab.report import run_lab, write_report

__all__ = ["FrameObservation", "CompareConfig", "CompareResult", "CompareCache", "Region", "PRESETS",
           "compare", "compare_preset", "error_map", "validity_map", "worst_bins", "worst_blocks",
           "worst_regions", "load_result", "FEATURES", "Feature", "FeatureConfig",
           "register_feature", "material_table_from_scene", "append_history", "load_history",
           "write_report", "run_lab", "MeasuredSequence", "load_model", "save_model", "FitConfig",
           "FitResult", "fit_model", "Candidate", "Diagnosis", "DiagnoseConfig", "diagnose"]
