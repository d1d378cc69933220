"""What a planar reference's measured noise curve is made of, per 0.25 m bin of ideal depth: the
robust std of depth - reference over each (frame, bin) group taken about the group's median, about
its local plane (:func:`synth.lab.calibration.local_plane_residuals`) and about a local quadric
(the same columns times u^2, u v, v^2), plus the adjacent-pixel difference / sqrt(2); the far bins
(from 2 m) also per incidence class (< 60, 60-75, 75-90 deg). A ramp or bend of the reference's
misfit shows as median >> local plane; pixel noise is the same in all three
(docs/sensor_lab.md, "The far grazing bin: noise or plane misfit").

    .venv/bin/python benchmarks/plane_noise_parts.py PLANE_REF [--frames 489:] [--model PARAMS_JSON]

``--frames``: a frame slice (``MeasuredSequence.load``'s ``frame_slice``); ``--model``: a JSON object of
``{"axial_noise.param": value}`` for ``axial_noise`` whose simulation gets the same table (seed 0).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

FAR_M = 2.0
"""Bins from here on are also split by incidence."""
CLASSES_DEG = (60.0, 75.0)
"""Incidence class edges, degrees."""
KINDS = ("median", "plane", "quadric", "neighbour")


def _rstd(r: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) if r.size else float("nan")


def group_parts(r: np.ndarray, z: np.ndarray, uv: np.ndarray) -> dict[str, np.ndarray]:
    """One (frame, bin) group's residuals ``r`` (N,) m about its median, local plane and local quadric."""
    from synth.lab.calibration import local_plane_residuals
    out = {"median": r - np.median(r), "plane": local_plane_residuals(r, z, uv)}
    r0 = out["median"]
    s = _rstd(r0)
    keep = np.abs(r0) <= 5 * s if s > 0 else np.ones(r.size, bool)
    z2 = z ** 2
    A = np.stack([z2, z2 * uv[:, 0], z2 * uv[:, 1], z2 * uv[:, 0] ** 2, z2 * uv[:, 0] * uv[:, 1],
                  z2 * uv[:, 1] ** 2], 1)
    x, *_ = np.linalg.lstsq(A[keep], r[keep], rcond=None)
    q = r - A @ x
    out["quadric"] = q - np.median(q)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq")
    ap.add_argument("--frames", default=None, help="frame slice, e.g. 489: (default: all)")
    ap.add_argument("--model", default=None, help="JSON {\"axial_noise.param\": value} to simulate")
    args = ap.parse_args(argv)
    from synth.lab import MeasuredSequence
    from synth.lab.calibration import BIN_EDGES_M, LOCAL_PLANE_MIN_PIXELS
    from synth.lab.feature_maps import incidence_angle_deg
    from synth.lab.params import set_params
    ms = MeasuredSequence.load(args.seq, frame_slice=args.frames)
    cfg = None
    if args.model:
        cfg = set_params(ms.default_config(["axial_noise"]), json.loads(args.model))
    edges = np.asarray(BIN_EDGES_M)
    acc: dict[tuple, dict[str, list]] = {}
    sides = ("measured", "simulated") if cfg is not None else ("measured",)
    for a in range(0, len(ms), 40):
        frames = list(range(a, min(a + 40, len(ms))))
        sims = ms.simulate(cfg, 0, frames=frames) if cfg is not None else None
        for i, k in enumerate(frames):
            o = ms.observation(k, sims[i] if sims is not None else ms.measured_depth(k))
            H, W = o.ideal.shape
            flat = np.flatnonzero(o.ideal.ravel() > 0)
            z = o.ideal.ravel()[flat].astype(np.float64)
            ang = incidence_angle_deg(o.normals, o.intrinsics, idx=flat)
            v, u = np.divmod(flat, W)
            uv = np.stack([(u - W / 2) / W, (v - H / 2) / W], 1)
            for side in sides:
                img = getattr(o, side)
                d = img.ravel()[flat].astype(np.float64)
                for b in range(len(edges) - 1):
                    sel = (d > 0) & (z >= edges[b]) & (z < edges[b + 1])
                    if sel.sum() < LOCAL_PLANE_MIN_PIXELS:
                        continue
                    parts = group_parts(d[sel] - z[sel], z[sel], uv[sel])
                    uu, vv = u[sel], v[sel]
                    okn = uu + 1 < W
                    dn = img[vv[okn], uu[okn] + 1].astype(np.float64)
                    zn = o.ideal[vv[okn], uu[okn] + 1].astype(np.float64)
                    good = (dn > 0) & (zn > 0)
                    parts["neighbour"] = ((dn - zn) - (d[sel][okn] - z[sel][okn]))[good] / np.sqrt(2.0)
                    cls = np.digitize(ang[sel], CLASSES_DEG)
                    keys = [(b, side, "all", None)]
                    if edges[b] >= FAR_M:
                        keys += [(b, side, c, cls == c) for c in range(len(CLASSES_DEG) + 1)]
                    for b_, s_, c_, m_ in keys:
                        if m_ is not None and m_.sum() < 10:
                            continue
                        e = acc.setdefault((b_, s_, c_), {kd: [] for kd in KINDS} | {"groups": 0})
                        e["groups"] += 1
                        for kd in KINDS:
                            e[kd].append(parts[kd] if m_ is None or kd == "neighbour" else parts[kd][m_])
        del sims
    names = ["< 60", "60-75", "75-90"]
    print(f"{'bin [m]':10s} {'side':9s} {'incidence':>9s} {'groups':>6s} {'pixels':>9s} " + " ".join(f"{k:>9s}" for k in KINDS) + "  (mm)")
    for (b, side, c), e in sorted(acc.items(), key=lambda t: (t[0][0], t[0][1], str(t[0][2]))):
        npx = sum(x.size for x in e["median"])
        vals = [1000 * _rstd(np.concatenate(e[kd])) if kd != "neighbour" or c == "all" else float("nan") for kd in KINDS]
        print(f"{edges[b]:.2f}-{edges[b + 1]:.2f}  {side:9s} {c if c == 'all' else names[c]:>9s} {e['groups']:6d} {npx:9d} "
              + " ".join(f"{x:9.2f}" for x in vals))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
