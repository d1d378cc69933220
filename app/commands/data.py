"""``realgap data``: dataset conversion and inspection."""
from __future__ import annotations

import argparse

from app.commands import RESUMES, add_group, add_shared, positive_float, positive_int, ranged
from data_tools.errors import ConfigError

NAME = "data"
HELP = "convert and inspect RGB-D datasets (TUM layout + camera.json/scene.json)"


def register(parser: argparse.ArgumentParser) -> None:
    sub = add_group(parser)
    p = sub.add_parser("convert-7scenes", help="convert a Microsoft 7-Scenes sequence to the TUM layout",
                       description="Convert frame-XXXXXX.{color.jpg,depth.png,pose.txt} (+camera-intrinsics.txt) "
                                   "into a TUM-layout sequence with camera.json (depth_scale 1000). Re-running "
                                   "continues an interrupted conversion.")
    p.add_argument("src", help="7-Scenes sequence folder")
    p.add_argument("dst", nargs="?", help="the converted sequence folder (TUM layout); or give it as --out")
    add_shared(p, "--out", "the converted sequence folder (same as DST)", metavar="DST")
    p.add_argument("--fps", type=positive_float("--fps"), default=30.0, help="frame rate used to make timestamps (default 30)")
    add_shared(p, "--overwrite", "delete DST first instead of continuing the conversion in it")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_convert_7scenes, on_interrupt=RESUMES)

    p = sub.add_parser("convert-kinect-raw", help="convert raw Kinect v1 captures (NNNN-d.pgm disparity) to the TUM layout",
                       description="Convert NNNN-d.pgm (16-bit raw 11-bit disparity, 2047 = none) and optional "
                                   "NNNN-c.ppm|png|jpg into a TUM-layout sequence with camera.json, using the "
                                   "Herrera et al. 2012 calibration (OpenCV YAML: dK, dkc, dc, dc_alpha, dc_beta). "
                                   "Frame N gets the timestamp N / fps. Re-running continues an interrupted run.")
    p.add_argument("src", help="folder of raw captures")
    p.add_argument("dst", nargs="?", help="the converted sequence folder (TUM layout); or give it as --out")
    add_shared(p, "--out", "the converted sequence folder (same as DST)", metavar="DST")
    p.add_argument("--calib", required=True, metavar="CALIB.yml", help="the depth calibration (OpenCV YAML)")
    p.add_argument("--undistort-disparity", action="store_true",
                   help="correct the disparity with dc_beta/dc_alpha (default: keep the raw sensor behaviour, "
                        "which is what the sensor lab models)")
    p.add_argument("--fps", type=positive_float("--fps"), default=30.0, help="frame rate used to make timestamps (default 30)")
    add_shared(p, "--overwrite", "a converted sequence already in DST")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_convert_kinect_raw, on_interrupt=RESUMES)

    p = sub.add_parser("info", help="validate a sequence and print what it holds",
                       description="Read the index, calibration and scene files of SEQ and print what it holds "
                                   "(frames, duration, intrinsics, depth scale, poses, scene; 'incomplete' when a "
                                   "command writing it has not finished). With --deep every image is opened: "
                                   "16-bit depth, size as camera.json says, decodable, median depth plausible; bad "
                                   "frames are listed by file name and the exit code is 1.")
    p.add_argument("seq", help="sequence folder (TUM layout)")
    p.add_argument("--deep", action="store_true", help="open and check every image (see above)")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_info)

    p = sub.add_parser("make-reference", help="fuse a reference mesh (scene.json) from a sequence and its poses",
                       description="Fuse every frame of SEQ at its ground-truth pose into a TSDF and write the "
                                   "cleaned mesh as scene.json + meshes/reference.ply (the reference geometry the "
                                   "sensor lab needs). With --out the sequence is copied there (images "
                                   "hard-linked when possible) and SEQ is left untouched; without it the "
                                   "reference is written into SEQ. reference_config.json records the options.")
    p.add_argument("seq", help="sequence folder (TUM layout with groundtruth.txt)")
    add_shared(p, "--out", "write a copy of the sequence with the reference here (default: into SEQ)",
               metavar="SEQ_OUT")
    p.add_argument("--camera", metavar="JSON|NAME",
                   help="camera.json to use (and write) instead of the sequence's own, or one of "
                        "tum_fr1, tum_fr2, tum_fr3, sevenscenes (TUM folders have no camera.json)")
    p.add_argument("--voxel", type=positive_float("--voxel"), default=0.01, metavar="M", help="TSDF voxel size in metres (default 0.01)")
    p.add_argument("--depth-max", type=positive_float("--depth-max"), default=4.0, metavar="M",
                   help="ignore depth beyond this many metres (default 4)")
    add_shared(p, "--max-frames", "fuse only the first N frames (default: every frame with a pose)")
    add_shared(p, "--spread-frames", "fuse N of them (default: all)")
    p.add_argument("--material", default="reference", help="material name of the mesh (default reference)")
    p.add_argument("--albedo", type=ranged("--albedo", float, 0, 1), default=0.5,
                   help="albedo of that material, in [0, 1] (default 0.5)")
    p.add_argument("--min-component", type=ranged("--min-component", int, 0), default=200, metavar="TRIANGLES",
                   help="drop connected pieces with fewer triangles (default 200)")
    p.add_argument("--plane", action="store_true",
                   help="a capture of a flat target without poses: fit the dominant plane per frame (RANSAC + "
                        "least squares), write poses that put it on z = 0, per-frame masks of the target "
                        "(mask.txt) and the plane as scene.json (needs --out)")
    p.add_argument("--roi", metavar="x0,y0,x1,y1", help="with --plane: the window holding the target (pixels)")
    add_shared(p, "--overwrite", "an existing scene.json")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_make_reference)


def _destination(args) -> str:
    """DST given as the second positional argument or as --out (one of them, not two different)."""
    if args.dst and args.out and args.dst != args.out:
        raise ConfigError(f"two destinations: DST {args.dst!r} and --out {args.out!r}; give one")
    if not (args.dst or args.out):
        raise ConfigError("no destination: give the converted sequence folder as DST (after SRC) or --out")
    return args.dst or args.out


def _convert_7scenes(args) -> int:
    from data_tools.sevenscenes import convert_7scenes
    r = convert_7scenes(args.src, _destination(args), fps=args.fps, overwrite=args.overwrite)
    print(f"wrote {r.frames} frames to {r.dst} (resumed after {r.skipped_existing}; "
          f"{r.invalid_65535_frames} depth images had 65535 invalid markers)")
    return 0


def _convert_kinect_raw(args) -> int:
    from data_tools.kinect_raw import convert_kinect_raw
    r = convert_kinect_raw(args.src, _destination(args), args.calib, undistort_disparity=args.undistort_disparity,
                           fps=args.fps, overwrite=args.overwrite, progress=not args.no_progress)
    print(f"wrote {r.frames} frames to {r.dst} ({r.colour_frames} with colour; resumed after {r.skipped_existing}; "
          f"disparity {'undistorted' if r.undistorted else 'raw'})")
    return 0


def _info(args) -> int:
    import json
    import sys
    from data_tools.sequence import sequence_info
    info = sequence_info(args.seq)
    if not args.deep:
        print(json.dumps(info, indent=2))
        return 0
    from data_tools.sequence_check import check_sequence
    check = check_sequence(args.seq)
    info["deep"] = check.to_json()
    print(json.dumps(info, indent=2))
    if not check.ok:
        print(f"realgap: error: {check.summary()}", file=sys.stderr)
        return 1
    return 0


def _make_plane_reference(args) -> int:
    from slam.plane_reference import PlaneReferenceConfig, make_plane_reference
    from slam.reference import named_camera
    if not args.out:
        raise ConfigError("--plane writes a new sequence: give --out REF")
    roi = None
    if args.roi:
        try:
            roi = tuple(int(v) for v in args.roi.split(","))
        except ValueError:
            raise ConfigError(f"--roi: expected x0,y0,x1,y1 in pixels, got {args.roi!r}") from None
        if len(roi) != 4:
            raise ConfigError(f"--roi: expected x0,y0,x1,y1 in pixels, got {args.roi!r}")
    cfg = PlaneReferenceConfig(roi=roi, material=args.material if args.material != "reference" else "target",
                               albedo=args.albedo)
    r = make_plane_reference(args.seq, args.out, cfg, camera=named_camera(args.camera) if args.camera else None,
                             max_frames=args.max_frames, spread_frames=args.spread_frames, overwrite=args.overwrite,
                             progress=not args.no_progress)
    d = sorted(r.distances_m)
    print(f"{r.out_dir}: target plane fitted in {r.frames_posed} of {r.frames} frames (distance "
          f"{d[0]:.2f}-{d[-1]:.2f} m, target {100 * sum(r.mask_fraction) / len(r.mask_fraction):.0f} % of the "
          f"image on average); poses in groundtruth.txt, masks in mask.txt, plane in scene.json")
    return 0


def _make_reference(args) -> int:
    if args.plane:
        return _make_plane_reference(args)
    from slam.reference import ReferenceConfig, make_reference, named_camera
    from slam.tsdf import TSDFConfig
    cfg = ReferenceConfig(tsdf=TSDFConfig(voxel_size_m=args.voxel, depth_max_m=args.depth_max,
                                          integrate_color=False),
                          max_frames=args.max_frames, spread_frames=args.spread_frames,
                          min_component_triangles=args.min_component,
                          material=args.material, albedo=args.albedo).validate()
    cam = named_camera(args.camera) if args.camera else None
    r = make_reference(args.seq, args.out, cfg, camera=cam, overwrite=args.overwrite, progress=True)
    info = r.to_json()
    print(f"{r.out_dir / 'scene.json'}: reference mesh with {info['triangles']} triangles fused from "
          f"{r.frames_fused} frames ({r.frames_without_pose} without a pose; {info['triangles_dropped']} "
          f"triangles cleaned away) in {r.seconds:.1f} s")
    return 0
