"""The sensor lab: compare measured depth with simulated depth, see where the model fails.

Plain-array inputs (:class:`FrameObservation`), so nothing here depends on the simulator or
the renderer::

    from synth.lab import FrameObservation, compare, write_report, append_history
    result = compare(frames)                       # CompareResult: gap + breakdowns
    append_history(out, ["noise", "shadow"], result.gap)
    write_report(result, frames[:3], out)          # out/report.html, metrics.json

Modules: :mod:`~synth.lab.features` (per-pixel features, registry), :mod:`~synth.lab.compare`
(the gap, error maps, worst regions), :mod:`~synth.lab.report` (HTML + PNG),
:mod:`~synth.lab.history` (gap per step).
"""
from synth.lab.compare import (PRESETS, CompareConfig, CompareResult, Region, compare,
                               compare_preset, error_map, load_result, validity_map, worst_bins,
                               worst_blocks, worst_regions)
from synth.lab.features import (FEATURES, Feature, FeatureConfig, FrameObservation,
                                material_table_from_scene, register_feature)
from synth.lab.history import append_history, load_history
from synth.lab.report import run_lab, write_report

__all__ = ["FrameObservation", "CompareConfig", "CompareResult", "Region", "PRESETS",
           "compare", "compare_preset", "error_map", "validity_map", "worst_bins", "worst_blocks",
           "worst_regions", "load_result", "FEATURES", "Feature", "FeatureConfig",
           "register_feature", "material_table_from_scene", "append_history", "load_history",
           "write_report", "run_lab"]
