"""``realgap data``: dataset conversion and inspection."""
from __future__ import annotations

import argparse

from app.commands import add_group

NAME = "data"
HELP = "convert and inspect RGB-D datasets (TUM layout + camera.json/scene.json)"


def register(parser: argparse.ArgumentParser) -> None:
    sub = add_group(parser)
    p = sub.add_parser("convert-7scenes", help="convert a Microsoft 7-Scenes sequence to the TUM layout",
                       description="Convert frame-XXXXXX.{color.jpg,depth.png,pose.txt} (+camera-intrinsics.txt) "
                                   "into a TUM-layout sequence with camera.json (depth_scale 1000). Re-running "
                                   "continues an interrupted conversion.")
    p.add_argument("src", help="7-Scenes sequence folder")
    p.add_argument("dst", help="output sequence folder (TUM layout)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate used to make timestamps (default 30)")
    p.add_argument("--overwrite", action="store_true", help="delete DST first instead of resuming")
    p.set_defaults(func=_convert_7scenes)

    p = sub.add_parser("info", help="validate a sequence and print what it holds")
    p.add_argument("seq", help="sequence folder (TUM layout)")
    p.set_defaults(func=_info)


def _convert_7scenes(args) -> int:
    from data_tools.sevenscenes import convert_7scenes
    r = convert_7scenes(args.src, args.dst, fps=args.fps, overwrite=args.overwrite)
    print(f"wrote {r.frames} frames to {r.dst} (resumed after {r.skipped_existing}; "
          f"{r.invalid_65535_frames} depth images had 65535 invalid markers)")
    return 0


def _info(args) -> int:
    import json
    from data_tools.sequence import SequenceReader
    seq = SequenceReader(args.seq)
    i = seq.intrinsics
    info = {
        "path": str(seq.path), "frames": len(seq),
        "duration_s": float(seq.timestamps[-1] - seq.timestamps[0]),
        "camera_json": seq.has_camera_json,
        "intrinsics": {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
        "depth_scale": seq.camera.depth_scale,
        "sensor": None if seq.camera.sensor is None else seq.camera.sensor.to_json(),
        "frames_with_pose": int(sum(1 for p in seq.poses if p[0, 0] == p[0, 0])),
        "scene_json": seq.has_scene,
    }
    if seq.has_scene:
        sc = seq.scene
        info["scene_meshes"] = len(sc.meshes)
        info["scene_triangles"] = int(sum(len(m.triangles) for m in sc.meshes))
    print(json.dumps(info, indent=2))
    return 0
