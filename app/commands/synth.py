"""``realgap synth``: synthetic RGB-D data (scenes, trajectories, rendering).

Subcommands (one ``_add_<name>`` function each; add new ones the same way):

* ``realgap synth sequence --scene room --frames N --out SEQ`` renders an ideal RGB-D
  sequence (:func:`synth.sequence.generate_sequence`).
* ``realgap synth scenes`` lists the registered scenes and their parameters.

:func:`add_sequence_arguments` and :func:`sequence_config_from_args` are separate so other
options (e.g. a depth-sensor model) can be added to ``synth sequence`` without touching them.
"""
from __future__ import annotations

import argparse
import inspect
import json
import sys
from dataclasses import replace

from data_tools.errors import ConfigError

NAME = "synth"
HELP = "generate synthetic RGB-D data: built-in scenes, camera trajectories, ideal rendering"
DESCRIPTION = ("Generate synthetic RGB-D sequences from built-in or loaded scenes (TUM layout with "
               "camera.json, scene.json and config.json).")


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands import add_group
    sub = add_group(parser)
    _add_sequence(sub)
    _add_scenes(sub)


# --------------------------------------------------------------------------- synth sequence

def _add_sequence(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("sequence", help="render an ideal RGB-D sequence of a scene along a trajectory",
                       description="Render an ideal (noise-free) RGB-D sequence: TUM layout with "
                                   "groundtruth.txt, camera.json, scene.json and config.json. "
                                   "Interrupted runs continue with --resume.")
    add_sequence_arguments(p)
    p.set_defaults(func=_cmd_sequence)
    return p


def _parse_param(text: str) -> tuple[str, object]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    key, value = text.split("=", 1)
    try:
        parsed = json.loads(value)  # numbers, booleans, lists
    except json.JSONDecodeError:
        parsed = value  # plain strings such as paths
    return key.strip(), parsed


def add_sequence_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``synth sequence`` that map to :class:`synth.sequence.SequenceConfig`."""
    from synth.sequence import SEQUENCE_PRESETS
    from synth.trajectories import TRAJECTORY_KINDS
    p.add_argument("--out", required=True, metavar="SEQ", help="output sequence folder")
    p.add_argument("--preset", choices=sorted(SEQUENCE_PRESETS), default="kinect_v1",
                   help="starting configuration (default: kinect_v1 = 640x480, f=580 px, 300 frames)")
    p.add_argument("--scene", help="registered scene name (see 'realgap synth scenes'; default room)")
    p.add_argument("--scene-param", action="append", type=_parse_param, default=[], metavar="KEY=VALUE",
                   help="scene builder parameter, repeatable (e.g. path=room.obj)")
    p.add_argument("--frames", type=int, help="number of frames")
    p.add_argument("--fps", type=float, help="frame rate (default 30)")
    p.add_argument("--trajectory", choices=sorted(TRAJECTORY_KINDS), help="camera path (default walkthrough)")
    p.add_argument("--seed", type=int, help="seed of scene, trajectory and jitter (default 0)")
    p.add_argument("--no-jitter", action="store_true", help="no hand-held shake on the trajectory")
    p.add_argument("--sensor", help="simulate this depth-sensor preset (kinect_v1, structure, realsense_d435, "
                                    "kinect_v2) instead of writing ideal depth; the ideal sequence goes to SEQ/ideal")
    p.add_argument("--effects", default=None,
                   help="with --sensor: 'physical' (default), 'direct' or a comma list of effect names")
    p.add_argument("--width", type=int, help=argparse.SUPPRESS)
    p.add_argument("--height", type=int, help=argparse.SUPPRESS)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true", help="continue an interrupted sequence in SEQ")
    g.add_argument("--overwrite", action="store_true", help="replace a sequence already in SEQ")


def sequence_config_from_args(args: argparse.Namespace):
    """The :class:`SequenceConfig` of parsed ``synth sequence`` arguments (preset + overrides)."""
    from synth.sequence import SEQUENCE_PRESETS
    cfg = SEQUENCE_PRESETS[args.preset]
    over = {k: getattr(args, k) for k in ("scene", "frames", "fps", "trajectory", "seed")
            if getattr(args, k) is not None}
    if args.scene_param:
        over["scene_params"] = dict(args.scene_param)
    elif "scene" in over and over["scene"] != cfg.scene:
        over["scene_params"] = {}
    if args.no_jitter:
        over.update(jitter_trans_m=0.0, jitter_rot_rad=0.0)
    cfg = replace(cfg, **over)
    if args.width is not None or args.height is not None:
        w = args.width if args.width is not None else cfg.width
        h = args.height if args.height is not None else cfg.height
        if w <= 0 or h <= 0:
            raise ConfigError(f"image size must be positive, got {w}x{h}")
        cfg = cfg.with_resolution(w, h)
    return cfg


def _cmd_sequence(args: argparse.Namespace) -> int:
    from synth.sequence import generate_sequence
    cfg = sequence_config_from_args(args)
    if args.sensor:
        return _cmd_sensor_sequence(args, cfg)
    res = generate_sequence(cfg, args.out, resume=args.resume, overwrite=args.overwrite, progress=True)
    kept = f", kept {res.frames_skipped} already there" if res.frames_skipped else ""
    empty = f", {res.empty_frames} with an empty view" if res.empty_frames else ""
    timing = f" ({res.render_ms_mean:.1f} ms/frame ray casting)" if res.frames_written else ""
    print(f"{res.out_dir}: wrote {res.frames_written} frames{kept}{empty}; {res.frames_total} in total{timing}")
    return 0


def _cmd_sensor_sequence(args: argparse.Namespace, cfg) -> int:
    """Ideal sequence in SEQ/ideal (ground truth, ideal depth), simulated sensor frames in SEQ."""
    import shutil
    from pathlib import Path

    from data_tools.sequence import SequenceReader, SequenceWriter
    from synth.sensor import SensorSimulator, simulate_trajectory
    from synth.sequence import generate_sequence

    out = Path(args.out)
    if args.overwrite and out.exists():
        shutil.rmtree(out)
    ideal_dir = out / "ideal"
    generate_sequence(cfg, ideal_dir, resume=args.resume and (ideal_dir / "depth.txt").exists(), progress=True)
    ideal = SequenceReader(ideal_dir)
    traj = ideal.trajectory
    sim = SensorSimulator(args.sensor, args.effects, ideal.scene)
    with SequenceWriter(out, sim.camera(), ideal.scene, resume=args.resume) as w:
        sim.config.save(out / "sensor_config.json")
        done = len(w)
        n = simulate_trajectory(sim, traj.poses, traj.timestamps, w, seed=cfg.seed)
    print(f"{out}: simulated {n} {args.sensor} frames (kept {done}); ideal depth and ground truth in {ideal_dir}")
    return 0


# --------------------------------------------------------------------------- synth scenes

def _add_scenes(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("scenes", help="list the registered scenes and their parameters")
    p.set_defaults(func=_cmd_scenes)
    return p


def _cmd_scenes(args: argparse.Namespace) -> int:
    from synth.scenes import SCENES, scene_names, scene_parameters
    for name in scene_names():
        params = []
        for k, v in scene_parameters(name).items():
            params.append(f"{k}=<required>" if v is inspect.Parameter.empty else f"{k}={v!r}")
        doc = (inspect.getdoc(SCENES[name]) or "").split("\n")[0]
        print(f"{name:15s} {doc}")
        if params:
            print(f"{'':15s} parameters: {', '.join(params)}")
    sys.stdout.flush()
    return 0
