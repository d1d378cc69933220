"""``--max-frames N`` means the first N frames in every command that takes it (issue 44, section 4).

Each command is run on a tiny 6-frame sequence and the frames it reports using are compared with
the sequence's first N: the trajectory of ``slam run`` and ``batch``, the written sequence of
``sensor simulate``, ``lab_config.json``'s frame indices of ``sensor compare/diagnose/fit``,
``reference_config.json``'s fused timestamps of ``data make-reference`` (``recog eval``:
tests/test_recog.py, on its trained model). ``--spread-frames K`` (the sensor lab's and
make-reference's sample) takes K of those, evenly spread; the lab's defaults stay spread samples.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from app.commands.sensor import first_frames_slice
from tests.test_cli_dialect import leaf_parsers, options

COVERED = {"slam run", "batch", "recog eval", "sensor simulate", "sensor compare", "sensor diagnose", "sensor fit",
           "data make-reference"}
"""Commands whose --max-frames is run below (recog eval in tests/test_recog.py)."""


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    from synth.sequence import SEQUENCE_PRESETS, generate_sequence
    root = tmp_path_factory.mktemp("mf") / "S"
    generate_sequence(replace(SEQUENCE_PRESETS["kinect_v1"], frames=6, seed=0).with_resolution(64, 48), root,
                      progress=False)
    return root


def _stamps(path: Path) -> list[float]:
    return [float(ln.split()[0]) for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def test_every_command_with_max_frames_is_covered_and_says_first_n():
    from app.commands import SHARED_FLAGS
    seen = {cmd for cmd, p in leaf_parsers().items() if "--max-frames" in options(p)}
    assert seen == COVERED
    for cmd, p in leaf_parsers().items():
        o = options(p)
        for flag in ("--max-frames", "--spread-frames"):
            if flag in o:
                assert o[flag].help.startswith(SHARED_FLAGS[flag]), (cmd, flag)
    assert SHARED_FLAGS["--max-frames"].startswith("the first N frames")


@pytest.mark.parametrize("text, first", [(None, 3), ("0::2", 2), ("1:4", 5), ("1::3", 1), ("-3:", 2), (":-1:2", 4),
                                         ("-5:-1", 9), ("2:", None), ("6:", 3)])
def test_first_frames_slice_is_the_slice_then_its_first_n(text, first):
    """Cross-check against numpy: the composed slice selects exactly the slice's first N frames."""
    from synth.lab.measured import parse_frame_slice
    n = 7
    got = first_frames_slice(text, first, lambda: n)
    frames = np.arange(n)
    want = frames[parse_frame_slice(text)] if text else frames
    assert list(frames[parse_frame_slice(got)] if got else frames) == list(want[:first])


@pytest.mark.parametrize("text", ["4:2", "10:20", "-20:-9"])
def test_a_slice_that_selects_nothing_is_named_as_written(text):
    from data_tools.errors import ConfigError
    with pytest.raises(ConfigError, match=f"^--frame-slice {text}: selects none of the 7 frames with a pose$"):
        first_frames_slice(text, 2, lambda: 7)


def test_slam_run_and_batch_use_the_first_n(seq, tmp_path, monkeypatch):
    from data_tools.trajectory import read_tum
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    stamps = _stamps(seq / "depth.txt")
    assert main(["slam", "run", str(seq), "--out", str(tmp_path / "R"), "--max-frames", "2",
                 "--tsdf.voxel-size-m", "0.05"]) in (0, 3)
    run = read_tum(tmp_path / "R" / "trajectory.txt").timestamps
    assert 1 <= len(run) <= 2 and set(run) <= set(stamps[:2])
    assert main(["batch", str(seq), "--backends", "icp", "--out", str(tmp_path / "B"), "--max-frames", "3",
                 "--workers", "1", "--tsdf.voxel-size-m", "0.05"]) in (0, 1)
    trajs = list((tmp_path / "B").rglob("trajectory.txt"))
    assert len(trajs) == 1
    run = read_tum(trajs[0]).timestamps
    assert 1 <= len(run) <= 3 and set(run) <= set(stamps[:3]) and stamps[0] in set(run)


def test_sensor_simulate_and_make_reference_use_the_first_n(seq, tmp_path, monkeypatch):
    from data_tools.sequence import SequenceReader
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    stamps = _stamps(seq / "depth.txt")
    assert main(["sensor", "simulate", str(seq), "--effects", "none", "--out", str(tmp_path / "Q"),
                 "--max-frames", "2"]) == 0
    assert list(SequenceReader(tmp_path / "Q").timestamps) == pytest.approx(stamps[:2])
    # the spread sample: 2 of the first 5 frames, evenly spread = the first and the fifth
    assert main(["sensor", "simulate", str(seq), "--effects", "none", "--out", str(tmp_path / "Q2"),
                 "--max-frames", "5", "--spread-frames", "2"]) == 0
    assert list(SequenceReader(tmp_path / "Q2").timestamps) == pytest.approx([stamps[0], stamps[4]])
    for name, extra, want in (("M", ["--max-frames", "3"], stamps[:3]),
                              ("M2", ["--spread-frames", "3"], [stamps[0], stamps[2], stamps[5]])):
        assert main(["data", "make-reference", str(seq), "--out", str(tmp_path / name), "--voxel", "0.05",
                     "--depth-max", "6", "--min-component", "0", "--no-progress", *extra]) == 0
        r = json.loads((tmp_path / name / "reference_config.json").read_text())["result"]
        assert r["frames_fused"] == len(want) and r["timestamps_s"] == pytest.approx(want), name


def test_sensor_compare_diagnose_fit_use_the_first_n(seq, tmp_path, monkeypatch):
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    fast = ["--compare-preset", "fast", "--report-frames", "0"]
    # the default sample (24 spread) on 6 frames: every frame, as before
    assert main(["sensor", "compare", str(seq), "--effects", "none", "--out", str(tmp_path / "C0"), *fast]) == 0
    assert json.loads((tmp_path / "C0" / "lab_config.json").read_text())["measured"]["frame_indices"] == list(range(6))
    assert main(["sensor", "compare", str(seq), "--effects", "none", "--out", str(tmp_path / "C"), *fast,
                 "--max-frames", "3", "--frame-slice=-5:"]) == 0   # a negative START: counted
    assert json.loads((tmp_path / "C" / "lab_config.json").read_text())["measured"]["frame_indices"] == [1, 2, 3]
    fit = ["--fit-option", "max_evaluations=2", "--fit-option", "intervals=false", "--fit-option",
           "max_pixels_per_frame=500", "--fit-option", "eval_pixels_per_frame=500"]
    assert main(["sensor", "fit", str(seq), "--effects", "axial_noise", "--out", str(tmp_path / "m.json"),
                 "--max-frames", "2", *fit]) == 0
    fitted = json.loads((tmp_path / "m.json").read_text())["fit"]
    assert fitted["lab_config"]["measured"]["frame_indices"] == [0, 1]
    assert main(["sensor", "diagnose", str(seq), "--effects", "none", "--candidates", "axial_noise", "--top", "0",
                 "--out", str(tmp_path / "D"), "--max-frames", "2", *fit[:2],
                 "--diagnose-option", "candidate_evaluations=2"]) == 0
    assert json.loads((tmp_path / "D" / "lab_config.json").read_text())["measured"]["frame_indices"] == [0, 1]
