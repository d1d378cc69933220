"""Kill-and-resume: every long command is killed part-way (SIGKILL, in a subprocess: no clean-up
runs), re-run with the same arguments, and its result must equal an uninterrupted run's.

The commands that continue (synth sequence, synth views, sensor simulate, sensor fit, sensor
diagnose, slam run, batch) must say how many finished steps they kept; the one that does not
(data make-reference) must say so in its unfinished marker and start again. While a folder is
unfinished, ``data info`` / ``realgap show`` report it as incomplete.

Each command is killed as soon as its own progress on disk shows a finished step (the
``incomplete.json`` marker, a journal of objective evaluations, a SLAM checkpoint), so the
test does not depend on timing; the workloads are sized to last several seconds after that.
"""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")


def _cmd(args, progress_flag: bool = True) -> list[str]:
    return [sys.executable, "-m", "app", *map(str, args), *(["--no-progress"] if progress_flag else [])]


def run_ok(args) -> subprocess.CompletedProcess:
    r = subprocess.run(_cmd(args), capture_output=True, text=True, cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stderr
    return r


def _descendants(pid: int) -> set[int]:
    """Process ids of every child, grandchild, ... of ``pid`` (Linux /proc)."""
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        try:
            kids = [int(k) for t in os.listdir(f"/proc/{p}/task")
                    for k in open(f"/proc/{p}/task/{t}/children").read().split()]
        except OSError:
            continue
        out.update(kids)
        todo += kids
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def kill_part_way(args, ready, timeout: float = 300.0) -> None:
    """Start ``realgap ARGS``, SIGKILL it as soon as ``ready()`` holds; fail if it ends first.
    Its worker processes must end with it (no orphans left computing)."""
    p = subprocess.Popen(_cmd(args), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    try:
        while not ready():
            if p.poll() is not None:
                pytest.fail(f"{' '.join(map(str, args[:2]))} ended (exit {p.returncode}) before it could be "
                            f"killed part-way; make the workload longer. stderr: {p.stderr.read()[-500:]}")
            if time.monotonic() - t0 > timeout:
                pytest.fail("the command showed no progress on disk in time")
            time.sleep(0.01)
        workers = _descendants(p.pid)
        p.send_signal(signal.SIGKILL)
    finally:
        p.wait(timeout=30)
        p.stderr.close()
    assert p.returncode == -signal.SIGKILL
    t0 = time.monotonic()
    while any(_alive(w) for w in workers) and time.monotonic() - t0 < 10:
        time.sleep(0.1)
    assert not [w for w in workers if _alive(w)], "worker processes outlived the killed command"


def marker_at_least(folder: Path, n: int):
    """ready() when ``folder/incomplete.json`` says at least ``n`` steps are done."""
    def ready() -> bool:
        try:
            return json.loads((folder / "incomplete.json").read_text())["done"] >= n
        except (OSError, ValueError, KeyError):
            return False
    return ready


def lines_at_least(path: Path, n: int):
    def ready() -> bool:
        try:
            return len(path.read_text().splitlines()) >= n
        except OSError:
            return False
    return ready


def assert_reported_incomplete(folder: Path) -> None:
    from data_tools.outputs import read_incomplete
    assert read_incomplete(folder) is not None, f"{folder} carries no unfinished marker after the kill"
    r = subprocess.run(_cmd(["data", "info", folder]), capture_output=True, text=True, cwd=REPO, timeout=120)
    assert "incomplete:" in r.stdout + r.stderr, (r.stdout, r.stderr)


def sequence_digest(folder: Path) -> dict:
    """Index files, ground truth and decoded depth pixels of a TUM-layout folder."""
    from data_tools.sequence import read_depth_png
    out = {}
    for name in ("depth.txt", "groundtruth.txt"):
        if (folder / name).is_file():
            out[name] = [ln.strip() for ln in (folder / name).read_text().splitlines()
                         if ln.strip() and not ln.startswith("#")]
    for ln in out["depth.txt"]:
        f = ln.split()[1]
        out[f] = hashlib.sha256(np.ascontiguousarray(read_depth_png(folder / f, 1.0)).tobytes()).hexdigest()
    return out


def _strip_volatile(d):
    """JSON without wall-clock fields (timings, dates, commands, output paths)."""
    volatile = {"seconds", "timings_s", "created", "updated", "header", "fit_s", "diagnose_s", "run_dir",
                "frames_per_second", "command", "out", "out_dir", "path", "meta", "seconds_total", "evaluations_s"}
    if isinstance(d, dict):
        return {k: _strip_volatile(v) for k, v in d.items() if k not in volatile}
    if isinstance(d, list):
        return [_strip_volatile(v) for v in d]
    return d


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    """A 'measured' 40-frame 320x240 simulated Kinect v1 sequence of the room (scene.json, ground truth)."""
    root = tmp_path_factory.mktemp("room")
    run_ok(["synth", "sequence", "--preset", "small", "--frames", "40", "--sensor", "kinect_v1",
            "--effects", "axial_noise,projector_shadow,disparity_quantization", "--out", root / "seq"])
    return root / "seq"


# ----------------------------------------------------------------------------------- synth

def test_synth_sequence_killed_resumes_identically(tmp_path):
    args = ["synth", "sequence", "--preset", "small", "--frames", "36", "--sensor", "kinect_v1", "--seed", "2",
            "--workers", "2"]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], marker_at_least(part, 3))
    assert_reported_incomplete(part)
    r = run_ok([*args, "--out", part])
    kept = int(r.stdout.split("(kept ")[1].split(")")[0])
    assert kept >= 3, r.stdout
    run_ok([*args, "--out", full])
    assert sequence_digest(part) == sequence_digest(full)
    assert sequence_digest(part / "ideal") == sequence_digest(full / "ideal")
    assert not (part / "incomplete.json").exists()


def test_synth_views_killed_resumes_identically(tmp_path):
    import trimesh
    box = tmp_path / "box.ply"
    trimesh.creation.box(extents=(0.12, 0.08, 0.10)).export(box)
    args = ["synth", "views", "--model", box, "--sensor", "kinect_v1", "--subdivisions", "1", "--roll-angles=0,30",
            "--distance", "0.8", "--clutter", "2", "--seed", "3", "--width", "160", "--height", "120"]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], marker_at_least(part, 3))
    assert_incomplete_views = json.loads((part / "incomplete.json").read_text())
    assert assert_incomplete_views["unit"] == "views" and assert_incomplete_views["resumable"]
    r = run_ok([*args, "--out", part])
    assert "kept" in r.stdout, r.stdout
    run_ok([*args, "--out", full])
    a, b = json.loads((part / "labels.json").read_text()), json.loads((full / "labels.json").read_text())
    assert _strip_volatile(a["views"]) == _strip_volatile(b["views"])
    from data_tools.sequence import read_depth_png
    for v in b["views"]:
        f = v["depth"]
        np.testing.assert_array_equal(read_depth_png(part / f, 1.0), read_depth_png(full / f, 1.0))


# ----------------------------------------------------------------------------------- sensor lab

def test_sensor_simulate_killed_resumes_identically(room, tmp_path):
    args = ["sensor", "simulate", room, "--effects", "axial_noise,projector_shadow,disparity_quantization",
            "--seed", "4"]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], marker_at_least(part, 3))
    assert_reported_incomplete(part)
    r = run_ok([*args, "--out", part])
    assert "resumed:" in r.stderr + r.stdout and "frames already simulated" in r.stderr + r.stdout
    run_ok([*args, "--out", full])
    assert sequence_digest(part) == sequence_digest(full)


FIT = ["--fit-option", "max_evaluations=14", "--fit-option", "max_frames=2", "--fit-option",
       "max_pixels_per_frame=1500"]


def test_sensor_fit_killed_resumes_identically(room, tmp_path):
    args = ["sensor", "fit", room, "--effects", "axial_noise,disparity_quantization", *FIT]
    part, full = tmp_path / "part.json", tmp_path / "full.json"
    journal = tmp_path / "part.json.journal.jsonl"
    kill_part_way([*args, "--out", part], lines_at_least(journal, 4))
    assert not part.exists()
    r = run_ok([*args, "--out", part])
    assert "resuming:" in r.stderr and "objective evaluations already done" in r.stderr, r.stderr
    assert not journal.exists()
    run_ok([*args, "--out", full])
    a, b = json.loads(part.read_text()), json.loads(full.read_text())
    assert a["fit"]["params"] == b["fit"]["params"] and a["fit"]["gap"] == b["fit"]["gap"]
    assert a["effects"] == b["effects"]


def test_sensor_diagnose_killed_resumes_identically(room, tmp_path):
    args = ["sensor", "diagnose", room, "--effects", "axial_noise", "--candidates",
            "projector_shadow,disparity_quantization", "--top", "1", "--report-frames", "0", *FIT]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], lines_at_least(part / "diagnose_journal.jsonl", 8))
    assert_reported_incomplete(part)
    r = run_ok([*args, "--out", part])
    assert "resuming:" in r.stderr, r.stderr
    run_ok([*args, "--out", full])
    a = json.loads((part / "diagnosis.json").read_text())
    b = json.loads((full / "diagnosis.json").read_text())
    assert [(c["effect"], c["gain"], c["params"]) for c in a["ranking"]] == \
           [(c["effect"], c["gain"], c["params"]) for c in b["ranking"]]
    assert a["gap"] == b["gap"]


# ----------------------------------------------------------------------------------- slam

def test_slam_run_killed_resumes_identically(room, tmp_path):
    args = ["slam", "run", room, "--checkpoint-every", "4"]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], marker_at_least(part, 8))
    assert (part / "checkpoint.json").is_file()
    r = subprocess.run(_cmd(["show", part], False), capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 1 and "incomplete:" in r.stderr, r.stderr
    r = run_ok([*args, "--out", part])
    run_ok([*args, "--out", full])
    # the same bytes: the run is deterministic (fixed-order ICP sums, canonical mesh order)
    assert (part / "trajectory.txt").read_bytes() == (full / "trajectory.txt").read_bytes()
    assert (part / "mesh.ply").read_bytes() == (full / "mesh.ply").read_bytes()


def test_batch_killed_resumes_identically(room, tmp_path):
    args = ["batch", room, room / "ideal", "--backends", "icp", "--workers", "1", "--threads-per-job", "1"]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], marker_at_least(part, 1))
    assert_reported_incomplete(part)
    r = run_ok([*args, "--out", part])
    assert "resumed: 1 of 2 runs had finished before" in r.stdout, r.stdout
    run_ok([*args, "--out", full])
    a = json.loads((part / "results.json").read_text())["results"]
    b = json.loads((full / "results.json").read_text())["results"]
    # one thread per job: Open3D's reductions are then deterministic, so the resumed report equals the
    # uninterrupted one number for number (with 2 threads they differed by up to 3e-3 relative)
    assert _strip_volatile(a) == _strip_volatile(b)


# ----------------------------------------------------------------------------------- make-reference

def test_make_reference_killed_says_it_starts_again(room, tmp_path):
    """make-reference does not continue (the TSDF is not checkpointed): its marker says so and a
    re-run starts again to the same reference."""
    args = ["data", "make-reference", room, "--voxel", "0.01"]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], lambda: (part / "incomplete.json").is_file())
    marker = json.loads((part / "incomplete.json").read_text())
    assert marker["resumable"] is False and "starts again" in marker["note"]
    run_ok([*args, "--out", part])
    run_ok([*args, "--out", full])
    assert not (part / "incomplete.json").exists()
    ma = json.loads((part / "scene.json").read_text())
    mb = json.loads((full / "scene.json").read_text())
    assert _strip_volatile(ma) == _strip_volatile(mb)
    a = sorted((part / "meshes").iterdir())
    b = sorted((full / "meshes").iterdir())
    assert [p.name for p in a] == [p.name for p in b]
    assert all(x.read_bytes() == y.read_bytes() for x, y in zip(a, b))


# ----------------------------------------------------------------------------- recog

@pytest.mark.slow  # ~40 s; the shared loop's exact resume is also in test_training and test_synda_train
def test_recog_train_killed_resumes_identically(tmp_path):
    """Killed while training (after a checkpoint): the re-run continues from the checkpoint and
    gives the same database as an uninterrupted run."""
    import trimesh
    trimesh.creation.box(extents=(0.10, 0.06, 0.05)).export(tmp_path / "box.ply")
    trimesh.creation.cylinder(radius=0.03, height=0.09).export(tmp_path / "cyl.ply")
    args = ["recog", "train", "--objects", f"{tmp_path / 'box.ply'},{tmp_path / 'cyl.ply'}", "--variant", "gaussian",
            "--subdivisions", "0", "--iterations", "120", "--batch", "8", "--checkpoint-every", "20",
            "--workers", "1"]
    part, full = tmp_path / "part", tmp_path / "full"
    kill_part_way([*args, "--out", part], lambda: (part / "checkpoint.pt").is_file())
    assert_reported_incomplete_marker = json.loads((part / "incomplete.json").read_text())
    assert assert_reported_incomplete_marker["command"] == "realgap recog train"
    r = run_ok([*args, "--out", part])
    assert "resumed: 2 chunks" in r.stderr and "resuming training at step" in r.stderr, r.stderr
    run_ok([*args, "--out", full])
    a, b = np.load(part / "database.npz"), np.load(full / "database.npz")
    np.testing.assert_array_equal(a["descriptors"], b["descriptors"])
    assert not (part / "checkpoint.pt").exists() and not (part / "incomplete.json").exists()
