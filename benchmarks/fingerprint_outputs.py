"""Fingerprints of the project's outputs for a fixed seed: run before and after a refactor and
compare, to show that behaviour did not change (simulated frames, fitted models, lab gaps,
diagnosis rankings and trajectories bit-identical).

    .venv/bin/python benchmarks/fingerprint_outputs.py --out /tmp/before.json
    ... change the code ...
    .venv/bin/python benchmarks/fingerprint_outputs.py --out /tmp/after.json --compare /tmp/before.json

Every step runs the ``realgap`` command line in a subprocess (what a user runs), and hashes the
array content of the outputs (decoded PNG pixels, trajectory numbers) and the result numbers of
the JSON files (timings and paths dropped). Takes ~2-3 minutes on 2 cores.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("REALGAP_SHARED_DATA", REPO.parent / "shared" / "data"))
VOLATILE = ("header", "seconds", "time", "timing", "_s", "path", "sequence", "created", "version", "host", "command",
            "out", "dir", "file", "inputs", "mesh", "model", "slam_run", "source", "description")


def _old_eval_cli() -> bool:
    """Before the one-dialect change, ``eval ate`` wrote its JSON with ``--json OUT`` (now ``--out DIR``)."""
    r = subprocess.run([sys.executable, "-m", "app", "eval", "ate", "--help"], cwd=REPO, capture_output=True, text=True)
    return "--out-dir" in r.stdout


_OLD_EVAL = None


def _realgap(*args: str, one_thread: bool = False) -> None:
    """Run ``realgap ARGS``; ``one_thread`` limits Open3D to one thread (its parallel float
    reductions differ in the last bits from run to run otherwise, see slam.batch)."""
    pre = "import open3d; open3d.utility.set_max_threads(1); " if one_thread else ""
    code = f"import sys; {pre}from app.cli import main; sys.exit(main(sys.argv[1:]))"
    r = subprocess.run([sys.executable, "-c", code, *args], cwd=REPO, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"realgap {' '.join(args)} failed ({r.returncode}):\n{r.stderr[-3000:]}")


def _hash_bytes(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()[:16]


def _hash_pngs(folder: Path) -> str:
    import cv2
    h = hashlib.sha256()
    for f in sorted(folder.rglob("*.png")):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        h.update(f.relative_to(folder).as_posix().encode())
        h.update(np.ascontiguousarray(img).tobytes())
    return h.hexdigest()[:16]


def _hash_npys(folder: Path) -> str:
    h = hashlib.sha256()
    for f in sorted(folder.rglob("*.npy")):
        h.update(f.relative_to(folder).as_posix().encode())
        h.update(np.ascontiguousarray(np.load(f)).tobytes())
    return h.hexdigest()[:16]


def _trajectory(path: Path) -> str:
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return _hash_bytes(np.asarray(rows, dtype=np.float64).tobytes())


def _numbers(x, key: str = ""):
    """The result numbers of a JSON document (volatile keys such as timings and paths dropped)."""
    if isinstance(x, dict):
        return {k: _numbers(v, k) for k, v in sorted(x.items())
                if not any(t in k.lower() for t in VOLATILE)}
    if isinstance(x, list):
        return [_numbers(v, key) for v in x]
    if isinstance(x, float):
        return repr(x)
    return x


def _json(path: Path, pick=None) -> str:
    d = json.loads(path.read_text())
    if pick is not None:
        d = pick(d)
    return _hash_bytes(json.dumps(_numbers(d), sort_keys=True).encode())


def fingerprint(work: Path) -> dict:
    fp = {}
    # 1. simulated sequences, each preset, physical pipeline (the default) and direct model
    for preset, frames in (("kinect_v1", 6), ("structure", 3), ("realsense_d435", 3), ("kinect_v2", 3)):
        out = work / f"seq_{preset}"
        _realgap("synth", "sequence", "--scene", "room", "--frames", str(frames), "--sensor", preset,
                 "--out", str(out))
        fp[f"synth sequence {preset} physical"] = _hash_pngs(out / "depth")
    out = work / "seq_direct"
    _realgap("synth", "sequence", "--scene", "room", "--frames", "4", "--sensor", "kinect_v1", "--effects", "direct",
             "--out", str(out))
    fp["synth sequence kinect_v1 direct"] = _hash_pngs(out / "depth")
    fp["synth sequence ideal"] = _hash_pngs(out / "ideal" / "depth")
    # moving camera: rolling shutter + motion blur (fast walk)
    out = work / "seq_motion"
    _realgap("synth", "sequence", "--scene", "room", "--frames", "3", "--fps", "5", "--sensor", "kinect_v1",
             "--out", str(out))
    fp["synth sequence kinect_v1 moving"] = _hash_pngs(out / "depth")

    # 2. the sensor lab on the simulated kinect_v1 sequence
    seq = work / "seq_kinect_v1"
    lab = work / "lab"
    _realgap("sensor", "compare", str(seq), "--effects", "axial_noise", "--spread-frames", "3", "--out", str(lab))
    fp["sensor compare gap+breakdowns"] = _json(lab / "metrics.json")
    model = work / "model.json"
    _realgap("sensor", "fit", str(seq), "--effects", "axial_noise,range_limits,edge_fattening", "--spread-frames", "3",
             "--fit-option", "max_evaluations=24", "--out", str(model))
    fp["sensor fit model"] = _json(model, lambda d: {k: v for k, v in d.items() if k != "fit"})
    fp["sensor fit record"] = _json(model, lambda d: {k: v for k, v in d.get("fit", {}).items()
                                                      if k in ("gap", "gap_before", "params", "evaluations")})
    model2 = work / "model_lens_quant.json"
    _realgap("sensor", "fit", str(seq), "--effects", "axial_noise,lens_distortion,disparity_quantization",
             "--spread-frames", "2", "--fit-option", "max_evaluations=30", "--out", str(model2))
    fp["sensor fit lens+quantization record"] = _json(model2, lambda d: {k: v for k, v in d.get("fit", {}).items()
                                                                         if k in ("gap", "gap_before", "params",
                                                                                  "evaluations")})
    simseq2 = work / "sim_lens_quant"
    _realgap("sensor", "simulate", str(seq), "--model", str(model2), "--spread-frames", "2", "--out", str(simseq2))
    fp["sensor simulate lens+quantization"] = _hash_pngs(simseq2 / "depth")
    diag = work / "diag"
    _realgap("sensor", "diagnose", str(seq), "--effects", "axial_noise", "--spread-frames", "2",
             "--candidates", "edge_fattening,projector_shadow,lens_distortion",
             "--fit-option", "max_evaluations=10", "--diagnose-option", "candidate_evaluations=8",
             "--top", "1", "--report-frames", "1", "--out", str(diag))
    fp["sensor diagnose"] = _json(diag / "diagnosis.json")
    simseq = work / "sim"
    _realgap("sensor", "simulate", str(seq), "--model", str(model), "--spread-frames", "3", "--out", str(simseq))
    fp["sensor simulate"] = _hash_pngs(simseq / "depth")

    # 3. slam on the simulated sequence, and the metrics
    run = work / "slam"
    _realgap("slam", "run", str(seq), "--backend", "icp", "--out", str(run), one_thread=True)
    fp["slam run icp trajectory"] = _trajectory(run / "trajectory.txt")
    run2 = work / "slam_odo"
    _realgap("slam", "run", str(seq), "--backend", "rgbd_odometry", "--out", str(run2), one_thread=True)
    fp["slam run rgbd_odometry trajectory"] = _trajectory(run2 / "trajectory.txt")
    evo = SHARED / "evo_trajectories"
    global _OLD_EVAL
    _OLD_EVAL = _old_eval_cli()
    if evo.is_dir():
        ate = work / "ate" / "ate.json"
        _realgap("eval", "ate", str(evo / "freiburg1_xyz-groundtruth.txt"), str(evo / "freiburg1_xyz-rgbdslam.txt"),
                 *(["--json", str(ate)] if _OLD_EVAL else ["--out", str(ate.parent)]))
        fp["eval ate"] = _json(ate)

    # 4. object-centred views for recognition
    obj = SHARED / "tless_cad" / "obj_01.ply"
    if obj.is_file():
        views = work / "views"
        _realgap("synth", "views", "--model", str(obj), "--scale", "0.001", "--sensor", "kinect_v1", "--clutter", "2",
                 "--limit", "4", "--out", str(views))
        fp["synth views"] = _hash_pngs(views)
        fp["synth views labels"] = _json(views / "labels.json")
    return fp


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="write the fingerprints here (JSON)")
    ap.add_argument("--compare", help="an earlier fingerprint file: print what differs, exit 1 if anything")
    ap.add_argument("--keep", help="keep the outputs in this folder (default: a temporary one)")
    a = ap.parse_args()
    if a.keep:
        work = Path(a.keep)
        work.mkdir(parents=True, exist_ok=True)
        fp = fingerprint(work)
    else:
        with tempfile.TemporaryDirectory() as d:
            fp = fingerprint(Path(d))
    Path(a.out).write_text(json.dumps(fp, indent=2) + "\n")
    for k, v in fp.items():
        print(f"{k:40s} {v}")
    if a.compare:
        old = json.loads(Path(a.compare).read_text())
        diff = [k for k in sorted(set(old) | set(fp)) if old.get(k) != fp.get(k)]
        print(f"\n{len(fp) - len(diff)} of {len(set(old) | set(fp))} fingerprints identical")
        for k in diff:
            print(f"DIFFERS: {k}: {old.get(k)} -> {fp.get(k)}")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
