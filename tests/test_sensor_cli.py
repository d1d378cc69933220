"""``realgap sensor``: simulate / compare / diagnose / fit on a tiny synthetic "measured" sequence,
plus the diagnosis figures' statistics on hand-made arrays.

The measured sequence is simulated with a known model (axial noise + projector shadow +
disparity quantisation, 160x120 crop of a Kinect v1), so the lab must find that adding the
true effects lowers the gap.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.cli import main

REPO = Path(__file__).resolve().parents[1]
TRUE_EFFECTS = ("axial_noise", "projector_shadow", "disparity_quantization")


def _run(*args):
    return subprocess.run([sys.executable, "-m", "app", *map(str, args)], capture_output=True, text=True,
                          cwd=REPO, timeout=300)


def make_measured_sequence(root: Path, frames: int = 3, width: int = 160, height: int = 120,
                           effects=TRUE_EFFECTS, seed: int = 7) -> Path:
    """A small 'measured' sequence: the room scene seen by a cropped Kinect v1 model."""
    from data_tools.sequence import SequenceReader, SequenceWriter
    from synth.sensor.presets import get_preset
    from synth.sensor.config import SensorConfig
    from synth.sensor.pool import simulate_trajectory
    from synth.sensor.simulator import SensorSimulator
    from synth.sequence import SEQUENCE_PRESETS, generate_sequence

    pre = get_preset("kinect_v1").cropped(width, height)
    cfg = replace(SEQUENCE_PRESETS["kinect_v1"], frames=frames, seed=0).with_resolution(width, height)
    generate_sequence(cfg, root / "ideal", progress=False)
    ideal = SequenceReader(root / "ideal")
    traj = ideal.trajectory
    sim = SensorSimulator(SensorConfig.build(pre, list(effects)), scene=ideal.scene)
    seq = root / "seq"
    with SequenceWriter(seq, sim.camera(), ideal.scene) as w:
        simulate_trajectory(sim, traj.poses, traj.timestamps, w, seed=seed, progress=False)
    return seq


@pytest.fixture(scope="module")
def measured(tmp_path_factory) -> Path:
    return make_measured_sequence(tmp_path_factory.mktemp("measured"))


def _data_lines(path: Path) -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


# ------------------------------------------------------------------------------------ compare

def test_compare_metrics_report_and_history_accumulates(measured, tmp_path):
    lab = tmp_path / "lab"
    assert main(["sensor", "compare", str(measured), "--effects", "none", "--out", str(lab),
                 "--compare-preset", "fast", "--report-frames", "1"]) == 0
    m = json.loads((lab / "metrics.json").read_text())
    assert isinstance(m["gap"], float) and m["gap"] > 0
    assert {"distance", "incidence", "radial", "material", "edge_distance"} <= set(m["breakdowns"])
    for f in ("report.html", "history.json", "lab_config.json", "sensor_config.json", "compare_config.json",
              "figures/history.png", "figures/frame_000.png", "figures/breakdown_distance.png"):
        assert (lab / f).is_file(), f
    cfg = json.loads((lab / "lab_config.json").read_text())
    assert cfg["effects_used"] == [] and cfg["command"] == "sensor compare"

    # the true effects (with the preset defaults the sequence was made with) close most of the gap; a finished
    # lab folder is replaced only with --overwrite (the re-run rule), and its gap history keeps its steps
    again = ["sensor", "compare", str(measured), "--effects", ",".join(TRUE_EFFECTS), "--out", str(lab),
             "--compare-preset", "fast", "--report-frames", "1"]
    assert main(again) == 1
    assert main(again + ["--overwrite"]) == 0
    hist = json.loads((lab / "history.json").read_text())["entries"]
    assert [e["effects"] for e in hist] == [[], list(TRUE_EFFECTS)]
    assert hist[1]["gap"] < 0.5 * hist[0]["gap"]
    page = (lab / "report.html").read_text()
    assert "Gap history" in page and "history.png" in page

    # --compare-against continues the history in a new folder
    lab2 = tmp_path / "lab2"
    assert main(["sensor", "compare", str(measured), "--effects", "axial_noise", "--out", str(lab2),
                 "--compare-against", str(lab), "--compare-preset", "fast", "--report-frames", "0"]) == 0
    hist2 = json.loads((lab2 / "history.json").read_text())["entries"]
    assert len(hist2) == 3 and hist2[2]["effects"] == ["axial_noise"]
    assert hist[1]["gap"] < hist2[2]["gap"] < hist[0]["gap"]


# ------------------------------------------------------------------------------------ simulate

def test_simulate_keeps_timestamps_and_names_and_resumes(measured, tmp_path):
    out = tmp_path / "sim"
    args = ["sensor", "simulate", str(measured), "--effects", "axial_noise,projector_shadow", "--out", str(out),
            "--seed", "3"]
    assert main(args) == 0
    assert _data_lines(out / "depth.txt") == _data_lines(measured / "depth.txt")
    assert (out / "groundtruth.txt").read_text() == (measured / "groundtruth.txt").read_text()
    assert _data_lines(out / "rgb.txt") == _data_lines(measured / "rgb.txt")
    for f in ("camera.json", "scene.json", "sensor_config.json", "lab_config.json"):
        assert (out / f).is_file(), f
    from data_tools.sequence import SequenceReader
    a, b = SequenceReader(measured), SequenceReader(out)
    assert len(a) == len(b) and a.depth_files == b.depth_files
    d0 = b.read_depth(0)
    assert d0.shape == a.intrinsics.shape and (d0 > 0).mean() > 0.5
    assert not np.array_equal(d0, a.read_depth(0))  # a different model and seed than the measurement
    first = {rel: (out / rel).read_bytes() for rel in b.depth_files}

    # interrupt: drop the last frame's index line and image, as a killed run leaves it (with its incomplete
    # marker), re-run -> identical result
    from data_tools.outputs import mark_incomplete
    mark_incomplete(out, "realgap sensor simulate", len(b.depth_files) - 1, len(b.depth_files))
    lines = (out / "depth.txt").read_text().splitlines()
    (out / "depth.txt").write_text("\n".join(lines[:-1]) + "\n")
    (out / b.depth_files[-1]).unlink()
    assert main(args) == 0
    assert {rel: (out / rel).read_bytes() for rel in b.depth_files} == first
    assert _data_lines(out / "depth.txt") == _data_lines(measured / "depth.txt")

    # the finished folder, and another model into it, need --overwrite
    assert main(args) == 1
    r = _run("sensor", "simulate", measured, "--effects", "axial_noise", "--out", out)
    assert r.returncode == 1 and "--overwrite" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert main(["sensor", "simulate", str(measured), "--effects", "none", "--out", str(out), "--overwrite",
                 "--max-frames", "2"]) == 0
    assert len(_data_lines(out / "depth.txt")) == 2


# ------------------------------------------------------------------------------------ fit + model

def test_fit_saves_model_reused_by_compare(measured, tmp_path):
    pytest.importorskip("synth.lab.fit")
    model = tmp_path / "model.json"
    assert main(["sensor", "fit", str(measured), "--effects", "axial_noise", "--out", str(model),
                 "--fit-option", "max_evaluations=8", "--fit-option", "max_frames=2",
                 "--fit-option", "max_pixels_per_frame=1500"]) == 0
    d = json.loads(model.read_text())
    assert {"preset", "effects", "fit"} <= set(d)
    assert d["fit"]["gap"] <= d["fit"]["gap_before"] + 1e-12
    lab = tmp_path / "lab"
    assert main(["sensor", "compare", str(measured), "--model", str(model), "--effects",
                 "projector_shadow", "--out", str(lab), "--compare-preset", "fast", "--report-frames", "0"]) == 0
    used = json.loads((lab / "lab_config.json").read_text())["effects_used"]
    assert used == ["axial_noise", "projector_shadow"]
    saved = json.loads((lab / "sensor_config.json").read_text())
    ax = next(e for e in saved["effects"] if e["name"] == "axial_noise")
    fitted = next(e for e in d["effects"] if e["name"] == "axial_noise")
    assert ax["params"] == fitted["params"]

    # both carry the one result header; `realgap show` lines them up
    from data_tools.results import read_result
    fit_r, lab_r = read_result(model), read_result(lab)
    assert (fit_r.kind, lab_r.kind) == ("lab.fit", "lab.compare")
    assert fit_r.metrics["gap"] == d["fit"]["gap"]
    assert lab_r.metrics["gap"] == json.loads((lab / "metrics.json").read_text())["gap"]
    assert fit_r.header["command"].startswith("realgap sensor fit ") and fit_r.header["inputs"][0]["sha256"]
    assert main(["show", str(model), str(lab)]) == 0


def test_fit_accepts_lab_side_parameters_and_model_keeps_motion_limits(measured, tmp_path):
    """lens_distortion's only fittable parameters are k1/k2 (added to its coefficients), so `sensor fit` must accept
    a model with only that effect; a --model file keeps its other fields (motion limits)."""
    import dataclasses

    from synth.lab.model import save_model
    from synth.sensor.config import MotionLimits, SensorConfig
    model = tmp_path / "lens.json"
    assert main(["sensor", "fit", str(measured), "--effects", "lens_distortion", "--out", str(model),
                 "--fit-option", "max_evaluations=4", "--fit-option", "max_frames=1",
                 "--fit-option", "max_pixels_per_frame=1500"]) == 0
    assert set(json.loads(model.read_text())["fit"]["params"]) == {"lens_distortion.k1", "lens_distortion.k2"}
    motion = MotionLimits(max_speed_m_s=0.7, max_angular_speed_rad_s=0.3)
    slow = save_model(dataclasses.replace(SensorConfig.build("kinect_v1", ["axial_noise"]), motion=motion),
                      tmp_path / "slow.json")
    from synth.lab.runs import build_config
    from synth.lab.measured import MeasuredSequence
    cfg = build_config(MeasuredSequence.load(measured, max_frames=1), ["projector_shadow"], slow)
    assert cfg.motion == motion and cfg.names() == ["axial_noise", "projector_shadow"]


# ------------------------------------------------------------------------------------ diagnose

def test_diagnose_ranks_the_missing_effect_first(measured, tmp_path):
    pytest.importorskip("synth.lab.diagnose")
    out = tmp_path / "diag"
    assert main(["sensor", "diagnose", str(measured), "--effects", "axial_noise,disparity_quantization",
                 "--candidates", "projector_shadow,depth_bias", "--out", str(out), "--top", "2",
                 "--report-frames", "1", "--fit-option", "max_evaluations=6", "--fit-option", "max_frames=2",
                 "--fit-option", "max_pixels_per_frame=1500"]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert isinstance(d["gap"], float) and d["ranking"]
    for c in d["ranking"]:
        assert {"effect", "gap_after", "gain", "params", "evidence"} <= set(c)
    gains = [c["gain"] for c in d["ranking"]]
    assert gains == sorted(gains, reverse=True)
    assert d["ranking"][0]["effect"] == "projector_shadow"
    from data_tools.results import read_result
    res = read_result(out)
    assert res.kind == "lab.diagnose" and res.metrics["gap"] == d["gap"]
    page = (out / "diagnosis.html").read_text()
    assert "projector_shadow" in page and "holes beside foreground objects" in page
    assert len(list((out / "figures").glob("diag_*.png"))) == 2
    assert (out / "lab_config.json").is_file()
    # the best candidate's fitted model is reusable
    best = json.loads((out / "best_model.json").read_text())
    assert "projector_shadow" in [e["name"] for e in best["effects"]]
    assert best["fit"]["gap"] == pytest.approx(d["ranking"][0]["gap_after"])
    assert (out / "models" / "model_refit.json").is_file() and (out / "models" / "depth_bias.json").is_file()
    assert main(["sensor", "compare", str(measured), "--model", str(out / "best_model.json"), "--out",
                 str(tmp_path / "lab"), "--compare-preset", "fast", "--report-frames", "0"]) == 0


# ------------------------------------------------------------------------------------ errors

def _one_line_error(r, *needles):
    assert r.returncode == 1, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_bad_input_is_one_line_exit_1(measured, tmp_path):
    _one_line_error(_run("sensor", "compare", measured, "--effects", "axial_noise,warp_drive", "--out", tmp_path / "x"),
                    "warp_drive", "known effects", "projector_shadow")
    _one_line_error(_run("sensor", "compare", measured, "--out", tmp_path / "x"), "--effects")
    bad = tmp_path / "noscene"
    shutil.copytree(measured, bad, ignore=shutil.ignore_patterns("scene.json"))
    _one_line_error(_run("sensor", "diagnose", bad, "--effects", "none", "--out", tmp_path / "x"), "scene.json")
    nogt = tmp_path / "nogt"
    shutil.copytree(measured, nogt, ignore=shutil.ignore_patterns("groundtruth.txt"))
    _one_line_error(_run("sensor", "simulate", nogt, "--effects", "none", "--out", tmp_path / "y"), "groundtruth")
    corrupt = tmp_path / "corrupt"
    shutil.copytree(measured, corrupt)
    first = _data_lines(corrupt / "depth.txt")[0].split()[1]
    (corrupt / first).write_bytes(b"\x89PNG\r\n\x1a\n not really")
    _one_line_error(_run("sensor", "compare", corrupt, "--effects", "none", "--out", tmp_path / "z"), first)
    _one_line_error(_run("sensor", "compare", measured, "--model", tmp_path / "nope.json", "--out", tmp_path / "z"),
                    "nope.json")


# ------------------------------------------------------------------------------------ figure statistics

def test_binned_statistics_by_hand():
    from synth.lab.signatures import binned_statistics
    x = np.array([0.5] * 40 + [1.5] * 40 + [2.5] * 5)
    ideal = np.ones(85)
    depth = np.concatenate([np.full(40, 1.01), np.r_[np.zeros(10), np.linspace(0.9, 1.1, 30)], np.ones(5)])
    st = binned_statistics(x, depth, ideal, [0, 1, 2, 3], min_count=20)
    assert st["count"].tolist() == [40, 40, 5]
    assert st["invalid_fraction"][0] == 0 and st["invalid_fraction"][1] == pytest.approx(0.25)
    assert st["bias"][0] == pytest.approx(0.01) and st["std"][0] == pytest.approx(0.0)
    assert st["bias"][1] == pytest.approx(0.0, abs=1e-12)
    q1, q3 = np.percentile(np.linspace(0.9, 1.1, 30) - 1, [25, 75])
    assert st["std"][1] == pytest.approx((q3 - q1) / 1.349)
    assert np.isnan(st["bias"][2]) and np.isnan(st["invalid_fraction"][2])  # 5 < min_count


def test_depth_level_steps_follow_disparity_quantisation():
    """Depths from quantised disparity d = k/8 px: spacing = z^2 / (8 f b) to first order."""
    from synth.lab.signatures import depth_level_steps
    f, b = 580.0, 0.075
    k = np.arange(8 * 10, 8 * 40)  # disparities 10..40 px -> z from ~1.1 m to ~4.3 m
    z = (f * b / (k / 8.0)).astype(np.float64)
    zs, steps = depth_level_steps(np.sort(z).reshape(1, -1))
    pred = zs ** 2 / (8 * f * b)
    np.testing.assert_allclose(steps, pred, rtol=0.05)


def test_radial_error_map_and_signature_figures(tmp_path):
    """A radial bias in a synthetic frame shows up as a bowl in the block map; every registered
    signature renders without error."""
    from data_tools.camera import Intrinsics
    from synth.lab.features import FrameObservation
    from synth.lab.signatures import radial_error_map, signature_of, write_diagnosis_report
    from synth.sensor.registry import effect_names
    intr = Intrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)
    v, u = np.mgrid[0:48, 0:64]
    r2 = ((u - 31.5) ** 2 + (v - 23.5) ** 2) / (31.5 ** 2 + 23.5 ** 2)
    ideal = np.full((48, 64), 2.0, np.float32)
    ideal[10:30, 20:40] = 1.2  # a box in front: depth edges
    meas = (ideal + 0.02 * r2).astype(np.float32)
    meas[10:30, 17:20] = 0  # holes beside it
    normals = np.zeros((48, 64, 3), np.float32)
    normals[..., 2] = -1
    ids = np.ones((48, 64), np.int32)
    obs = [FrameObservation(meas, ideal, ideal, normals, ids, {0: "(no geometry)", 1: "wall"}, intr,
                            (0.075, 0.0, 0.0), index=0)]
    m = radial_error_map(obs, "measured", block_px=16)
    assert m.shape == (3, 4)
    assert m[1, 1] < m[0, 0] and m[1, 2] < m[2, 3]  # centre blocks below corner blocks
    cands = {name: obs for name in effect_names() if signature_of(name) is not None}
    cands["warp_field"] = obs  # an effect without a signature gets the generic figure
    diag = {"gap": 1.0, "model": [], "ranking": [{"effect": n, "gap_after": 0.5, "gain": 0.5, "params": {},
                                                  "evidence": f"evidence for {n}"} for n in cands]}
    page = write_diagnosis_report(diag, obs, cands, tmp_path)
    text = page.read_text()
    assert text.count("<img") == len(cands) and "evidence for lens_distortion" in text
    assert "residual growing with image radius" in text
