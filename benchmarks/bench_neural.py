"""Benchmark: inference speed of the neural memory (thesis 4.4: "register 5 views + localise + recall 5 +
hallucinate 5 in < 1 s on a Titan X"), for the shipped 2D and 3D weights, on this machine.

    .venv/bin/python benchmarks/bench_neural.py [--repeats 10] [--threads N] [--device cpu|cuda]

For each model: the median time of (encode + localise + register 5 observations, recall the 5 observed
views, hallucinate the memory and decode 5 unseen views), batch 1. The baseline measured in the same
run is the classic memory's equivalent: Open3D TSDF integration of 5 VGA RGB-D frames at their poses
+ ray casting 5 views (``slam.tsdf``) - the ratio says how the neural memory's cost compares to
what ``icp`` runs do per view. Inputs are synthetic (fixed seeds), so no data is needed.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    import torch

    from slam.neural.io import load_model
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    weights = Path(__file__).resolve().parents[1] / "slam" / "neural" / "weights"
    rng = np.random.default_rng(0)
    rows = []
    for name in ("front_2d", "planar_3d"):
        if not (weights / name / "neural.json").is_file():
            print(f"{name}: no shipped weights, skipped")
            continue
        model, cfg, _ = load_model(weights / name)
        model = model.to(dev)
        mc = model.cfg
        q = mc.view
        vm = torch.ones(q, q, device=dev)
        if mc.input == "image":
            H, W = mc.image_size
            obs = torch.from_numpy(rng.uniform(-1, 1, (1, 5, mc.channels, H, W)).astype(np.float32)).to(dev)
            cells = torch.from_numpy(rng.integers(-1, q * q, (1, 5, mc.rotations, H * W))).to(dev)
        else:
            obs = torch.from_numpy(rng.uniform(-1, 1, (1, 5, mc.channels, q, q)).astype(np.float32)).to(dev)
            cells = None
        req = torch.tensor([[i, -i, i % mc.rotations] for i in range(5)], device=dev)

        def run(score="sum"):
            with torch.no_grad():
                out = model(obs, vm, None, cells=cells, score=score)
                model.recall(out["psi"].expand(5, -1, -1, -1), req, vm)
                filled = model.hallucinate(out["psi"], out["occ"])
                model.recall(filled.expand(5, -1, -1, -1), req, vm)
            if dev.type == "cuda":
                torch.cuda.synchronize()
        rows.append((name, _median_time(run, args.repeats)))
        if mc.input == "image":      # the neural backend's default score (slam.backends.neural.NeuralConfig.score)
            rows.append((name + " (overlap score)", _median_time(lambda: run("overlap"), args.repeats)))

    # baseline: TSDF integrate 5 VGA frames + ray cast 5 views
    from data_tools.camera import Intrinsics
    from data_tools.geometry import look_at
    from slam.tsdf import TSDFConfig, TSDFVolume
    intr = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5)
    depth = np.full((480, 640), 2.0, np.float32) + rng.uniform(0, 0.01, (480, 640)).astype(np.float32)
    rgb = rng.integers(0, 255, (480, 640, 3)).astype(np.uint8)
    poses = [look_at(np.array([0.05 * i, 0.0, 0.0]), np.array([0.05 * i, 0.0, 2.0]), up=(0, -1, 0)) for i in range(5)]

    def tsdf():
        v = TSDFVolume(TSDFConfig())
        for P in poses:
            v.integrate(depth, rgb, intr, P)
        for P in poses:
            v.raycast(intr, P, with_color=True, with_normal=False)
    base = _median_time(tsdf, max(3, args.repeats // 3))
    print(f"device {args.device}, torch threads {torch.get_num_threads()}")
    print(f"{'what':<68} {'seconds':>8} {'x baseline':>10}")
    print(f"{'baseline: TSDF integrate 5 VGA frames + ray cast 5':<68} {base:8.3f} {1.0:10.2f}")
    for name, t in rows:
        print(f"{name + ': register 5 + recall 5 + hallucinate 5':<68} {t:8.3f} {t / base:10.2f}")
    print("thesis (Titan X GPU): < 1 s for register 5 + localise + recall 5 + hallucinate 5")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
