"""Benchmark: the structured-light physical pipeline fitted to 24 VGA frames of a flat target, the
fit as it runs now against the old path, measured in the same run (issue #43 item 4: <= 2 min on
2 cores, with the same or a lower held-out gap).

    .venv/bin/python benchmarks/bench_lab_fit.py [--frames 24] [--no-old] [--seed 3]

Data (no shared data needed): a capture of a large flat target (albedo 0.6) at 2 x ``--frames``
distances from 0.6 to 2.7 m, each with a small random tilt, seen by a simulated Kinect v1 whose
physical pipeline differs from the preset in three parameters (``TRUTH``); the capture gets its
poses, masks and plane from ``realgap data make-reference --plane``, as a real one would. The
even frames are fitted (``--frame-slice 0::2``: the fit searches 4 of them and checks on all),
the odd frames are held out.

Two fits from ``--effects physical`` with the default :class:`~synth.lab.fit.FitConfig`:

* ``old``: the search over every parameter (``screen=False``), a new simulator resource set
  per evaluation (pattern, reference image and ray grid rebuilt each time) and a new masked ideal
  depth per comparison (the compare cache missed every frame of a masked sequence), as before #43;
* ``new``: the default path - the sensitivity screen (:func:`synth.lab.intervals.screen_parameters`)
  freezes what the data does not constrain and fits the rest in sensitivity order; simulators
  share the pattern, reference images, rays and seeded draws of the sequence; the compare cache
  serves the masked frames. It adds the noise-vs-distance term of a planar reference
  (``noise_curve_weight``; the old one has the gap alone).

(The old path here still scores the fitted model once on the evaluation set instead of twice, a
few seconds in its favour.)

Prints the wall and CPU seconds of each fit (load averages: the machine may be shared), the
evaluations, the gap on the fitted frames and on the held-out frames (all 24, 20000 pixels each,
seed 0) of the start, of the true model (the floor: the same sensor, other noise draws) and of
both fits, the ratio old / new, and the parameters the new fit froze.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TRUTH = {"ir_capture.speckle_contrast": 0.45, "ir_capture.psf_sigma_px": 0.9, "pattern_projection.power": 0.6}
"""Where the 'measured' sensor differs from the kinect_v1 preset's physical pipeline."""


def _rot(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def make_plane_capture(out: Path, frames: int, seed: int, width: int = 640, height: int = 480,
                       truth: dict | None = None, effects="physical", z_range=(0.6, 2.7)) -> Path:
    """A flat-target capture without poses (the input of ``data make-reference --plane``): frame
    k at distance z_range[0] + k / (frames - 1) x span, tilted up to 8 degrees, 1 s apart (static)."""
    from data_tools.scene_spec import Material, SceneSpec
    from data_tools.sequence import Frame, SequenceWriter
    from synth.lab.params import set_params
    from synth.sensor.config import SensorConfig
    from synth.sensor.presets import get_preset
    from synth.sensor.simulator import SensorSimulator
    from synth.sensor.testscenes import quad_mesh
    target = quad_mesh([0, 0, 0], [4, 0, 0], [0, 4, 0], "target", "target", 4)
    scene = SceneSpec([target], {"target": Material(0.6, 0.0)})
    cfg = SensorConfig.build(get_preset("kinect_v1").cropped(width, height), effects)
    cfg = set_params(cfg, TRUTH if truth is None else truth)
    sim = SensorSimulator(cfg, scene=scene)
    rng = np.random.default_rng(seed)
    with SequenceWriter(out, sim.camera(), scene) as w:
        for k in range(frames):
            z = z_range[0] + (z_range[1] - z_range[0]) * k / max(frames - 1, 1)
            T = np.eye(4)
            T[:3, :3] = _rot(rng.normal(size=3), np.radians(rng.uniform(0, 8))) @ np.diag([1.0, -1.0, -1.0])
            T[:3, 3] = [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), z]
            w.write(Frame(float(k), sim.simulate(T, seed=1000 * seed + k).depth, None, None, k))
    (out / "groundtruth.txt").unlink(missing_ok=True)
    return out


def _fit(ref: Path, old: bool, fit_options: dict):
    from synth.lab.fit import FitConfig, fit_model
    from synth.lab.measured import MeasuredSequence
    ms = MeasuredSequence.load(ref, frame_slice="0::2")
    if old:
        ms._sim_shared = None                       # a new pattern / reference / ray grid per evaluation

        def fresh_ideal(k):                         # a new masked ideal array per call: the compare cache misses
            return np.where(ms.mask(k), ms.render(k).depth, np.float32(0.0))
        ms._masked_ideal = fresh_ideal
    cfg = ms.default_config("physical")
    fc = FitConfig(**fit_options)
    if old:
        fc.screen, fc.noise_curve_weight = False, 0.0
    la = os.getloadavg()[0]
    t, c = time.perf_counter(), time.process_time()
    res = fit_model(ms, cfg, fit_config=fc)
    return res, time.perf_counter() - t, time.process_time() - c, la, os.getloadavg()[0]


def held_out_gap(ref: Path, config, pixels: int = 20000, seed: int = 0) -> tuple[float, float, list]:
    """(gap, noise-curve term, per-bin simulated / measured std) of ``config`` on the odd frames of
    ``ref`` (every one, ``pixels`` samples each)."""
    from synth.lab.calibration import curve_table
    from synth.lab.fit import FitConfig, Objective
    from synth.lab.measured import MeasuredSequence
    ms = MeasuredSequence.load(ref, frame_slice="1::2")
    obj = Objective(ms, range(len(ms)), FitConfig().compare_config(pixels), seed, noise_weight=1.0)
    obj(config)
    term, obs = obj.curve(config)
    return float(obj.last_result.gap), float(term), [r["ratio"] for r in curve_table(obs, pixels, seed)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=24, help="fitted frames (as many more are held out)")
    ap.add_argument("--size", default="640x480", help="image size WxH")
    ap.add_argument("--seed", type=int, default=3, help="capture seed")
    ap.add_argument("--no-old", action="store_true", help="skip the old path (minutes)")
    ap.add_argument("--fit-option", action="append", default=[], metavar="KEY=VALUE",
                    help="FitConfig override for both fits (JSON value)")
    args = ap.parse_args(argv)
    import json
    from slam.plane_reference import PlaneReferenceConfig, make_plane_reference
    opts = {k: json.loads(v) for k, v in (o.split("=", 1) for o in args.fit_option)}
    w, h = (int(x) for x in args.size.lower().split("x"))
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        t = time.perf_counter()
        cap = make_plane_capture(d / "capture", 2 * args.frames, args.seed, w, h)
        make_plane_reference(cap, d / "ref", PlaneReferenceConfig(), progress=False)
        gen_s = time.perf_counter() - t
        print(f"data: flat target, {2 * args.frames} frames of {w}x{h} at 0.6-2.7 m (made in {gen_s:.1f} s); "
              f"truth {TRUTH}; fit on the {args.frames} even frames, held out: the {args.frames} odd ones; "
              f"{os.cpu_count()} CPUs")
        runs = {}
        for name in (("new",) if args.no_old else ("new", "old")):
            res, wall, cpu, la0, la1 = _fit(d / "ref", name == "old", opts)
            runs[name] = (res, wall)
            print(f"{name}: {wall:.1f} s wall, {cpu:.1f} s CPU, {res.evaluations} evaluations, load average "
                  f"{la0:.2f} -> {la1:.2f}; gap on the fitted frames {res.gap_before:.4f} -> {res.gap:.4f}")
            print("  stages: " + ", ".join(f"{k} {v['seconds']:.1f} s / {v['evaluations']} ev."
                                           for k, v in res.stages.items()))
        start_cfg = runs["new"][0].config.__class__.build(runs["new"][0].config.preset, "physical")
        from synth.lab.params import set_params
        held = {"start": held_out_gap(d / "ref", start_cfg),      # truth: the floor (two noise draws)
                "truth": held_out_gap(d / "ref", set_params(start_cfg, TRUTH))}
        for name, (res, _) in runs.items():
            held[name] = held_out_gap(d / "ref", res.config)
    print("held-out gap: " + ", ".join(f"{k} {v[0]:.4f}" for k, v in held.items()))
    print("held-out noise-curve term (mean |ln simulated/measured std| over 0.25 m bins): "
          + ", ".join(f"{k} {v[1]:.4f}" for k, v in held.items()))
    for k, v in held.items():
        print(f"  {k} simulated / measured std per bin from 0.5 m: "
              + " ".join("-" if r is None else f"{r:.2f}" for r in v[2]))
    new = runs["new"][0]
    print(f"new fit: {len(new.params) - len(new.frozen)} parameters fitted, {len(new.frozen)} frozen "
          f"({', '.join(new.frozen)})")
    print("  fitted: " + ", ".join(f"{k}={v:.4g}" for k, v in new.params.items() if k not in new.frozen))
    if "old" in runs:
        old, old_s = runs["old"]
        moved = [k for k, v in old.params.items() if not np.isclose(v, old.start_params.get(k, np.nan), rtol=1e-6)]
        print(f"old fit moved {len(moved)} of {len(old.params)} parameters: "
              + ", ".join(f"{k}={old.params[k]:.4g}" for k in moved))
        print(f"old / new wall time: x{old_s / runs['new'][1]:.2f}; held-out gap new - old "
              f"{held['new'][0] - held['old'][0]:+.4f}")
    print(f"target: new <= 120 s wall ({runs['new'][1]:.1f} s) and held-out gap <= old's")
    return 0


if __name__ == "__main__":
    sys.exit(main())
