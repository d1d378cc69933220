"""The sensor lab on real Kinect v1 data (shared/data; skipped when absent).

Reference geometry = a TSDF mesh fused from the sequence's own frames at their ground-truth
poses (slam.reference). Acceptance (issue #4): the gap of the ideal model > the gap of
``axial_noise`` alone > the gap of the best fitted model, on TUM fr1/xyz and 7-Scenes chess;
compare and diagnose run end to end through the CLI.

The default test is small (4 TUM frames, 5000 compare pixels per frame, library calls, no
figures); the end-to-end runs are ``slow``.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from app.cli import main
from tests.conftest import shared_path


def _tum_with_reference(root: Path, voxel: float = 0.01) -> Path:
    from slam.reference import NAMED_CAMERAS, ReferenceConfig, make_reference
    from slam.tsdf import TSDFConfig
    src = shared_path("tum_fr1_xyz_10")
    out = root / "tum_fr1_xyz_ref"
    cfg = ReferenceConfig(tsdf=TSDFConfig(voxel_size_m=voxel, integrate_color=False, depth_max_m=4.0))
    make_reference(src, out, cfg, camera=NAMED_CAMERAS["tum_fr1"])
    return out


def test_tum_fr1_ideal_worse_than_axial_noise_fast(tmp_path):
    """Few frames, reduced pixels: adding the preset's axial noise lowers the gap on real data."""
    from synth.lab.compare import compare, compare_preset
    from synth.lab.measured import MeasuredSequence
    seq = _tum_with_reference(tmp_path, voxel=0.02)
    ms = MeasuredSequence.load(seq, max_frames=4)
    assert ms.preset.type == "structured_light" and ms.intrinsics.fx == 517.3
    cfg = compare_preset("fast")
    gaps = {}
    for name, effects in (("ideal", []), ("axial_noise", ["axial_noise"])):
        sim = ms.simulate(ms.default_config(effects), seed=0)
        gaps[name] = compare(ms.observations(sim), cfg, effects=effects).gap
    assert gaps["axial_noise"] < 0.9 * gaps["ideal"], gaps


def _lab_run(seq: Path, lab: Path, frames: int, diag_frames: int) -> dict:
    """ideal -> axial_noise -> diagnose -> best fitted model (diagnose's best_model.json), all through
    the CLI; the history in ``lab`` must fall at every step. Returns the numbers."""
    common = ["--spread-frames", str(frames), "--report-frames", "2"]
    assert main(["sensor", "compare", str(seq), "--effects", "none", "--out", str(lab), *common]) == 0
    assert main(["sensor", "compare", str(seq), "--effects", "axial_noise", "--out", str(lab), "--overwrite",
                 *common]) == 0      # a finished lab folder: --overwrite (the re-run rule); the history keeps its steps
    diag_dir = lab / "diagnosis"
    assert main(["sensor", "diagnose", str(seq), "--effects", "axial_noise", "--out", str(diag_dir),
                 "--spread-frames", str(diag_frames)]) == 0
    diag = json.loads((diag_dir / "diagnosis.json").read_text())
    assert diag["ranking"] and diag["ranking"][0]["gain"] > 0, diag["ranking"]
    # the best fitted model = the diagnosis's best candidate (axial noise refitted + that effect)
    best = diag_dir / "best_model.json"
    assert main(["sensor", "compare", str(seq), "--model", str(best), "--out", str(lab), "--overwrite", *common]) == 0
    hist = json.loads((lab / "history.json").read_text())["entries"]
    gaps = [e["gap"] for e in hist]
    assert len(gaps) == 3
    assert gaps[0] > gaps[1] > gaps[2], gaps
    page = (lab / "report.html").read_text()
    assert "Gap history" in page
    assert (diag_dir / "diagnosis.html").is_file()
    assert all({"effect", "gap_after", "gain", "params", "evidence"} <= set(c) for c in diag["ranking"])
    return {"gaps": gaps, "top3": [(c["effect"], c["gain"]) for c in diag["ranking"][:3]]}


@pytest.mark.slow
def test_tum_fr1_end_to_end_gap_falls(tmp_path):
    seq = _tum_with_reference(tmp_path)
    _lab_run(seq, tmp_path / "lab", frames=10, diag_frames=6)


@pytest.mark.slow
def test_sevenscenes_chess_end_to_end_gap_falls(tmp_path):
    src = shared_path("sevenscenes_chess_1000")
    conv = tmp_path / "chess"
    assert main(["data", "convert-7scenes", str(src), "--out", str(conv)]) == 0
    seq = tmp_path / "chess_ref"
    assert main(["data", "make-reference", str(conv), "--out", str(seq), "--material", "chess_scene",
                 "--albedo", "0.5"]) == 0
    sc = json.loads((seq / "scene.json").read_text())
    assert sc["materials"]["chess_scene"]["albedo"] == 0.5
    _lab_run(seq, tmp_path / "lab", frames=24, diag_frames=8)
