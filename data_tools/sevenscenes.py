"""Convert Microsoft 7-Scenes sequences to the TUM layout (+ camera.json).

7-Scenes layout: ``frame-XXXXXX.color.jpg`` (8-bit colour), ``frame-XXXXXX.depth.png``
(uint16 millimetres; 0 and 65535 = no measurement), ``frame-XXXXXX.pose.txt`` (4x4
camera-to-world, metres, from KinectFusion) and an optional ``camera-intrinsics.txt`` (3x3 K).
It has no timestamps: frame k gets ``t0 + k / fps`` (Kinect v1 runs at 30 Hz).

Colour JPEGs are copied byte for byte (no re-encoding); depth PNGs are copied unless they
contain 65535 (rewritten with 0 there). Depth keeps millimetres: camera.json says
``depth_scale: 1000``. Pose rotations are stored with 8 digits in 7-Scenes, so they are
re-orthonormalised (SVD) before being written as quaternions; a pose further than 0.01 from
a rotation, or with NaN, is an error naming the file.
"""
from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass, asdict
from pathlib import Path

import numpy as np

from data_tools.camera import Camera, Intrinsics, SensorSpec, write_camera_json
from data_tools.errors import FormatError
from data_tools.geometry import pose_to_tum
from data_tools.results import atomic_write_image, atomic_write_json, atomic_write_text

SEVENSCENES_DEFAULT_K = (585.0, 585.0, 320.0, 240.0)
"""fx, fy, cx, cy published with 7-Scenes (depth camera), used when camera-intrinsics.txt is absent."""

_FRAME_RE = re.compile(r"^frame-(\d+)\.color\.(jpg|png)$")


@dataclass
class ConvertResult:
    """What a conversion did."""

    src: str
    dst: str
    frames: int
    """Frames in the destination after the run."""
    skipped_existing: int
    """Frames already converted by an earlier, interrupted run (resume)."""
    invalid_65535_frames: int
    """Depth images where 65535 (7-Scenes' invalid marker) was rewritten to 0."""
    fps: float


def read_intrinsics_txt(path: Path) -> tuple[float, float, float, float]:
    try:
        K = np.loadtxt(path)
    except Exception as e:
        raise FormatError(path, f"cannot parse 3x3 intrinsics matrix ({e})") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise FormatError(path, f"expected a finite 3x3 camera matrix with positive focal lengths, got shape {K.shape}")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def read_pose_txt(path: Path) -> np.ndarray:
    """4x4 camera-to-world from a 7-Scenes pose file, rotation re-orthonormalised."""
    try:
        T = np.loadtxt(path)
    except Exception as e:
        raise FormatError(path, f"cannot parse 4x4 pose ({e})") from None
    if T.shape != (4, 4):
        raise FormatError(path, f"expected a 4x4 pose matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise FormatError(path, "pose contains NaN or infinite values")
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0 or np.abs(R - T[:3, :3]).max() > 1e-2 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise FormatError(path, "pose is not a rigid transform (rotation not orthonormal or bad last row)")
    out = T.copy()
    out[:3, :3] = R
    return out


def convert_7scenes(src: str | os.PathLike, dst: str | os.PathLike, fps: float = 30.0,
                    t0: float = 0.0, overwrite: bool = False, progress: bool = True) -> ConvertResult:
    """Convert a 7-Scenes sequence folder ``src`` into a TUM-layout sequence ``dst``.

    Re-running on a partially converted ``dst`` continues where it stopped (frames are
    appended to the index files only once their images are in place).
    """
    import cv2
    from data_tools.progress import progress_bar

    from data_tools.outputs import check_input_dir, check_output_dir
    import math
    if not (math.isfinite(fps) and fps > 0):     # 0 divides by zero, < 0 makes timestamps run backwards
        raise FormatError(None, f"--fps must be a finite number > 0, got {fps}")
    src = check_input_dir(src, "7-Scenes sequence folder")
    dst = check_output_dir(dst, what="output sequence folder")
    frames = sorted((int(m.group(1)), m.group(0)) for f in os.listdir(src) if (m := _FRAME_RE.match(f)))
    if not frames:
        raise FormatError(src, "no 7-Scenes frames (frame-XXXXXX.color.jpg) found")
    kfile = src / "camera-intrinsics.txt"
    fx, fy, cx, cy = read_intrinsics_txt(kfile) if kfile.exists() else SEVENSCENES_DEFAULT_K

    # validate everything before writing anything
    poses = []
    for idx, color_name in frames:
        stem = f"frame-{idx:06d}"
        for suffix in (".depth.png", ".pose.txt"):
            if not (src / (stem + suffix)).is_file():
                raise FormatError(src / (stem + suffix), "missing (every colour frame needs depth and pose)")
        poses.append(read_pose_txt(src / f"{stem}.pose.txt"))
    first = cv2.imread(str(src / frames[0][1]), cv2.IMREAD_COLOR)
    if first is None:
        raise FormatError(src / frames[0][1], "cannot decode image (corrupt or not an image)")
    h, w = first.shape[:2]
    camera = Camera(Intrinsics(w, h, fx, fy, cx, cy), 1000.0,
                    SensorSpec("structured_light", 0.075, (0.075, 0.0, 0.0), {"model": "kinect_v1"}))

    if dst.exists() and overwrite:
        ours = {"depth.txt", "rgb.txt", "groundtruth.txt", "camera.json", "convert.json", "depth", "rgb",
                "incomplete.json"}
        other = sorted(p.name for p in dst.iterdir() if p.name not in ours)
        if other:
            raise FormatError(dst, f"--overwrite would delete files that are not a converted sequence "
                                   f"({', '.join(other[:3])}); choose another output folder")
        shutil.rmtree(dst)
    (dst / "rgb").mkdir(parents=True, exist_ok=True)
    (dst / "depth").mkdir(parents=True, exist_ok=True)
    done = 0
    if (dst / "depth.txt").exists():
        done = sum(1 for line in (dst / "depth.txt").read_text().splitlines()
                   if line.strip() and not line.startswith("#"))
        for name in ("rgb.txt", "groundtruth.txt"):  # drop a half-written last frame
            lines = (dst / name).read_text().splitlines() if (dst / name).exists() else []
            head = [x for x in lines if x.startswith("#")]
            data = [x for x in lines if x.strip() and not x.startswith("#")][:done]
            atomic_write_text(dst / name, "\n".join(head + data) + "\n")
    else:
        (dst / "rgb.txt").write_text("# colour images (converted from 7-Scenes)\n# timestamp filename\n")
        (dst / "depth.txt").write_text("# depth images, millimetres (depth_scale 1000)\n# timestamp filename\n")
        (dst / "groundtruth.txt").write_text("# KinectFusion poses from 7-Scenes (camera-to-world)\n"
                                             "# timestamp tx ty tz qx qy qz qw\n")
    write_camera_json(dst / "camera.json", camera)

    from data_tools.outputs import clear_incomplete, mark_incomplete
    mark_incomplete(dst, "realgap data convert-7scenes", done, len(frames))
    n_fixed = 0
    it = range(done, len(frames))
    bar = progress_bar(it, desc=f"convert {src.name}", unit="frame", enabled=progress, initial=done,
                       total=len(frames))
    for k in bar:
        idx, color_name = frames[k]
        stem = f"frame-{idx:06d}"
        ts = f"{t0 + idx / fps:.6f}"
        ext = color_name.rsplit(".", 1)[1]
        depth = cv2.imread(str(src / f"{stem}.depth.png"), cv2.IMREAD_UNCHANGED)
        if depth is None:
            raise FormatError(src / f"{stem}.depth.png", "cannot decode image (corrupt or not an image)")
        if depth.dtype != np.uint16 or depth.ndim != 2:
            raise FormatError(src / f"{stem}.depth.png", f"depth must be single-channel 16-bit, got {depth.dtype} with shape {depth.shape}")
        if depth.shape != (h, w):
            raise FormatError(src / f"{stem}.depth.png", f"depth is {depth.shape[1]}x{depth.shape[0]}, colour is {w}x{h}")
        if (depth == 65535).any():
            depth = np.where(depth == 65535, 0, depth).astype(np.uint16)
            atomic_write_image(dst / "depth" / f"{ts}.png", depth)
            n_fixed += 1
        else:
            shutil.copyfile(src / f"{stem}.depth.png", dst / "depth" / f"{ts}.png")
        shutil.copyfile(src / color_name, dst / "rgb" / f"{ts}.{ext}")
        row = pose_to_tum(poses[k])
        with open(dst / "groundtruth.txt", "a") as f:
            f.write(f"{ts} " + " ".join(f"{x:.9g}" for x in row) + "\n")
        with open(dst / "rgb.txt", "a") as f:
            f.write(f"{ts} rgb/{ts}.{ext}\n")
        with open(dst / "depth.txt", "a") as f:
            f.write(f"{ts} depth/{ts}.png\n")
        mark_incomplete(dst, "realgap data convert-7scenes", k + 1, len(frames))
    result = ConvertResult(str(src), str(dst), len(frames), done, n_fixed, fps)
    atomic_write_json(dst / "convert.json", asdict(result))
    clear_incomplete(dst)
    return result
