"""No silent wrong result from ``slam run`` and ``batch`` (issue 44, item 2).

A run that registers fewer than half its frames ends with a FAILED RUN line and exit code 3 and
``batch`` marks it failed; a sequence marked incomplete gives a warning; two writers into one
``--out`` are refused through ``RUN/lock.json`` (a stale lock of a dead pid is reported and taken
over); ``batch --backends icp,icp`` is refused before any work.
"""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from app.cli import main
from app.commands import EXIT_POOR_TRACKING
from data_tools.outputs import LOCK_FILE, mark_incomplete
from slam.pipeline import poor_tracking
from tests.slam_scenes import camera_path, render_frames, room_scene, write_sequence

SMALL = ["--tsdf.voxel-size-m", "0.01", "--tsdf.mesh-weight-threshold", "1", "--icp.raycast-scale", "1",
         "--no-progress"]


@pytest.fixture(scope="module")
def seqs(tmp_path_factory):
    """(good 6-frame sequence, the same with frames 1-5 all black: 1 of 6 frames registers)."""
    root = tmp_path_factory.mktemp("safety")
    frames = render_frames(room_scene(), camera_path(6, 0.02, 1.0))
    good = write_sequence(root / "good", frames)
    for f in frames[1:]:
        f.depth[:] = 0
        f.rgb[:] = 0
    return good, write_sequence(root / "poor", frames)


def test_poor_tracking_rule():
    assert poor_tracking({"frames": 40, "frames_tracked": 1}).startswith("only 1 of 40 frames")
    assert poor_tracking({"frames": 40, "frames_tracked": 20}) is None          # half is enough
    assert poor_tracking({"frames": 40, "frames_tracked": 19}) is not None
    assert poor_tracking({"frames": 0, "frames_tracked": 0}) is None


def test_a_run_that_loses_track_is_loud_and_exits_3(seqs, tmp_path, capsys):
    _, poor = seqs
    rc = main(["slam", "run", str(poor), "--out", str(tmp_path / "run"), *SMALL])
    err = capsys.readouterr().err
    assert rc == EXIT_POOR_TRACKING == 3, err
    assert "FAILED RUN" in err and "of 6 frames registered" in err
    stats = json.loads((tmp_path / "run" / "stats.json").read_text())      # the run is still written
    assert stats["frames_tracked"] < 3 and not (tmp_path / "run" / LOCK_FILE).exists()


def test_batch_marks_a_run_that_loses_track_failed(seqs, tmp_path, capsys):
    _, poor = seqs
    rc = main(["batch", str(poor), "--backends", "icp", "--out", str(tmp_path / "rep"), "--workers", "1", *SMALL])
    assert rc == 1
    (r,) = json.loads((tmp_path / "rep" / "results.json").read_text())["results"]
    assert r["ok"] is False and r["error"].startswith("failed run: only")


def test_an_incomplete_sequence_warns_and_a_stale_lock_is_taken_over(seqs, tmp_path, capsys):
    import shutil
    good, _ = seqs
    seq = tmp_path / "seq"
    shutil.copytree(good, seq)
    mark_incomplete(seq, "realgap synth sequence", 6, 10)
    run = tmp_path / "run"
    run.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()                                        # a pid that no longer runs
    (run / LOCK_FILE).write_text(json.dumps({"pid": dead.pid, "host": __import__("socket").gethostname(),
                                             "command": "realgap slam run", "started": "2026-01-01T00:00:00"}))
    assert main(["slam", "run", str(seq), "--out", str(run), "--max-frames", "2", *SMALL]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "unfinished" in err and "incomplete: 6/10" in err, err
    assert f"stale lock of pid {dead.pid}" in err, err
    assert not (run / LOCK_FILE).exists() and (run / "stats.json").is_file()


def test_a_second_writer_is_refused_and_changes_nothing(seqs, tmp_path, capsys):
    good, _ = seqs
    run = tmp_path / "run"
    run.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = json.dumps({"pid": holder.pid, "host": __import__("socket").gethostname(),
                           "command": "realgap slam run", "started": "2026-01-01T00:00:00"})
        (run / LOCK_FILE).write_text(lock)
        assert main(["slam", "run", str(good), "--out", str(run), *SMALL]) == 1
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and f"pid {holder.pid}" in err and "another process" in err, err
        assert sorted(p.name for p in run.iterdir()) == [LOCK_FILE] and (run / LOCK_FILE).read_text() == lock
    finally:
        holder.kill()
        holder.wait()


def test_batch_refuses_a_backend_twice(seqs, tmp_path, capsys):
    good, _ = seqs
    assert main(["batch", str(good), "--backends", "icp,icp", "--out", str(tmp_path / "rep")]) == 1
    err = capsys.readouterr().err.strip()
    assert "--backends" in err and "icp given twice" in err and "\n" not in err
    assert not (tmp_path / "rep").exists()
