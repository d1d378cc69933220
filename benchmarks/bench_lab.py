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
  compare_cached : the same comparison with a warm CompareCache (what a fit pays per frame)
  fit_eval  : one fit objective evaluation (direct model, FitConfig defaults, the sequence's
              compare cache warm), per frame
  fit_eval_nocache : the same without the compare cache
and each as a ratio to ``raycast`` (plus compare/compare_cached and fit_eval_nocache/fit_eval:
the speed-up of the cache).

Diagnose timing (issue #4 target: a 24-frame VGA sequence diagnosed in < 2 min on 2 cores)::

    .venv/bin/python benchmarks/bench_lab.py --diagnose [--hidden projector_shadow] [--frames 24]
        [--size 640x480] [--scene studio]

generates a sequence with the independent hidden-effect generator (tests/hidden_effects.py:
base disparity noise + range limits + one hidden effect), runs ``diagnose()`` with the default
settings from ``axial_noise,range_limits`` and prints the wall time, the CPU time of the
process (all threads), both load averages (before/after), the evaluation count, the top of the
ranking, the evaluation-set gain, and the cost of one objective evaluation with and without the
compare cache measured in the same run.
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


def _cpu_timed(fn, repeats: int) -> tuple[float, float]:
    """(best wall seconds, CPU seconds of that run) over ``repeats`` calls of fn."""
    best = (float("inf"), float("nan"))
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        w = time.perf_counter() - t
        if w < best[0]:
            best = (w, time.process_time() - c)
    return best


def bench_diagnose(args) -> int:
    """The VGA diagnose timing (module docstring)."""
    from synth.lab.diagnose import diagnose
    from synth.lab.fit import FitConfig, Objective, spread
    from synth.lab.measured import MeasuredSequence
    from tests import hidden_effects as he

    w, h = (int(x) for x in args.size.lower().split("x"))
    hidden = None if args.hidden == "none" else args.hidden
    with tempfile.TemporaryDirectory() as d:
        seq = Path(d) / "seq"
        t = time.perf_counter()
        truth = he.generate(seq, hidden, seed=args.seed, n_frames=args.frames, width=w, height=h, scene=args.scene)
        gen_s = time.perf_counter() - t
        ms = MeasuredSequence.load(seq)
        cfg = ms.default_config(["axial_noise", "range_limits"])
        la0 = os.getloadavg()
        t, c = time.perf_counter(), time.process_time()
        diag = diagnose(ms, cfg)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        la1 = os.getloadavg()
        # one objective evaluation (the fit's unit of cost) with and without the compare cache
        fc = FitConfig()
        frames = spread(len(ms), fc.max_frames)
        obj = Objective(ms, frames, fc.compare_config(int(fc.max_pixels_per_frame)), fc.seed)
        cold = Objective(ms, frames, fc.compare_config(int(fc.max_pixels_per_frame)), fc.seed)
        cold.cache = None
        obj(cfg)
        e_cached = _cpu_timed(lambda: obj(cfg), args.repeats)
        e_cold = _cpu_timed(lambda: cold(cfg), args.repeats)
    print(f"data: hidden-effect generator, {hidden or 'no'} hidden effect, scene {args.scene}, {len(ms)} frames of "
          f"{w}x{h} (generated in {gen_s:.1f} s); truth {truth}")
    print(f"load average before {la0[0]:.2f} {la0[1]:.2f} {la0[2]:.2f}, after {la1[0]:.2f} {la1[1]:.2f} {la1[2]:.2f}")
    print(f"diagnose: {wall:.1f} s wall, {cpu:.1f} s CPU (all threads), {diag.evaluations} gap evaluations, "
          f"{len(diag.ranking)} candidates tried, {len(diag.skipped)} skipped; target 120 s wall "
          f"(wall/target {wall / 120:.2f}); time_capped {diag.time_capped}")
    for c in diag.ranking[:3]:
        print(f"  {c.effect:24s} gain {c.gain:6.3f}  {c.evaluations:3d} evaluations  {c.seconds:5.1f} s")
    print(f"evaluation-set gain of the best: {diag.eval_gain}")
    print(f"one objective evaluation ({len(frames)} frames, {fc.max_pixels_per_frame} px/frame): "
          f"{1000 * e_cached[0]:.0f} ms wall / {1000 * e_cached[1]:.0f} ms CPU with the compare cache, "
          f"{1000 * e_cold[0]:.0f} ms / {1000 * e_cold[1]:.0f} ms without (x{e_cold[0] / e_cached[0]:.2f} wall, "
          f"x{e_cold[1] / e_cached[1]:.2f} CPU)")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", choices=("tum", "chess", "synthetic"), default="tum")
    ap.add_argument("--frames", type=int, default=None, help="frames (default 10; --diagnose: 24)")
    ap.add_argument("--fuse-frames", type=int, default=100, help="chess: frames converted and fused")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--diagnose", action="store_true", help="time diagnose() on a generated VGA sequence instead")
    ap.add_argument("--hidden", default="projector_shadow", help="--diagnose: the hidden effect (or 'none')")
    ap.add_argument("--size", default="640x480", help="--diagnose: image size WxH")
    ap.add_argument("--scene", default="studio", choices=("studio", "room"), help="--diagnose: generator scene")
    ap.add_argument("--seed", type=int, default=11, help="--diagnose: generator seed")
    args = ap.parse_args(argv)
    if args.diagnose:
        args.frames = args.frames or 24
        return bench_diagnose(args)
    args.frames = args.frames or 10

    from synth.lab.compare import CompareCache, CompareConfig, compare
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
        cache = CompareCache()
        compare(obs, CompareConfig(), cache=cache)
        rows["compare_cached"] = _timed(lambda: compare(obs, CompareConfig(), cache=cache), args.repeats) / n
        rows["report (per run)"] = _timed(lambda: run_lab(obs, tmp / "lab", effects=cfg_dir.names(),
                                                          report_frames=2), 1)
        fc = FitConfig()
        frames = spread(n, fc.max_frames)
        obj = Objective(ms, frames, fc.compare_config(int(fc.max_pixels_per_frame)), fc.seed)
        obj(cfg_dir)
        rows["fit_eval"] = _timed(lambda: obj(cfg_dir), args.repeats) / len(frames)
        obj.cache = None
        rows["fit_eval_nocache"] = _timed(lambda: obj(cfg_dir), args.repeats) / len(frames)
    base = rows["raycast"]
    print(f"data: {args.data}, {n} frames of {ms.intrinsics.width}x{ms.intrinsics.height}")
    print(f"{'stage':18s} {'ms':>10s} {'x raycast':>10s}")
    for k, v in rows.items():
        print(f"{k:18s} {1000 * v:10.1f} {v / base:10.2f}")
    print(f"compare cache speed-up: compare x{rows['compare'] / rows['compare_cached']:.2f}, "
          f"fit evaluation x{rows['fit_eval_nocache'] / rows['fit_eval']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
