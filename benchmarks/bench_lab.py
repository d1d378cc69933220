"""Benchmark: the sensor lab on a measured sequence, each stage against the ideal ray cast
measured in the same run.

    .venv/bin/python benchmarks/bench_lab.py [--data tum|chess|synthetic] [--frames 10] [--repeats 3]

Data: ``tum`` = the 10 TUM fr1/xyz frames (shared/data) with a reference fused from them,
``chess`` = 7-Scenes chess (the first --fuse-frames frames converted and fused), ``synthetic`` =
the built-in room seen by a simulated Kinect v1 (no shared data needed).

Prints per frame (minimum over repeats of the per-frame mean; the machine may be shared, the
load average is printed):
  fuse      : reference fusion (read depth + TSDF integrate), per fused frame
  raycast   : IdealRenderer.render of the reference at a ground-truth pose (the baseline)
  sim_axial : simulate with axial_noise (cached render, as the lab does)
  sim_direct: simulate with the preset's direct model (cached render)
  compare   : synth.lab.compare per frame (default preset, 20k pixels/frame)
  report    : run_lab's report (figures + HTML), per run (not per frame)
  fit_eval  : one fit objective evaluation (direct model, FitConfig defaults), per frame
and each as a ratio to ``raycast``.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SHARED = Path(os.environ.get("REALGAP_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def _timed(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _prepare(kind: str, tmp: Path, fuse_frames: int) -> tuple[Path, float, int]:
    """A measured sequence with scene.json; returns (folder, fusion seconds, frames fused)."""
    from slam.reference import NAMED_CAMERAS, ReferenceConfig, make_reference
    if kind == "synthetic":
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from tests.test_sensor_cli import make_measured_sequence
        seq = make_measured_sequence(tmp, frames=10, width=640, height=480)
        return seq, float("nan"), 0
    if kind == "tum":
        src, cam = SHARED / "tum_fr1_xyz_10", NAMED_CAMERAS["tum_fr1"]
    else:
        from data_tools.sevenscenes import convert_7scenes
        raw = SHARED / "sevenscenes_chess_1000"
        part = tmp / "chess_part"
        part.mkdir()
        for k in range(fuse_frames):
            for ext in ("color.jpg", "depth.png", "pose.txt"):
                shutil.copy(raw / f"frame-{k:06d}.{ext}", part)
        shutil.copy(raw / "camera-intrinsics.txt", part)
        src, cam = tmp / "chess", None
        convert_7scenes(part, src, progress=False)
    if not src.exists():
        raise SystemExit(f"{src} not found: use --data synthetic")
    res = make_reference(src, tmp / "seq", ReferenceConfig(), camera=cam)
    return tmp / "seq", res.seconds, res.frames_fused


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", choices=("tum", "chess", "synthetic"), default="tum")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--fuse-frames", type=int, default=100, help="chess: frames converted and fused")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)

    from synth.lab.compare import CompareConfig, compare
    from synth.lab.fit import FitConfig, Objective, spread
    from synth.lab.measured import MeasuredSequence
    from synth.lab.report import run_lab
    from synth.render import IdealRenderer

    print(f"load average: {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        seq, fuse_s, n_fused = _prepare(args.data, tmp, args.fuse_frames)
        ms = MeasuredSequence.load(seq, max_frames=args.frames)
        n = len(ms)
        rows = {}
        if n_fused:
            rows["fuse"] = fuse_s / n_fused
        ren = IdealRenderer(ms.scene)
        ren.render(ms.poses[0], ms.intrinsics, with_rgb=False)
        rows["raycast"] = _timed(lambda: [ren.render(ms.poses[k], ms.intrinsics, with_rgb=False)
                                          for k in range(n)], args.repeats) / n
        for k in range(n):  # fill the lab's render cache
            ms.render(k)
        cfg_ax = ms.default_config(["axial_noise"])
        cfg_dir = ms.default_config("direct")
        sim_ax = ms.simulator(cfg_ax)
        sim_dir = ms.simulator(cfg_dir)
        rows["sim_axial"] = _timed(lambda: ms.simulate(cfg_ax, simulator=sim_ax), args.repeats) / n
        rows["sim_direct"] = _timed(lambda: ms.simulate(cfg_dir, simulator=sim_dir), args.repeats) / n
        obs = ms.observations(ms.simulate(cfg_dir, simulator=sim_dir))
        rows["compare"] = _timed(lambda: compare(obs, CompareConfig()), args.repeats) / n
        rows["report (per run)"] = _timed(lambda: run_lab(obs, tmp / "lab", effects=cfg_dir.names(),
                                                          report_frames=2), 1)
        fc = FitConfig()
        frames = spread(n, fc.max_frames)
        obj = Objective(ms, frames, fc.compare_config(int(fc.max_pixels_per_frame)), fc.seed)
        rows["fit_eval"] = _timed(lambda: obj(cfg_dir), args.repeats) / len(frames)
    base = rows["raycast"]
    print(f"data: {args.data}, {n} frames of {ms.intrinsics.width}x{ms.intrinsics.height}")
    print(f"{'stage':18s} {'ms':>10s} {'x raycast':>10s}")
    for k, v in rows.items():
        print(f"{k:18s} {1000 * v:10.1f} {v / base:10.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
