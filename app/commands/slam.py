"""``realgap slam``: register an RGB-D sequence (run) and render novel views of the result (render)."""
from __future__ import annotations

import argparse
import sys
import typing

from data_tools.camera import read_camera_json
from data_tools.errors import ConfigError

NAME = "slam"
HELP = "RGB-D registration + TSDF fusion (run) and novel-view rendering (render)"
DESCRIPTION = ("Register every frame of an RGB-D sequence with a backend (icp: frame-to-model ICP "
               "against the TSDF, rgbd_odometry: frame-to-frame hybrid RGB-D odometry, colmap: "
               "offline RGB structure-from-motion), fuse the frames into a TSDF and write a RUN "
               "folder (trajectory.txt, stats.json, config.json, mesh.ply). Re-running a "
               "command continues an interrupted run.")


# --------------------------------------------------------------------------------------------
# configuration flags generated from the config dataclasses


def add_config_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by ``slam run`` and ``batch``: preset, config file, and one flag per
    configuration field (``--tsdf.voxel_size_m``, ``--icp.min_fitness``, ...)."""
    from slam.loop_closure import LoopClosureConfig
    from slam.pipeline import PRESETS, SlamConfig
    from slam.registration import backend_names, get_backend
    from slam.tsdf import TSDFConfig
    p.add_argument("--preset", default="default", choices=sorted(PRESETS),
                   help="named configuration preset (default: default)")
    p.add_argument("--config", metavar="JSON", help="full configuration (a RUN/config.json, or its "
                   "'config' object); flags below override it")
    p.add_argument("--camera", metavar="JSON", help="camera.json to use instead of the sequence's "
                   "own (e.g. TUM fr1 intrinsics)")
    from app.commands.flags import add_config_flags
    g = p.add_argument_group("run options")
    add_config_flags(g, SlamConfig, exclude=("backend",), typed=False, nested=False)
    g = p.add_argument_group("TSDF options (--tsdf.NAME VALUE)")
    add_config_flags(g, TSDFConfig, "tsdf.", typed=False, nested=False)
    g = p.add_argument_group("loop closure options (--loop-closure.NAME VALUE; off: --loop-closure.enabled false)")
    add_config_flags(g, LoopClosureConfig, "loop_closure.", typed=False, nested=False, flag_prefix="loop-closure.")
    for name in backend_names():
        try:
            cls = get_backend(name).Config
        except Exception:  # a backend whose module cannot load does not break the CLI
            continue
        g = p.add_argument_group(f"{name} backend options (--{name}.NAME VALUE)")
        add_config_flags(g, cls, f"{name}.", typed=False, nested=False)


def config_from_args(args, backend: str, siblings: tuple[str, ...] = ()):
    """SlamConfig from --config/--preset and the generated flags (values checked and typed).
    ``siblings``: other backends of the same command (``batch``), whose options are skipped here."""
    import dataclasses
    from slam.pipeline import SlamConfig, make_config
    from slam.registration import backend_names, get_backend, parse_value
    from slam.tsdf import TSDFConfig
    from slam.pipeline import read_config_file
    from slam.loop_closure import LoopClosureConfig
    sections = {"tsdf": TSDFConfig, "loop_closure": LoopClosureConfig}
    base = read_config_file(args.config) if getattr(args, "config", None) else None
    overrides = {}
    backends = set(backend_names())
    for key, raw in vars(args).items():
        if not key.startswith("cfg:"):
            continue
        dotted = key[4:]
        section, _, name = dotted.rpartition(".")
        if section in backends:
            if section != backend and section in siblings:
                continue
            if section != backend:
                raise ConfigError(f"--{dotted} is an option of backend {section}, not of {backend}")
            cls = get_backend(section).Config
            target = f"backend_config.{name}"
        else:       # --tsdf.x, --loop-closure.x or a SlamConfig field
            cls, target = sections.get(section, SlamConfig), dotted
        hints = typing.get_type_hints(cls)
        if name not in {f.name for f in dataclasses.fields(cls)}:
            raise ConfigError(f"unknown option --{dotted}")
        try:
            overrides[target] = parse_value(raw, hints[name])
        except ConfigError as e:
            raise ConfigError(f"--{dotted.replace('_', '-')}: {e}") from None
        if dotted == "max_frames" and (str(raw).strip() in ("0", "-0") or str(raw).strip().startswith("-")):
            raise ConfigError(f"--max-frames: must be >= 1, got {raw} (leave it out for every frame)")
    try:
        return make_config(backend, args.preset, overrides, base)
    except ConfigError as e:
        raise ConfigError(flag_names(str(e), backend)) from None


def flag_names(message: str, backend: str) -> str:
    """An error of the configuration classes in the words of the command line: ``SlamConfig.max_frames``
    -> ``--max-frames``, ``TSDFConfig.voxel_size_m`` -> ``--tsdf.voxel-size-m``, ``backend_config.x`` and
    ``ICPConfig.x`` -> ``--icp.x``."""
    import re
    from slam.registration import get_backend
    try:
        backend_cls = get_backend(backend).Config.__name__
    except Exception:
        backend_cls = None

    def dash(name: str) -> str:
        return name.replace("_", "-")
    message = re.sub(r"\bconfig\.tsdf\.(\w+)", lambda m: f"--tsdf.{dash(m.group(1))}", message)
    message = re.sub(r"\b(?:config\.loop_closure\.|LoopClosureConfig[.:] ?)(\w+)",
                     lambda m: f"--loop-closure.{dash(m.group(1))}", message)
    message = re.sub(r"\bconfig\.backend_config\.(\w+)", lambda m: f"--{backend}.{dash(m.group(1))}", message)
    message = re.sub(r"\b(?:SlamConfig|config)\.(\w+)", lambda m: f"--{dash(m.group(1))}", message)
    message = re.sub(r"\bTSDFConfig[.:] ?(\w+)", lambda m: f"--tsdf.{dash(m.group(1))}", message)
    message = re.sub(r"\bbackend_config\.(\w+)", lambda m: f"--{backend}.{dash(m.group(1))}", message)
    if backend_cls:
        message = re.sub(rf"\b{backend_cls}\.(\w+)", lambda m: f"--{backend}.{dash(m.group(1))}", message)
    return message


def _camera(args):
    if not getattr(args, "camera", None):
        return None
    from data_tools.outputs import check_input_file
    return read_camera_json(check_input_file(args.camera, "camera file", "--camera"))


# --------------------------------------------------------------------------------------------
# commands


def _run(args) -> int:
    from slam.pipeline import run_slam
    cfg = config_from_args(args, args.backend)
    res = run_slam(args.sequence, args.out, cfg, camera=_camera(args), overwrite=args.overwrite,
                   progress=not args.no_progress, skip_unreadable=args.skip_unreadable)
    s = res.stats
    fps = s.get("frames_per_second")
    print(f"{res.run_dir}: {s.get('frames_tracked', 0)}/{s.get('frames', 0)} frames registered with "
          f"{s.get('backend')}, {s.get('frames_failed', 0)} failed"
          + (f", {fps:.1f} frames/s" if fps else ""))
    if s.get("frames_failed"):
        bad = [r for r in s.get("per_frame", []) if r.get("failed")][:5]
        for r in bad:
            print(f"  failed t={r['timestamp']:.6f}: {r.get('reason', '')}", file=sys.stderr)
    from slam.pipeline import poor_tracking
    bad = poor_tracking(s)
    if bad:
        from app.commands import EXIT_POOR_TRACKING
        print(f"realgap: FAILED RUN: {res.run_dir}: {bad} (exit code {EXIT_POOR_TRACKING})", file=sys.stderr)
        return EXIT_POOR_TRACKING
    return 0


def _render(args) -> int:
    from slam.render import render_run_to_png
    view, paths, depth_scale = render_run_to_png(args.run, args.out, pose=args.pose, frame=args.frame,
                                                 scale=args.scale, source=args.source,
                                                 hallucinate=args.hallucinate)
    print(f"{paths['colour']}: colour; {paths['depth']}: depth (x{depth_scale:g} per metre); "
          f"{view.coverage:.1%} of the pixels see the model (unobserved = magenta)")
    return 0


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands import RESUMES, add_group, add_shared
    from slam.registration import backend_names
    sub = add_group(parser)
    p = sub.add_parser("run", help="register a sequence, fuse it, write RUN/",
                       description="Register every frame of SEQ, fuse them into a TSDF and write RUN/"
                                   "{trajectory.txt,stats.json,config.json,camera.json,mesh.ply}. "
                                   "Re-running the same command resumes an interrupted run. A run that registers "
                                   "fewer than half its frames ends with a FAILED RUN line and exit code 3 (its "
                                   "files are written); one writer at a time holds RUN/lock.json.")
    p.add_argument("sequence", metavar="SEQ", help="TUM-layout sequence folder")
    p.add_argument("--backend", default="icp", choices=backend_names(), help="registration backend (default: icp)")
    add_shared(p, "--out", "the run folder", required=True, metavar="RUN")
    add_shared(p, "--overwrite", "discard a run in RUN made with other settings (the same run is continued)")
    add_shared(p, "--no-progress")
    p.add_argument("--skip-unreadable", action="store_true",
                   help="register the sequence without input frames that cannot be read (reported as failed "
                        "frames); default: such a frame stops the run with an error naming it")
    add_config_arguments(p)
    p.set_defaults(func=_run, on_interrupt=RESUMES)

    p = sub.add_parser("render", help="render colour + depth of the fused model from a pose",
                       description="Render the reconstruction in RUN from any camera pose (novel view) "
                                   "with the run's camera. Writes PNG (colour, unobserved pixels "
                                   "magenta), PNG stem + _depth.png (16-bit, camera depth scale) and "
                                   "stem + .json.")
    p.add_argument("run", metavar="RUN", help="run folder written by 'realgap slam run'")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--pose", metavar='"tx ty tz qx qy qz qw"', help="camera-to-world pose (TUM order)")
    g.add_argument("--frame", type=int, metavar="K", help="use the K-th pose of RUN/trajectory.txt (from 0; -1 is the last)")
    add_shared(p, "--out", "colour image (.png); the depth image and the view's JSON are written next to it",
               required=True, metavar="PNG")
    add_shared(p, "--overwrite", "existing images of that name")
    from app.commands import ranged
    p.add_argument("--scale", type=ranged("--scale", float, 0, 8, low_open=True), default=1.0,
                   help="image size relative to the run's camera, in (0, 8] (default 1)")
    p.add_argument("--source", default="auto", choices=("auto", "mesh", "volume", "neural"),
                   help="render the mesh, the saved TSDF volume or decode the neural memory's recalled view "
                        "(auto: neural for a run of the neural backend, else the volume when saved)")
    p.add_argument("--hallucinate", action="store_true",
                   help="neural runs: decode the view after the hallucination module filled the unobserved memory")
    p.set_defaults(func=_render, _io_allow_inside=("RUN",))  # a view of RUN may live in RUN
