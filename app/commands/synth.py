"""``realgap synth``: synthetic RGB-D data (scenes, trajectories, rendering).

Subcommands (one ``_add_<name>`` function each; add new ones the same way):

* ``realgap synth sequence --scene room --frames N --out SEQ`` renders an ideal RGB-D
  sequence (:func:`synth.sequence.generate_sequence`).
* ``realgap synth scenes`` lists the registered scenes and their parameters.
* ``realgap synth views --model M.ply --sensor kinect_v1 --out DIR`` simulates object-centred
  views of one model with labels for recognition training (:func:`synth.sensor.views.render_views`).

:func:`add_sequence_arguments` and :func:`sequence_config_from_args` are separate so other
options (e.g. a depth-sensor model) can be added to ``synth sequence`` without touching them.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

from app.commands import RESUMES, positive_float, positive_int, ranged
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
    _add_views(sub)


# --------------------------------------------------------------------------- synth sequence

def _add_sequence(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("sequence", help="render an ideal RGB-D sequence of a scene along a trajectory",
                       description="Render an ideal (noise-free) RGB-D sequence: TUM layout with "
                                   "groundtruth.txt, camera.json, scene.json and config.json. "
                                   "An interrupted run continues when re-run (or with --resume).")
    add_sequence_arguments(p)
    p.set_defaults(func=_cmd_sequence, on_interrupt=RESUMES)
    return p


def _continues(args: argparse.Namespace, *folders: str) -> bool:
    """--resume, or (without --overwrite) an unfinished folder that a killed run left (incomplete.json)."""
    from data_tools.outputs import read_incomplete
    if args.resume:
        return True
    return not args.overwrite and any(read_incomplete(f) is not None for f in folders)


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
    from app.commands import add_shared
    add_shared(p, "--out", "the sequence folder", required=True, metavar="SEQ")
    p.add_argument("--preset", choices=sorted(SEQUENCE_PRESETS), default="kinect_v1",
                   help="starting configuration (default: kinect_v1 = 640x480, f=580 px, 300 frames)")
    p.add_argument("--scene", help="registered scene name (see 'realgap synth scenes'; default room)")
    p.add_argument("--scene-param", action="append", type=_parse_param, default=[], metavar="KEY=VALUE",
                   help="scene builder parameter, repeatable (e.g. path=room.obj)")
    p.add_argument("--frames", type=positive_int("--frames"), help="number of frames to generate (default from --preset)")
    p.add_argument("--fps", type=positive_float("--fps"), help="frame rate (default 30)")
    p.add_argument("--trajectory", choices=sorted(TRAJECTORY_KINDS), help="camera path (default walkthrough)")
    add_shared(p, "--seed", "of scene, trajectory and jitter (default 0)")
    p.add_argument("--no-jitter", action="store_true", help="no hand-held shake on the trajectory")
    p.add_argument("--sensor", help="simulate this depth-sensor preset (kinect_v1, structure, realsense_d435, "
                                    "kinect_v2) instead of writing ideal depth; the ideal sequence goes to SEQ/ideal")
    p.add_argument("--effects", default=None,
                   help="with --sensor: 'physical' (default), 'direct' or a comma list of effect names")
    add_shared(p, "--workers", "with --sensor, simulate N frames at once (same frames, more frames/s when cores "
                              "are free; default 1)", default=1)
    add_shared(p, "--no-progress")
    p.add_argument("--width", type=positive_int("--width"), help=argparse.SUPPRESS)
    p.add_argument("--height", type=positive_int("--height"), help=argparse.SUPPRESS)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true",
                   help="continue the sequence in SEQ (an unfinished one, marked by incomplete.json, continues "
                        "without it)")
    add_shared(g, "--overwrite", "a sequence already in SEQ")


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


MAX_FRAMES_UP_FRONT = 1_000_000
"""Most frames a sequence may have: its trajectory (poses, timestamps: ~0.3 kB a frame) is built
in memory before the first frame is rendered, so more would allocate gigabytes with nothing shown."""
PNG_BYTES_PER_PIXEL = 2.5
"""Rough size of a frame on disk per pixel (16-bit depth + 8-bit colour PNG at about half their
raw size): an estimate to refuse a sequence that cannot fit, not a promise."""


def check_sequence_size(cfg, out: str, sensor: bool = False) -> None:
    """Refuse, before any allocation, a sequence too long to build up front
    (:data:`MAX_FRAMES_UP_FRONT`) or whose frames would not fit on the disk of ``out``
    (estimated with :data:`PNG_BYTES_PER_PIXEL`; twice with ``--sensor``: ideal + simulated)."""
    import shutil
    from pathlib import Path
    if cfg.frames > MAX_FRAMES_UP_FRONT:
        raise ConfigError(f"--frames {cfg.frames}: at most {MAX_FRAMES_UP_FRONT} frames per sequence (the "
                          f"trajectory is built in memory first); make several shorter sequences")
    need = cfg.frames * cfg.width * cfg.height * PNG_BYTES_PER_PIXEL * (2 if sensor else 1)
    p = Path(out).absolute()
    while not p.exists():
        p = p.parent
    free = shutil.disk_usage(p).free
    if need > free:
        raise ConfigError(f"--frames {cfg.frames}: about {need / 1e9:.3g} GB of images at {cfg.width}x{cfg.height}, "
                          f"but {p} has {free / 1e9:.3g} GB free")


def _cmd_sequence(args: argparse.Namespace) -> int:
    from synth.sequence import generate_sequence
    cfg = sequence_config_from_args(args)
    check_sequence_size(cfg, args.out, sensor=bool(args.sensor))
    if args.sensor:
        return _cmd_sensor_sequence(args, cfg)
    res = generate_sequence(cfg, args.out, resume=_continues(args, args.out), overwrite=args.overwrite,
                            progress=True)
    kept = f", kept {res.frames_skipped} already there" if res.frames_skipped else ""
    empty = f", {res.empty_frames} with an empty view" if res.empty_frames else ""
    timing = f" ({res.render_ms_mean:.1f} ms/frame ray casting)" if res.frames_written else ""
    print(f"{res.out_dir}: wrote {res.frames_written} frames{kept}{empty}; {res.frames_total} in total{timing}")
    return 0


def _cmd_sensor_sequence(args: argparse.Namespace, cfg) -> int:
    """Ideal sequence in SEQ/ideal (ground truth, ideal depth), simulated sensor frames in SEQ."""
    from synth.sequence import generate_simulated_sequence
    resume = _continues(args, args.out, f"{args.out}/ideal")
    ideal, n = generate_simulated_sequence(cfg, args.out, args.sensor, args.effects, resume=resume,
                                           overwrite=args.overwrite, workers=args.workers)
    print(f"{args.out}: simulated {n} {args.sensor} frames (kept {ideal.frames_total - n}); "
          f"ideal depth and ground truth in {ideal.out_dir}")
    return 0


# --------------------------------------------------------------------------- synth scenes

def _add_scenes(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("scenes", help="list the registered scenes and their parameters")
    p.set_defaults(func=_cmd_scenes)
    return p


def _cmd_scenes(args: argparse.Namespace) -> int:
    from synth.scenes import describe_scenes
    for name, doc, params in describe_scenes():
        print(f"{name:15s} {doc}")
        if params:
            print(f"{'':15s} parameters: {', '.join(params)}")
    sys.stdout.flush()
    return 0


# --------------------------------------------------------------------------- synth views

def _add_views(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "views", help="simulate object-centred depth views of one model, with pose labels",
        description="Simulate a depth sensor looking at one object from the vertices of a subdivided "
                    "half-icosahedron (object on a ground plane), with in-plane rotations and optional "
                    "clutter/background walls. Writes depth/, ideal/, mask/ PNGs, views.jsonl and "
                    "labels.json (object name, 4x4 object-to-camera pose per view), camera.json, "
                    "sensor_config.json and views_config.json (the effective settings). Interrupted "
                    "runs continue with --resume.")
    p.add_argument("--model", required=True, metavar="MESH", help="PLY/OBJ/STL/OFF model of the object")
    from app.commands import add_shared
    add_shared(p, "--out", "folder of the views (depth/, mask/, ideal/, labels.json)", required=True, metavar="DIR")
    p.add_argument("--sensor", default="kinect_v1",
                   help="sensor preset (kinect_v1, structure, realsense_d435, kinect_v2) or a sensor_config.json "
                        "(default kinect_v1)")
    p.add_argument("--effects", default=None,
                   help="'physical' (default), 'direct' or a comma list of effect names")
    p.add_argument("--scale", type=positive_float("--scale"), default=1.0,
                   help="factor from the model's units to metres (T-LESS models are in mm: 0.001; default 1)")
    p.add_argument("--subdivisions", type=ranged("--subdivisions", int, 0, 5), default=1,
                   help="icosahedron subdivisions: 0 -> 4, 1 -> 17, 2 -> 73 viewpoints above 5 deg elevation "
                        "(default 1)")
    rolls = p.add_mutually_exclusive_group()
    rolls.add_argument("--rolls", type=positive_int("--rolls"), default=None, metavar="N",
                       help="in-plane rotations per viewpoint, evenly spaced over 360 deg (default 1: none)")
    rolls.add_argument("--roll-angles", default=None, metavar="A,B,...",
                       help="explicit in-plane angles in degrees (write --roll-angles=-30,0,30)")
    p.add_argument("--distance", type=positive_float("--distance"), default=None, metavar="M",
                   help="camera distance to the object centre, metres (default: the object fills ~40%% of "
                        "the image height)")
    p.add_argument("--min-elevation", type=float, default=5.0, metavar="DEG",
                   help="lowest viewpoint elevation above the ground, degrees (default 5)")
    p.add_argument("--clutter", type=ranged("--clutter", int, 0), default=0, metavar="N", help="random clutter boxes around the object")
    p.add_argument("--background", action="store_true", help="surround the set-up with four walls")
    p.add_argument("--no-ground", action="store_true", help="no ground plane under the object")
    p.add_argument("--no-ideal", action="store_true", help="do not write the ideal depth images")
    add_shared(p, "--seed", "of the clutter and of the sensor draws (default 0)", default=0)
    add_shared(p, "--no-progress")
    p.add_argument("--limit", type=positive_int("--limit"), default=None, metavar="N",
                   help="render only the first N views (a later --resume without --limit adds the rest)")
    p.add_argument("--width", type=positive_int("--width"), help=argparse.SUPPRESS)   # centred crop (tests)
    p.add_argument("--height", type=positive_int("--height"), help=argparse.SUPPRESS)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true",
                   help="add views to DIR (an unfinished run, marked by incomplete.json, continues without it)")
    add_shared(g, "--overwrite", "views already in DIR")
    p.set_defaults(func=_cmd_views, on_interrupt=RESUMES)
    return p


def views_config_from_args(args: argparse.Namespace):
    """The :class:`synth.sensor.views.ViewsConfig` of parsed ``synth views`` arguments."""
    from pathlib import Path

    from synth.sensor.views import ViewsConfig
    if args.roll_angles is not None:
        try:
            angles = tuple(float(a) for a in args.roll_angles.split(",") if a.strip())
        except ValueError:
            raise ConfigError(f"--roll-angles: expected comma-separated degrees, got {args.roll_angles!r}") from None
        if not angles:
            raise ConfigError("--roll-angles: give at least one angle")
    else:
        n = 1 if args.rolls is None else args.rolls
        if n < 1:
            raise ConfigError(f"--rolls must be >= 1, got {n}")
        angles = tuple(360.0 * k / n for k in range(n))
    return ViewsConfig(subdivisions=args.subdivisions, inplane_deg=angles, distance_m=args.distance,
                       min_elevation_deg=args.min_elevation, ground=not args.no_ground, clutter=args.clutter,
                       background=args.background, seed=args.seed, write_ideal=not args.no_ideal,
                       max_views=args.limit, model_path=str(Path(args.model).resolve()),
                       model_scale=args.scale)


def _views_sensor(args: argparse.Namespace):
    """The sensor config of ``synth views`` (preset or JSON file, effects, optional crop)."""
    from synth.sensor import SensorConfig
    return SensorConfig.from_spec(args.sensor, args.effects, args.width, args.height)


def _cmd_views(args: argparse.Namespace) -> int:
    from synth.sensor.views import render_views_of_file
    cfg = views_config_from_args(args)
    res = render_views_of_file(args.model, args.scale, _views_sensor(args), args.out, cfg,
                               resume=_continues(args, args.out),
                               overwrite=args.overwrite, progress=True)
    kept = res.n_views - res.n_written
    part = f" (first {res.n_views} of {res.n_views_all}; --resume without --limit adds the rest)" \
        if res.n_views < res.n_views_all else ""
    print(f"{res.out_dir}: wrote {res.n_written} views of {res.object_name!r}"
          f"{f', kept {kept} already there' if kept else ''}; {res.n_views} in total{part}; "
          f"labels in {res.out_dir}/labels.json")
    return 0
