"""Raw Kinect v1 captures -> the TUM layout (``realgap data convert-kinect-raw``).

Input folder: frames ``NNNN-d.pgm`` (16-bit PGM of the raw 11-bit disparity the device reports;
2047 = no measurement) and optionally ``NNNN-c.ppm|png|jpg`` colour, plus a calibration file in
the OpenCV-YAML layout of the Kinect calibration toolbox of Herrera, Kannala & Heikkila 2012:

    dK        3x3 depth-camera matrix (pixels)
    dkc       1x5 distortion of the depth camera (k1 k2 p1 p2 k3, OpenCV order)
    dc        [c0, c1]: depth z = 1 / (c0 + c1 d), metres, from disparity d
    dc_alpha  [a0, a1]: decay of the disparity distortion with disparity
    dc_beta   HxW map beta(u, v): the spatially varying disparity distortion

Herrera's model of the device's disparity error: the measured disparity d relates to the
undistorted one by d_u = d + beta(u, v) exp(a0 - a1 d). Without ``undistort_disparity`` the
depth is computed from the raw d (the device's own behaviour, distortion included: what the
sensor lab should model); with it from d_u (a calibrated depth, as the toolbox corrects it).

Output: ``depth/<t>.png`` (16-bit, depth_scale 5000: 0.2 mm steps up to 13.1 m), ``rgb/<t>.png``
when every frame has colour (PPM converted to PNG, PNG/JPG copied byte for byte; if only some
have, colour is left out with a warning, so that the TUM association drops no depth frame), ``depth.txt``,
``rgb.txt``, ``camera.json`` (intrinsics from ``dK``, distortion from ``dkc``, the kinect_v1
sensor block with the disparity calibration kept under ``raw_disparity``) and ``convert.json``.
Timestamps come from the frame numbers: frame N at N / fps seconds (default 30 Hz). There are no
poses (``groundtruth.txt`` is absent): ``data make-reference --plane`` can make them for captures
of a flat target. An interrupted conversion continues when re-run.
"""
from __future__ import annotations

import os
import re
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError

__all__ = ["KinectCalibration", "read_kinect_calibration", "disparity_to_depth", "convert_kinect_raw",
           "INVALID_DISPARITY", "KINECT_RAW_DEPTH_SCALE"]

INVALID_DISPARITY = 2047
"""The raw disparity value of a pixel without measurement."""
KINECT_RAW_DEPTH_SCALE = 5000.0
"""Depth PNG units per metre of the converted sequence."""
_DEPTH_RE = re.compile(r"^(\d+)-d\.pgm$")


@dataclass
class KinectCalibration:
    """Herrera et al. 2012 depth-camera calibration (see the module docstring)."""

    K: np.ndarray
    """(3, 3) depth-camera matrix, pixels."""
    distortion: np.ndarray
    """(5,) k1 k2 p1 p2 k3."""
    dc: tuple[float, float]
    """(c0, c1): z = 1 / (c0 + c1 d), metres."""
    alpha: tuple[float, float]
    """(a0, a1) of the distortion decay exp(a0 - a1 d)."""
    beta: np.ndarray | None
    """(H, W) disparity distortion map, or None (no distortion model)."""


def read_kinect_calibration(path: str | os.PathLike) -> KinectCalibration:
    """Read the OpenCV-YAML calibration file; one-line FormatError naming the file and the key."""
    import cv2
    p = Path(path)
    from data_tools.outputs import check_input_file
    check_input_file(p, "calibration file", "--calib")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:     # OpenCV's parser error surfaces as either
        msg = str(getattr(e, "__cause__", None) or e).strip().splitlines()
        raise FormatError(p, f"not an OpenCV YAML/XML file ({msg[-1][:80] if msg else 'parse error'})") from None
    if not fs.isOpened():
        raise FormatError(p, "not an OpenCV YAML/XML file")

    def mat(key: str, required: bool = True):
        node = fs.getNode(key)
        if node.empty():
            if required:
                raise FormatError(p, f"no {key!r} in the calibration (needs dK, dc; optional dkc, dc_alpha, dc_beta)")
            return None
        m = node.mat()
        if m is None:
            vals = [node.at(i).real() for i in range(node.size())] if node.isSeq() else [node.real()]
            m = np.asarray(vals, float)
        m = np.asarray(m, float)
        if not np.all(np.isfinite(m)):
            raise FormatError(p, f"{key!r} holds NaN or infinite values")
        return m

    K = mat("dK")
    if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise FormatError(p, f"'dK' must be a 3x3 camera matrix with positive focal lengths, got shape {K.shape}")
    dkc = mat("dkc", False)
    dkc = np.zeros(5) if dkc is None else dkc.reshape(-1)
    if dkc.size not in (4, 5):
        raise FormatError(p, f"'dkc' must hold 4 or 5 distortion coefficients, got {dkc.size}")
    dc = mat("dc").reshape(-1)
    if dc.size != 2 or dc[1] == 0:
        raise FormatError(p, f"'dc' must be [c0, c1] with c1 != 0 (z = 1 / (c0 + c1 d)), got {dc.tolist()}")
    alpha = mat("dc_alpha", False)
    alpha = (0.0, 0.0) if alpha is None else tuple(float(x) for x in alpha.reshape(-1)[:2])
    beta = mat("dc_beta", False)
    fs.release()
    return KinectCalibration(K, np.pad(dkc, (0, 5 - dkc.size)), (float(dc[0]), float(dc[1])), alpha,
                             None if beta is None else beta.astype(np.float64))


def disparity_to_depth(raw: np.ndarray, calib: KinectCalibration, undistort: bool = False) -> np.ndarray:
    """(H, W) float32 metres (0 = no measurement) of a raw disparity image (uint16, 2047 = none)."""
    raw = np.asarray(raw)
    d = raw.astype(np.float64)
    valid = raw < INVALID_DISPARITY
    if undistort and calib.beta is not None:
        a0, a1 = calib.alpha
        d = d + calib.beta * np.exp(a0 - a1 * d)
    denom = calib.dc[0] + calib.dc[1] * d
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(valid & (denom > 0), 1.0 / denom, 0.0)
    z[~np.isfinite(z) | (z < 0)] = 0.0
    return z.astype(np.float32)


@dataclass
class RawConvertResult:
    src: str
    dst: str
    frames: int
    skipped_existing: int
    colour_frames: int
    undistorted: bool
    fps: float


def convert_kinect_raw(src: str | os.PathLike, dst: str | os.PathLike, calib_path: str | os.PathLike,
                       undistort_disparity: bool = False, fps: float = 30.0, overwrite: bool = False,
                       progress: bool = True) -> RawConvertResult:
    """Convert the raw captures in ``src`` into a TUM-layout sequence ``dst`` (module docstring)."""
    import cv2

    from data_tools.camera import Camera, Intrinsics, SensorSpec, write_camera_json
    from data_tools.outputs import check_input_dir, check_output_dir, clear_incomplete, mark_incomplete
    from data_tools.progress import progress_bar
    from data_tools.results import atomic_write_image, atomic_write_json
    src = check_input_dir(src, "raw capture folder")
    dst = check_output_dir(dst, what="output sequence folder", finished="convert.json", overwrite=overwrite)
    if not fps > 0:
        raise FormatError(None, f"--fps must be > 0, got {fps}")
    calib = read_kinect_calibration(calib_path)
    frames = sorted((int(m.group(1)), f) for f in os.listdir(src) if (m := _DEPTH_RE.match(f)))
    if not frames:
        raise FormatError(src, "no raw depth frames (NNNN-d.pgm) found")
    nums = [n for n, _ in frames]
    if len(set(nums)) != len(nums):
        dup = next(n for n in nums if nums.count(n) > 1)
        raise FormatError(src, f"frame number {dup} appears twice (e.g. 0012-d.pgm and 12-d.pgm)")
    def colour_of(name: str) -> Path | None:
        cands = [src / name.replace("-d.pgm", f"-c.{ext}") for ext in ("png", "jpg", "ppm")]
        return next((c for c in cands if c.is_file()), None)
    with_colour = [colour_of(name) is not None for _, name in frames]
    use_colour = all(with_colour)
    if any(with_colour) and not use_colour:
        from data_tools.errors import warn
        missing = next(name for (_, name), c in zip(frames, with_colour) if not c)
        warn(f"{src}: {with_colour.count(False)} of {len(frames)} frames have no colour image (e.g. "
                      f"{missing}); the sequence is written without colour so that no depth frame is dropped")
    first = cv2.imread(str(src / frames[0][1]), cv2.IMREAD_UNCHANGED)
    if first is None or first.dtype != np.uint16 or first.ndim != 2:
        raise FormatError(src / frames[0][1], "not a 16-bit single-channel PGM of raw disparity")
    h, w = first.shape
    if calib.beta is not None and calib.beta.shape != (h, w):
        raise FormatError(calib_path, f"'dc_beta' is {calib.beta.shape[1]}x{calib.beta.shape[0]}, the frames are {w}x{h}")
    K = calib.K
    camera = Camera(Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                               tuple(float(x) for x in calib.distortion)), KINECT_RAW_DEPTH_SCALE,
                    SensorSpec("structured_light", 0.075, (0.075, 0.0, 0.0),
                               {"model": "kinect_v1", "raw_disparity": {
                                   "dc": list(calib.dc), "dc_alpha": list(calib.alpha),
                                   "has_beta": calib.beta is not None, "undistorted": bool(undistort_disparity)}}))
    if overwrite and dst.exists():
        for name in ("depth", "rgb"):
            shutil.rmtree(dst / name, ignore_errors=True)
        for name in ("depth.txt", "rgb.txt", "convert.json", "camera.json"):
            (dst / name).unlink(missing_ok=True)
    (dst / "depth").mkdir(parents=True, exist_ok=True)
    done = 0
    if (dst / "depth.txt").exists():
        done = sum(1 for ln in (dst / "depth.txt").read_text().splitlines() if ln.strip() and not ln.startswith("#"))
        lines = (dst / "rgb.txt").read_text().splitlines() if (dst / "rgb.txt").exists() else []
        keep_ts = {ln.split()[0] for ln in (dst / "depth.txt").read_text().splitlines()
                   if ln.strip() and not ln.startswith("#")}
        if lines:        # drop a colour line written after the last finished depth line
            (dst / "rgb.txt").write_text("\n".join(x for x in lines if x.startswith("#") or not x.strip()
                                                   or x.split()[0] in keep_ts) + "\n")
    else:
        (dst / "depth.txt").write_text(f"# depth from raw Kinect v1 disparity (depth_scale {KINECT_RAW_DEPTH_SCALE:g}"
                                       f"{', disparity undistorted' if undistort_disparity else ''})\n"
                                       "# timestamp filename\n")
    write_camera_json(dst / "camera.json", camera)
    mark_incomplete(dst, "realgap data convert-kinect-raw", done, len(frames))
    n_colour = 0
    bar = progress_bar(range(done, len(frames)), desc=f"convert {src.name}", unit="frame", enabled=progress,
                       initial=done, total=len(frames))
    for k in bar:
        num, name = frames[k]
        ts = f"{num / fps:.6f}"
        raw = cv2.imread(str(src / name), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise FormatError(src / name, "cannot decode image (corrupt or not a PGM)")
        if raw.dtype != np.uint16 or raw.shape != (h, w):
            raise FormatError(src / name, f"expected a {w}x{h} 16-bit PGM of raw disparity, got {raw.dtype} "
                                          f"{raw.shape[1] if raw.ndim > 1 else '?'}x{raw.shape[0]}")
        if int(raw.max()) > INVALID_DISPARITY:
            raise FormatError(src / name, f"values up to {int(raw.max())}: raw Kinect v1 disparity is 11-bit "
                                          f"(0..2047) - is this already depth in millimetres?")
        z = disparity_to_depth(raw, calib, undistort_disparity)
        from data_tools.sequence import encode_depth
        atomic_write_image(dst / "depth" / f"{ts}.png", encode_depth(z, KINECT_RAW_DEPTH_SCALE))
        colour = colour_of(name) if use_colour else None
        if colour is not None:
            (dst / "rgb").mkdir(exist_ok=True)
            if not (dst / "rgb.txt").exists():
                (dst / "rgb.txt").write_text("# colour images (raw Kinect v1 capture)\n# timestamp filename\n")
            out_ext = "png" if colour.suffix.lower() == ".ppm" else colour.suffix.lower().lstrip(".")
            if colour.suffix.lower() == ".ppm":
                img = cv2.imread(str(colour), cv2.IMREAD_COLOR)
                if img is None:
                    raise FormatError(colour, "cannot decode image (corrupt or not a PPM)")
                atomic_write_image(dst / "rgb" / f"{ts}.png", img)
            else:
                shutil.copyfile(colour, dst / "rgb" / f"{ts}.{out_ext}")
            with open(dst / "rgb.txt", "a") as f:
                f.write(f"{ts} rgb/{ts}.{out_ext}\n")
            n_colour += 1
        with open(dst / "depth.txt", "a") as f:
            f.write(f"{ts} depth/{ts}.png\n")
        mark_incomplete(dst, "realgap data convert-kinect-raw", k + 1, len(frames))
    result = RawConvertResult(str(src), str(dst), len(frames), done, n_colour, bool(undistort_disparity), fps)
    atomic_write_json(dst / "convert.json", asdict(result))
    clear_incomplete(dst)
    return result
