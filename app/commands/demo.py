"""``realgap demo``: the main demo on embedded default data (no downloads).

Pipeline: generate the built-in furnished room as an ideal RGB-D sequence (walk-through
trajectory) -> simulate a Kinect v1 on the same poses with the full physical structured-light
pipeline -> register the simulated sequence with frame-to-model ICP + TSDF -> evaluate the
estimated trajectory against the ground truth (ATE, SE(3) alignment). Re-running resumes.
"""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "demo"
HELP = "run the main demo on embedded default data (simulate -> register -> evaluate)"


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands import RESUMES, add_shared
    add_shared(parser, "--out", "the demo folder (default demo_out)", default="demo_out")
    parser.add_argument("--frames", type=int, default=60, help="number of frames to generate (default 60)")
    parser.add_argument("--sensor", default="kinect_v1", help="sensor preset (default kinect_v1)")
    add_shared(parser, "--seed", "(default 0)", default=0)
    add_shared(parser, "--no-progress")
    parser.set_defaults(func=run, on_interrupt=RESUMES)


def run(args) -> int:
    from app.pipelines import run_demo
    s = run_demo(args.out, args.frames, args.sensor, args.seed)
    print(f"\nATE rmse of ICP on the simulated {args.sensor} sequence: {s['ate_rmse_m'] * 100:.2f} cm "
          f"over {s['ate_pairs']} frames, {s['frames_failed']} failed ({s['seconds']} s)")
    print(f"outputs in {Path(args.out).resolve()}: room_ideal/ (ideal RGB-D), {Path(s['simulated_sequence']).name}/ "
          f"(simulated), slam_icp/ (trajectory.txt, mesh.ply, stats.json), ate/, summary.json")
    return 0
