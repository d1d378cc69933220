"""More bad input of the kinds issue 44 lists (wrong types, zero or negative numbers, outputs in inputs
through symlinks, partial folders, bad JSON, wrong image sizes, a finished output re-run), a sibling
table of ``tests/test_bad_input.py`` with the same contract: exit 1, ONE line naming the file or the
flag and the problem, every file that existed before byte-identical afterwards - and, here, nothing
new left behind (no empty output folder).
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from tests.test_bad_input import _edit_lines, _png_size, _write, check_one_line_error, good  # noqa: F401 (good: the fixture)


def _json_edit(path: Path, fn) -> None:
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


def _camera(**values):
    return lambda t: _json_edit(t / "S" / "camera.json", lambda d: d.update(values))


def _camera_sensor_baseline_string(t: Path) -> None:
    _json_edit(t / "S" / "camera.json",
               lambda d: d.update(sensor={"type": "structured_light", "baseline_m": "0.075"}))


def _run_folder(t: Path, stats: str | None = None) -> None:
    """A run folder R with the sequence's trajectory (and ``stats`` as its stats.json)."""
    (t / "R").mkdir()
    shutil.copy(t / "traj.txt", t / "R" / "trajectory.txt")
    if stats is not None:
        _write(t / "R" / "stats.json", stats)


def _link_to_sequence(t: Path) -> None:
    os.symlink(t / "S", t / "lnk")


CASES = [
    # camera.json / scene.json: wrong types and values (strict JSON types, ported from branch rel2)
    ("info: camera.json fx is a string", ["data", "info", "{S}"], _camera(fx="525"), ["camera.json", "fx", "number"]),
    ("slam run: camera.json depth_scale is true", ["slam", "run", "{S}", "--out", "{T}/R"], _camera(depth_scale=True),
     ["camera.json", "depth_scale", "number"]),
    ("compare: sensor.baseline_m is a string", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/L"],
     _camera_sensor_baseline_string, ["camera.json", "baseline_m", "number"]),
    ("info: camera width negative", ["data", "info", "{S}"], _camera(width=-160), ["camera.json", "width"]),
    ("slam run: camera fx zero", ["slam", "run", "{S}", "--out", "{T}/R"], _camera(fx=0), ["camera.json", "fx"]),
    ("info: camera.json is a list", ["data", "info", "{S}"], lambda t: _write(t / "S" / "camera.json", "[1, 2]"),
     ["camera.json", "object"]),
    ("compare: scene.json meshes not a list", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/L"],
     lambda t: _write(t / "S" / "scene.json", '{"meshes": 5}'), ["scene.json", "meshes"]),
    # configuration files: a string where a number belongs is an error naming the file, not converted
    ("slam run: --config number as a string", ["slam", "run", "{S}", "--config", "{T}/c.json", "--out", "{T}/R"],
     lambda t: _write(t / "c.json", '{"config": {"tsdf": {"voxel_size_m": "0.01"}}}'),
     ["c.json", "voxel_size_m", "number"]),
    ("slam run: --config boolean frame count", ["slam", "run", "{S}", "--config", "{T}/c.json", "--out", "{T}/R"],
     lambda t: _write(t / "c.json", '{"config": {"max_frames": true}}'), ["c.json", "max_frames"]),
    # zero / negative / out-of-range numbers: one line naming the flag, in the one wording of Range.problem
    # (app.commands.ranged and the generated configuration flags share app.commands.flags.number_parser)
    ("ate: --max-dt negative", ["eval", "ate", "{S}/groundtruth.txt", "{T}/traj.txt", "--max-dt", "-1"], None,
     ["--max-dt", "must be >= 0, got -1"]),
    ("rpe: --delta 0", ["eval", "rpe", "{S}/groundtruth.txt", "{T}/traj.txt", "--delta", "0"], None, ["--delta", "must be > 0, got 0"]),
    ("slam render: --scale 0", ["slam", "render", "{T}/R", "--frame", "0", "--scale", "0", "--out", "{T}/v.png"],
     _run_folder, ["--scale", "must be in (0, 8], got 0"]),
    ("compare: --report-frames -1", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/L",
                                     "--report-frames", "-1"], None, ["--report-frames", "must be >= 0, got -1"]),
    ("diagnose: --top -1", ["sensor", "diagnose", "{S}", "--effects", "none", "--out", "{T}/D", "--top", "-1"],
     None, ["--top", "must be >= 0, got -1"]),
    ("recog train: --scale -1", ["recog", "train", "--objects", "chairs", "--out", "{T}/M", "--scale", "-1"], None,
     ["--scale", "must be > 0, got -1"]),
    ("recog eval: --k 0", ["recog", "eval", "{T}/M", "{T}/TS", "--k", "0"], None, ["--k", "must be >= 1, got 0"]),
    ("make-reference: --albedo 2", ["data", "make-reference", "{S}", "--out", "{T}/O", "--albedo", "2"], None,
     ["--albedo", "must be in [0, 1], got 2"]),
    ("make-reference: --min-component -5", ["data", "make-reference", "{S}", "--out", "{T}/O", "--min-component",
                                            "-5"], None, ["--min-component", "must be >= 0, got -5"]),
    ("synth views: --subdivisions 9", ["synth", "views", "--model", "{T}/m.ply", "--out", "{T}/V", "--subdivisions",
                                       "9"], None, ["--subdivisions", "must be in [0, 5], got 9"]),
    ("synth views: --clutter -2", ["synth", "views", "--model", "{T}/m.ply", "--out", "{T}/V", "--clutter", "-2"],
     None, ["--clutter", "must be >= 0, got -2"]),
    ("synth views: --distance -1", ["synth", "views", "--model", "{T}/m.ply", "--out", "{T}/V", "--distance", "-1"],
     None, ["--distance", "must be > 0, got -1"]),
    ("synth sequence: --width 0", ["synth", "sequence", "--out", "{T}/O", "--width", "0"], None, ["--width", "must be >= 1, got 0"]),
    ("batch: --threads-per-job -1", ["batch", "{S}", "--out", "{T}/B", "--threads-per-job", "-1"], None,
     ["--threads-per-job", "must be >= 0, got -1"]),
    # one dialect: --json is a switch (recog eval's file comes from --out DIR)
    ("recog eval: --json FILE", ["recog", "eval", "{T}/M", "{T}/TS", "--json", "{T}/x.json"], None, ["x.json"]),
    # partial folders, bad JSON, wrong image sizes
    ("eval run: stats.json corrupt", ["eval", "run", "{T}/R", "--gt", "{S}", "--out", "{T}/E"],
     lambda t: _run_folder(t, '{"frames": '), ["stats.json", "JSON"]),
    ("compare: depth.txt missing", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/L"],
     lambda t: (t / "S" / "depth.txt").unlink(), ["depth.txt"]),
    ("compare: depth image of the wrong size", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/L"],
     _png_size, ["80x60", "160x120"]),
    ("slam run: ground truth line of 3 values", ["slam", "run", "{S}", "--out", "{T}/R"],
     lambda t: _write(t / "S" / "groundtruth.txt", (t / "S" / "groundtruth.txt").read_text() + "1 2 3\n"),
     ["groundtruth.txt", "8 values"]),
    # outputs in inputs through symlinks; the same sequence twice through a symlink
    ("compare: --out inside the sequence through a link", ["sensor", "compare", "{S}", "--effects", "none",
                                                           "--out", "{T}/lnk/lab"], _link_to_sequence,
     ["--out", "input"]),
    ("batch: an empty backend name", ["batch", "{S}", "--backends", ",icp", "--out", "{T}/B"], None,
     ["--backends", "empty name"]),
    ("batch: a sequence twice through a link", ["batch", "{S}", "{T}/lnk", "--backends", "icp", "--out", "{T}/B"],
     _link_to_sequence, ["given twice"]),
    # a finished output re-run without --overwrite (the one re-run rule)
    ("slam run: onto a finished run", ["slam", "run", "{S}", "--out", "{T}/R"],
     lambda t: _run_folder(t, '{"complete": true}'), ["R", "finished", "--overwrite"]),
    ("compare: onto a finished lab folder", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/L"],
     lambda t: _write(t / "L" / "metrics.json", "{}"), ["metrics.json", "--overwrite"]),
]


def test_at_least_twenty_more_cases_over_the_command_groups():
    assert len(CASES) >= 20
    assert {argv[0] for _, argv, _, _ in CASES} >= {"data", "sensor", "slam", "eval", "recog", "synth", "batch"}


@pytest.mark.parametrize("name, argv, breaks, words", CASES, ids=[c[0] for c in CASES])
def test_more_bad_input_is_one_line_exit_1_and_changes_nothing(name, argv, breaks, words, good, tmp_path, capsys,
                                                               monkeypatch):
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    shutil.copytree(good, tmp_path, dirs_exist_ok=True)
    if breaks is not None:
        breaks(tmp_path)
    check_one_line_error(tmp_path, argv, words, capsys, exact=True)


@pytest.mark.parametrize("kind, low, high, low_open, text", [(int, 1, None, False, "0"), (float, 0, None, True, "-2"),
                                                             (float, 0, 1, False, "1.5"), (int, 0, 5, False, "9"),
                                                             (float, 0, None, True, "nan"), (int, 0, None, False, "x")])
def test_one_wording_for_range_errors(kind, low, high, low_open, text):
    """``ranged`` (hand-written flags) and a generated configuration flag with the same Range fail with
    the same words: one parser, one wording (Range.problem)."""
    import argparse

    from app.commands import ranged
    from app.commands.flags import number_parser
    from data_tools.config import Range
    rng = Range(low, high, open_lo=low_open)
    msgs = []
    for parse in (ranged("--x", kind, low, high, low_open), number_parser(kind, rng)):
        with pytest.raises(argparse.ArgumentTypeError) as e:
            parse(text)
        msgs.append(str(e.value))
    assert msgs[0] == msgs[1] and msgs[0].endswith(f"got {text!r}" if text == "x" else f"got {text}")
    if text not in ("x", "nan"):
        assert msgs[0] == f"{rng.problem(kind(text))}, got {text}"
