"""How consistent is a reference trajectory with its own depth images at the places it revisits?

    .venv/bin/python benchmarks/bench_reference_consistency.py [--sequence DIR] [--step 10] [--pairs 30]

For frame pairs at least 5 s apart whose reference poses are within 0.3 m and 20 degrees (the
reference's revisits), the later depth image is registered onto the earlier one with the loop
closure's refinement (:func:`slam.loop_verify.refine_loop`: projective point-to-plane ICP at
quarter and half resolution, 1.5 cm finest distance) started from the reference's relative pose.
Printed per pair: how far the ICP moves that relative pose, and the fitness and RMS residual at
half resolution before and after. A reference that is consistent with the depth (a loop-closed
one, or motion capture) is moved by millimetres; a drifting one by its drift. A loop-closed
estimate can only agree with the reference to about the median move, so that is a floor for the
ATE of any consistent trajectory against it. The default sequence is 7-Scenes chess converted by
``realgap data convert-7scenes`` (KinectFusion poses).

``--short K`` audits the reference at short baselines instead: every frame i (``--step``) is
registered with frame i + K the same way, once started from the reference's relative pose and once
from the estimate's (``--estimate RUN/trajectory.txt``, optional). Where both starts converge to
the same transform (within 1 mm and 0.05 degrees: the depth pins a unique alignment), that
transform is what the depth says the camera did in K frames; the printout lists the frames where
the reference (or the estimate) disagrees with it by more than ``--glitch-cm``, and the
distribution of the disagreements. A fraction of a second apart, drift cannot explain a
centimetre: such a disagreement is a jump in the trajectory.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="/tmp/realgap_bench/chess", help="a sequence folder with a reference")
    ap.add_argument("--step", type=int, default=10, help="consider every n-th frame")
    ap.add_argument("--pairs", type=int, default=30, help="register at most this many revisit pairs (spread evenly)")
    ap.add_argument("--short", type=int, default=0, help="audit short baselines: register frame i + K onto i (K frames)")
    ap.add_argument("--estimate", default="", help="with --short: a TUM trajectory to audit beside the reference")
    ap.add_argument("--glitch-cm", type=float, default=1.0, help="with --short: list disagreements above this, cm")
    args = ap.parse_args(argv)
    if args.short > 0:
        short_baseline_audit(args.sequence, args.short, args.step, args.estimate, args.glitch_cm)
        return 0
    from data_tools.geometry import rotation_angle_rad
    from data_tools.sequence import SequenceReader
    from slam.backends._p2p_kernel import normal_equations
    from slam.backends._pyramid import Pyramid, normal_map
    from slam.loop_verify import refine_loop
    r = SequenceReader(args.sequence)
    G, ts, intr = r.groundtruth.poses, np.asarray(r.timestamps), r.intrinsics
    n = min(len(G), len(r))

    def fit(dj, di, T):
        ps, pt = Pyramid(dj, intr, 2, 0.1, 4.0, None, 0.06), Pyramid(di, intr, 2, 0.1, 4.0, None, 0.06)
        tv = pt[1].vertex_np()
        _, _, m, ssr = normal_equations(ps[1].vertex_np(), tv, normal_map(tv, 0.06), pt[1].intr.K, T, 0.015, 0.15)
        return m / max(ps[1].valid, 1), 1000 * math.sqrt(ssr / max(m, 1))

    pairs = []
    for j in range(0, n, args.step):
        for i in range(0, j, args.step):
            E = np.linalg.inv(G[i]) @ G[j]
            if (ts[j] - ts[i] >= 5.0 and np.linalg.norm(E[:3, 3]) < 0.3
                    and math.degrees(rotation_angle_rad(E[:3, :3])) < 20.0):
                pairs.append((i, j))
    print(f"{len(pairs)} revisit pairs by the reference (every {args.step}th frame)")
    moves = []
    for i, j in pairs[::max(1, len(pairs) // args.pairs)]:
        di, dj = r[i].depth, r[j].depth
        T0 = np.linalg.inv(G[i]) @ G[j]
        T1, _, _ = refine_loop(dj, di, intr, T0, 0.1, 4.0)
        D = np.linalg.inv(T0) @ T1
        dt, da = 100 * float(np.linalg.norm(D[:3, 3])), math.degrees(rotation_angle_rad(D[:3, :3]))
        (f0, r0), (f1, r1) = fit(dj, di, T0), fit(dj, di, T1)
        moves.append(dt)
        print(f"frames {i:5d} -> {j:5d}: ICP moves the reference's relative pose by {dt:5.2f} cm {da:4.2f} deg; "
              f"fitness {f0:.2f} -> {f1:.2f}, RMS residual {r0:.1f} -> {r1:.1f} mm")
    if moves:
        print(f"median move {np.median(moves):.2f} cm, {np.mean(np.array(moves) > 2):.0%} of the pairs moved > 2 cm")
    return 0


def short_baseline_audit(sequence: str, k: int, step: int, estimate: str, glitch_cm: float) -> dict:
    """The ``--short`` mode of the module docstring; prints one line per disagreement and a summary.
    Returns {"reference" (and "estimate"): [(i, j, cm off the depth's alignment)], "unique": pairs
    whose alignment the depth pins}."""
    from data_tools.geometry import rotation_angle_rad
    from data_tools.sequence import SequenceReader
    from data_tools.trajectory import read_tum
    from slam.loop_verify import refine_loop
    r = SequenceReader(sequence)
    G, ts, intr = r.groundtruth.poses, np.asarray(r.timestamps), r.intrinsics
    n = min(len(G), len(r))
    E = None
    if estimate:
        est = read_tum(estimate)
        at = {round(float(t), 6): P for t, P in zip(est.timestamps, est.poses)}
        E = [at.get(round(float(t), 6)) for t in ts[:n]]
    names = ["reference"] + (["estimate"] if E is not None else [])
    off = {name: [] for name in names}
    pairs = {name: [] for name in names}
    unique = 0
    step = max(1, step)
    for i in range(0, n - k, step):
        j = i + k
        di, dj = r[i].depth, r[j].depth
        starts = {"reference": np.linalg.inv(G[i]) @ G[j]}
        if E is not None and E[i] is not None and E[j] is not None:
            starts["estimate"] = np.linalg.inv(E[i]) @ E[j]
        fits = {name: refine_loop(dj, di, intr, T0, 0.1, 4.0)[0] for name, T0 in starts.items()}
        T_depth = fits["reference"]
        if "estimate" in fits:
            D = np.linalg.inv(fits["reference"]) @ fits["estimate"]
            if not (np.linalg.norm(D[:3, 3]) < 1e-3 and math.degrees(rotation_angle_rad(D[:3, :3])) < 0.05):
                continue                # two optima: the depth does not decide this pair
        unique += 1
        for name, T0 in starts.items():
            D = np.linalg.inv(T0) @ T_depth
            dt = 100 * float(np.linalg.norm(D[:3, 3]))
            off[name].append(dt)
            pairs[name].append((i, j, dt))
            if dt > glitch_cm:
                print(f"frames {i:5d} -> {j:5d}: the depth moves the {name}'s relative pose by {dt:5.2f} cm "
                      f"{math.degrees(rotation_angle_rad(D[:3, :3])):4.2f} deg")
    print(f"{unique} pairs {k} frames apart with a unique depth alignment (every {step}th frame)")
    for name in names:
        a = np.asarray(off[name])
        if len(a):
            print(f"{name}: disagrees with the depth by median {np.median(a) * 10:.1f} mm, p95 "
                  f"{np.percentile(a, 95) * 10:.1f} mm, max {a.max():.2f} cm; {int((a > glitch_cm).sum())} pairs "
                  f"over {glitch_cm:g} cm")
    return dict(pairs, unique=unique)


if __name__ == "__main__":
    sys.exit(main())
