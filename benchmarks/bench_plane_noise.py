"""Benchmark: the plane-fit noise against distance of a fitted model on held-out frames of a planar
reference (issue #43 item 3: within 10 % of the measured in every 0.25 m bin from 0.5 to 3 m),
each ratio shown beside the measurement's own sampling spread.

    .venv/bin/python benchmarks/bench_plane_noise.py PLANE_REF [--effects axial_noise,range_limits]
        [--search-frames N] [--search-pixels N] [--eval-frames N] [--split alternate|halves|kfold] [--folds K] [--curve-weight W]
        [--min-frames 10] [--boot 200] [--block 1] [--json OUT] [--no-rounding] [--median-only]

``PLANE_REF``: a sequence made by ``realgap data make-reference --plane`` (poses, masks and plane).
The even frames are fitted (``fit_model``, :class:`~synth.lab.fit.FitConfig` with the noise-curve
term; ``--search-frames`` / ``--search-pixels`` / ``--eval-frames`` set its ``max_frames`` /
``max_pixels_per_frame`` / ``eval_frames``; ``--curve-weight`` its ``noise_curve_weight``), the odd frames are held out (``--split halves``: the
first half of the sequence fitted, the second held out; ``--split kfold``: ``--folds`` contiguous blocks,
each simulated by a model fitted on the other blocks alone, so every frame is held out once - for a short
sequence, where half of it is too few frames to judge a bin): per bin, the measured robust std of depth - plane
(:func:`synth.lab.calibration.noise_curve`, every target pixel) against the simulated one, the mean
over ``--seeds`` simulation seeds.

Columns: ``measured CI`` and ``ratio CI``: 95 % frame-level bootstrap intervals
(:func:`synth.lab.calibration.curve_uncertainty`: the held-out frames resampled with replacement,
in runs of ``--block`` consecutive frames);
``fit/held``: the measured std of the fitted half over that of the held-out half (how much the
measured curve itself moves between two disjoint frame sets; NaN for ``kfold``, where every frame is both); ``frames``: held-out frames with
target pixels in the bin. Verdict per bin: ``too few frames`` (fewer than ``--min-frames``: the
bin is listed, not judged), ``within`` (|ratio - 1| <= 10 %), ``OFF`` (the whole ratio CI outside
0.9-1.1: off by more than the sampling spread allows), ``unresolved`` (outside 10 % but its CI
reaches into 0.9-1.1). ``--no-rounding``: without the simulation's rounding to the measured depth's
storage quantum (the behaviour before it, for comparison). ``--median-only``: each (frame, bin)
group's residuals about their median alone, not about their local plane
(:data:`synth.lab.calibration.LOCAL_PLANE` False, in the fit's objective and in the table: the
behaviour before it, for comparison).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def verdict(ratio: float, ci: tuple[float, float], frames: int, min_frames: int, tol: float = 0.10) -> str:
    """The per-bin verdict of the module docstring."""
    if frames < min_frames:
        return "too few frames"
    if not np.isfinite(ratio):
        return "OFF"
    if abs(ratio - 1.0) <= tol:
        return "within"
    lo, hi = ci
    if np.isfinite(lo) and np.isfinite(hi) and (hi < 1.0 - tol or lo > 1.0 + tol):
        return "OFF"
    return "unresolved"


def chunked_groups(seq, positions, config, seeds: int, chunk: int = 40, first: int = 0):
    """(measured, [simulated per seed]) :func:`synth.lab.calibration.curve_groups` (every target pixel) of
    the frames at ``positions`` (among the frames with a pose), ``chunk`` frames at a time (each chunk
    loaded afresh: the cached renders and draws of a 500-frame sequence do not fit in memory);
    ``config`` None: the measured side alone. Group positions count over ``positions`` from ``first``."""
    import synth.lab.calibration as cal
    from synth.lab import MeasuredSequence
    pos = np.asarray(positions, dtype=int)
    m_all, s_all = None, None
    for a in range(0, len(pos), chunk):
        ms = MeasuredSequence.load(seq, frames=pos[a:a + chunk])
        sims = [ms.simulate(config, s) for s in range(seeds)] if config is not None else []
        obs = ms.observations(sims[0] if sims else [ms.measured_depth(k) for k in range(len(ms))])
        m = cal.curve_groups(obs, "measured", None, 0)
        ss = [cal.curve_groups(ms.observations(x), "simulated", None, 0) for x in sims]
        shift = [[[(p + a + first, g.astype(np.float32)) for p, g in b] for b in gs] for gs in [m, *ss]]
        if m_all is None:
            m_all, s_all = shift[0], shift[1:]
        else:
            for b in range(len(m_all)):
                m_all[b] += shift[0][b]
                for j in range(len(s_all)):
                    s_all[j][b] += shift[1 + j][b]
        del ms, obs, sims
    return m_all, s_all


def merge_groups(parts):
    """Per-bin concatenation of several :func:`chunked_groups` results (disjoint frame positions)."""
    out = [list(b) for b in parts[0]]
    for p in parts[1:]:
        for b in range(len(out)):
            out[b] += p[b]
    return out


def splits(n: int, split: str, folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(fitted positions, held-out positions) per fit of ``n`` frames: ``alternate`` (even / odd),
    ``halves`` (first / second half) or ``kfold`` (``folds`` contiguous blocks, each held out once
    while the others are fitted: every frame is held out from the model that simulates it)."""
    idx = np.arange(n)
    if split == "halves":
        return [(idx[:n // 2], idx[n // 2:])]
    if split == "alternate":
        return [(idx[0::2], idx[1::2])]
    if not 2 <= folds <= n:
        raise SystemExit(f"--folds {folds}: must lie in 2..{n} (the frames with a pose)")
    return [(np.setdiff1d(idx, b), b) for b in np.array_split(idx, folds)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", help="a planar reference (data make-reference --plane)")
    ap.add_argument("--effects", default="axial_noise,range_limits")
    ap.add_argument("--no-rounding", action="store_true", help="simulation not rounded to the measured quantum")
    ap.add_argument("--median-only", action="store_true",
                    help="residuals about each (frame, bin) group's median, not its local plane (fit and table)")
    ap.add_argument("--seeds", type=int, default=2, help="simulation seeds averaged per bin")
    ap.add_argument("--search-frames", type=int, default=None,
                    help="FitConfig.max_frames: fitted frames the search sees (default: FitConfig's)")
    ap.add_argument("--search-pixels", type=int, default=None,
                    help="FitConfig.max_pixels_per_frame (default: FitConfig's)")
    ap.add_argument("--split", choices=("alternate", "halves", "kfold"), default="alternate",
                    help="fit the even frames and hold out the odd ones (alternate), fit the first half of the "
                         "sequence and hold out the second (halves: other views, not the neighbours of fitted frames), "
                         "or --folds contiguous blocks each held out from a fit of the others (kfold: every frame "
                         "held out once; for short sequences)")
    ap.add_argument("--folds", type=int, default=5, help="--split kfold: number of blocks (fits)")
    ap.add_argument("--eval-frames", type=int, default=None,
                    help="FitConfig.eval_frames: fitted frames of the final scores and the noise-curve calibration")
    ap.add_argument("--curve-weight", type=float, default=None,
                    help="FitConfig.noise_curve_weight: the noise-curve term's weight beside the gap (default: FitConfig's)")
    ap.add_argument("--min-frames", type=int, default=10, help="fewest held-out frames a bin needs to be judged")
    ap.add_argument("--boot", type=int, default=200, help="bootstrap replicates")
    ap.add_argument("--block", type=int, default=1,
                    help="bootstrap runs of this many consecutive held-out frames together (correlated views)")
    ap.add_argument("--json", default=None, help="write the table here (JSON)")
    args = ap.parse_args(argv)
    import synth.lab.calibration as cal
    from synth.lab import FitConfig, MeasuredSequence, fit_model
    if args.no_rounding:
        cal.storage_quantum_m = lambda depth, share=0.99: 0.0
    if args.median_only:
        cal.LOCAL_PLANE = False
    t0 = time.perf_counter()
    n_all = len(MeasuredSequence.load(args.seq))
    kw = {}
    if args.search_frames is not None:
        kw["max_frames"] = args.search_frames
    if args.eval_frames is not None:
        kw["eval_frames"] = args.eval_frames
    if args.search_pixels is not None:
        kw["max_pixels_per_frame"] = args.search_pixels
    if args.curve_weight is not None:
        kw["noise_curve_weight"] = args.curve_weight
    effects = [e for e in args.effects.split(",") if e]
    fits, parts_m, parts_s, n_held = [], [], [], 0
    for fit_pos, held_pos in splits(n_all, args.split, args.folds):
        t1 = time.perf_counter()
        fit = MeasuredSequence.load(args.seq, frames=fit_pos)
        res = fit_model(fit, fit.default_config(effects), fit_config=FitConfig(intervals=False, **kw))
        del fit                 # its cached renders: the held-out frames are evaluated in chunks
        print("fitted:", {k: round(v, 6) for k, v in res.params.items() if isinstance(v, float)},
              f"({time.perf_counter() - t1:.0f} s, {res.evaluations} evaluations, {len(fit_pos)} fit / "
              f"{len(held_pos)} held-out frames)", flush=True)
        # group positions: the frame's rank among all held-out frames (the bootstrap's blocks stay consecutive)
        m_g, s_g = chunked_groups(args.seq, held_pos, res.config, args.seeds, first=n_held)
        n_held += len(held_pos)
        fits.append((fit_pos, held_pos, res))
        parts_m.append(m_g)
        parts_s.append(s_g)
    t_fit = time.perf_counter() - t0
    m_groups = merge_groups(parts_m)
    s_groups = [merge_groups([p[j] for p in parts_s]) for j in range(args.seeds)]
    if len(fits) == 1:
        fit_groups, _ = chunked_groups(args.seq, fits[0][0], None, 0)
        fit_meas = [cal._robust_std(np.concatenate([g for _, g in b])) if b else float("nan") for b in fit_groups]
    else:                       # k-fold: every frame is both fitted and held out; no separate fit side
        fit_meas = [float("nan")] * len(m_groups)
    unc = cal.curve_uncertainty(m_groups, s_groups, n_held, n_boot=args.boot, block=args.block)
    edges = cal.BIN_EDGES_M
    rows, worst, worst_judged = [], 0.0, 0.0
    print(f"{'bin [m]':10s} {'measured mm':>11s} {'measured CI':>13s} {'fit/held':>8s} {'simulated':>9s} "
          f"{'ratio':>6s} {'ratio CI':>12s} {'frames':>6s} {'pixels':>8s}  verdict")
    for k in range(len(edges) - 1):
        allm = [g for _, g in m_groups[k]]
        if not allm or sum(g.size for g in allm) < cal.MIN_PIXELS:
            continue
        m = cal._robust_std(np.concatenate(allm))
        sims = [cal._robust_std(np.concatenate([g for _, g in sg[k]])) for sg in s_groups if sg[k]]
        sim = float(np.nanmean(sims)) if sims else float("nan")
        ratio = sim / m
        u = unc[k]
        v = verdict(ratio, u["ratio_ci"], u["frames"], args.min_frames)
        dev = abs(ratio - 1.0) if np.isfinite(ratio) else float("inf")
        worst = max(worst, dev)
        if v != "too few frames":
            worst_judged = max(worst_judged, dev)
        fh = fit_meas[k] / m if np.isfinite(fit_meas[k]) else float("nan")
        mlo, mhi = (1000 * x for x in u["measured_ci"])
        rlo, rhi = u["ratio_ci"]
        npx = sum(g.size for g in allm)
        rows.append({"bin_m": [edges[k], edges[k + 1]], "measured_mm": 1000 * m, "measured_ci_mm": [mlo, mhi],
                     "fit_over_held": fh, "simulated_mm": 1000 * sim, "ratio": ratio, "ratio_ci": [rlo, rhi],
                     "frames": u["frames"], "pixels": npx, "verdict": v})
        print(f"{edges[k]:.2f}-{edges[k + 1]:.2f}  {1000 * m:11.2f} {mlo:6.2f}-{mhi:6.2f} {fh:8.3f} {1000 * sim:9.2f} "
              f"{ratio:6.3f} {rlo:5.3f}-{rhi:5.3f} {u['frames']:6d} {npx:8d}  {v}")
    judged = [r for r in rows if r["verdict"] != "too few frames"]
    n_off = sum(r["verdict"] == "OFF" for r in rows)
    n_unres = sum(r["verdict"] == "unresolved" for r in rows)
    print(f"largest |ratio - 1|: {worst:.3f} over all bins, {worst_judged:.3f} over the {len(judged)} bins with >= "
          f"{args.min_frames} frames ({'within' if worst_judged <= 0.10 else 'NOT within'} 10 %); "
          f"OFF beyond the CI: {n_off}, unresolved: {n_unres}, too few frames: {len(rows) - len(judged)}")
    if args.json:
        per_fit = [{"fitted_frames": len(f), "held_out_frames": [int(x) for x in h], "params": r.params,
                    "evaluations": r.evaluations} for f, h, r in fits]
        Path(args.json).write_text(json.dumps({"seq": str(args.seq), "effects": args.effects, "split": args.split,
                                               "params": fits[0][2].params, "fits": per_fit, "seconds": t_fit,
                                               "evaluations": sum(r.evaluations for _, _, r in fits),
                                               "bins": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
