"""Streaming reader and writer for RGB-D sequences in the TUM layout (+ camera.json, scene.json).

Layout (../shared/FORMATS.md)::

    SEQ/rgb.txt, depth.txt       "timestamp path" per line, '#' comments
    SEQ/groundtruth.txt          optional, "timestamp tx ty tz qx qy qz qw" (camera-to-world)
    SEQ/rgb/*.png|jpg            8-bit colour
    SEQ/depth/*.png              16-bit, metres = value / depth_scale, 0 = no measurement
    SEQ/camera.json, scene.json  optional extensions

Frames are the depth images; each gets the nearest colour image and ground-truth pose within
``max_dt`` (0.02 s, TUM's rule). Opening a sequence reads only the index files and checks that
every listed file exists; images are decoded one frame at a time, so a 1000-frame sequence
never sits in memory.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from data_tools.camera import Camera, read_camera_json, write_camera_json
from data_tools.errors import FormatError, RealgapError
from data_tools.scene_spec import SceneSpec, read_scene_json, write_scene_json
from data_tools.trajectory import (DEFAULT_MAX_DT, Trajectory, associate, check_timestamps,
                                   read_tum)


@dataclass
class Frame:
    """One RGB-D frame."""

    timestamp: float
    """Seconds."""
    depth: np.ndarray
    """(H, W) float32 z-depth in metres, 0 = no measurement."""
    rgb: np.ndarray | None = None
    """(H, W, 3) uint8 RGB, or None."""
    pose: np.ndarray | None = None
    """(4, 4) float64 camera-to-world, or None when no ground truth is associated."""
    index: int = 0
    """Position of the frame in its sequence."""
    extra: dict = field(default_factory=dict)
    """Optional per-frame arrays (ideal depth, normals, instance ids, IR image...)."""
    encoded: dict = field(default_factory=dict)
    """Optional images already encoded as PNG files (e.g. by a worker process): ``"depth"`` (bytes
    of :func:`encode_depth_png` with ``"depth_scale"``) and/or ``"rgb"`` (:func:`encode_rgb_png`);
    :class:`SequenceWriter` writes them as they are instead of encoding ``depth`` / ``rgb`` again."""


def read_index(path: Path) -> tuple[np.ndarray, list[str]]:
    """Parse rgb.txt/depth.txt: (timestamps (N,), relative paths); validates order."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except UnicodeDecodeError:
        raise FormatError(path, "not a text file") from None
    ts, files = [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.split("#", 1)[0].split()
        if not s:
            continue
        if len(s) < 2:
            raise FormatError(path, f"line {lineno}: expected 'timestamp path', got {line.strip()!r}")
        try:
            ts.append(float(s[0]))
        except ValueError:
            raise FormatError(path, f"line {lineno}: timestamp {s[0]!r} is not a number") from None
        files.append(s[1])
    ts = np.array(ts, dtype=np.float64)
    check_timestamps(ts, path)
    return ts, files


def read_depth_png(path: str | os.PathLike, depth_scale: float,
                   expected_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Decode a 16-bit depth PNG to float32 metres (0 = invalid); clear errors for bad files."""
    import cv2
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "depth image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FormatError(path, "cannot decode image (corrupt or not an image)")
    if img.ndim != 2:
        raise FormatError(path, f"depth image must be single-channel, got {img.shape[2]} channels")
    if img.dtype != np.uint16:
        raise FormatError(path, f"depth image must be 16-bit, got {img.dtype} "
                                f"(an 8-bit PNG cannot hold depth; check the depth scale/export)")
    if expected_shape is not None and img.shape != tuple(expected_shape):
        raise FormatError(path, f"depth image is {img.shape[1]}x{img.shape[0]}, camera says "
                                f"{expected_shape[1]}x{expected_shape[0]}")
    return (img.astype(np.float32) / np.float32(depth_scale))


def read_rgb_image(path: str | os.PathLike, expected_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Decode an 8-bit colour image to (H, W, 3) uint8 RGB."""
    import cv2
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "colour image not found")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FormatError(path, "cannot decode image (corrupt or not an image)")
    if expected_shape is not None and img.shape[:2] != tuple(expected_shape):
        raise FormatError(path, f"colour image is {img.shape[1]}x{img.shape[0]}, camera says "
                                f"{expected_shape[1]}x{expected_shape[0]}")
    return img[:, :, ::-1].copy()


class SequenceReader:
    """Lazy, indexable view of a TUM-layout sequence.

    ``reader[i]`` decodes frame i; iterating streams frames. ``reader.trajectory`` holds the
    ground-truth poses associated to the frames (entries without a pose are NaN in
    ``reader.poses``).
    """

    def __init__(self, path: str | os.PathLike, max_dt: float = DEFAULT_MAX_DT,
                 camera: Camera | None = None, check_files: bool = True):
        self.path = Path(path)
        from data_tools.outputs import check_input_dir
        check_input_dir(self.path, "sequence folder")
        self.max_dt = max_dt
        cam_file = self.path / "camera.json"
        if camera is not None:
            self.camera = camera
        elif cam_file.exists():
            self.camera = read_camera_json(cam_file)
        else:
            self.camera = Camera.tum_default()
        self.has_camera_json = cam_file.exists()
        d_ts, d_files = read_index(self.path / "depth.txt")
        if len(d_ts) == 0:
            raise FormatError(self.path / "depth.txt", "no depth frames listed")
        if check_files:
            self._check_listed(self.path / "depth.txt", d_files)
        rgb_txt = self.path / "rgb.txt"
        self.rgb_files: list[str | None]
        r_ts, r_files = read_index(rgb_txt) if rgb_txt.exists() else (np.zeros(0), [])
        if len(r_ts):                  # an rgb.txt without entries (a depth-only writer's header) = no colour
            if check_files:
                self._check_listed(rgb_txt, r_files)
            id_, ir = associate(d_ts, r_ts, max_dt)
            if len(id_) == 0:
                raise FormatError(rgb_txt, f"no colour timestamp lies within {max_dt} s of a depth timestamp")
            d_ts = d_ts[id_]
            d_files = [d_files[i] for i in id_]
            self.rgb_files = [r_files[j] for j in ir]
            self.rgb_timestamps = r_ts[ir]
        else:
            self.rgb_files = [None] * len(d_ts)
            self.rgb_timestamps = np.full(len(d_ts), np.nan)
        self.timestamps = d_ts
        self.depth_files = d_files
        self.mask_files: list[str | None] = [None] * len(d_ts)
        mask_txt = self.path / "mask.txt"
        self.has_masks = mask_txt.exists()
        """True when the sequence has per-frame masks (FORMATS.md section 4): only masked-in pixels
        are compared; a frame without an associated mask compares nothing."""
        if self.has_masks:
            m_ts, m_files = read_index(mask_txt)
            if check_files:
                self._check_listed(mask_txt, m_files)
            im, jm = associate(d_ts, m_ts, max_dt)
            for a, b in zip(im, jm):
                self.mask_files[a] = m_files[b]
        self.poses = np.full((len(d_ts), 4, 4), np.nan)
        gt = self.path / "groundtruth.txt"
        self.has_groundtruth = gt.exists()
        if self.has_groundtruth:
            self.groundtruth = read_tum(gt)
            ia, ib = associate(d_ts, self.groundtruth.timestamps, max_dt)
            self.poses[ia] = self.groundtruth.poses[ib]
        self._scene: SceneSpec | None = None

    def _check_listed(self, index_file: Path, files: list[str]) -> None:
        for rel in files:
            if not (self.path / rel).is_file():
                raise FormatError(index_file, f"lists {rel!r}, which does not exist")

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def intrinsics(self):
        return self.camera.intrinsics

    @property
    def has_scene(self) -> bool:
        return (self.path / "scene.json").exists()

    @property
    def scene(self) -> SceneSpec:
        """The reference geometry (scene.json), loaded and validated on first use."""
        if self._scene is None:
            if not self.has_scene:
                raise FormatError(self.path, "sequence has no scene.json (reference geometry)")
            self._scene = read_scene_json(self.path / "scene.json")
        return self._scene

    @property
    def trajectory(self) -> Trajectory:
        """Ground-truth poses of the frames that have one."""
        ok = np.all(np.isfinite(self.poses.reshape(len(self), -1)), axis=1)
        if not ok.any():
            raise FormatError(self.path, "sequence has no ground-truth poses associated to its frames")
        return Trajectory(self.timestamps[ok], self.poses[ok])

    def read_depth(self, i: int) -> np.ndarray:
        return read_depth_png(self.path / self.depth_files[i], self.camera.depth_scale,
                              self.intrinsics.shape)

    def read_mask(self, i: int) -> np.ndarray | None:
        """(H, W) bool mask of frame i (True = compare this pixel); None when the sequence has no
        masks; all False for a frame without an associated mask."""
        if not self.has_masks:
            return None
        rel = self.mask_files[i]
        if rel is None:
            return np.zeros(self.intrinsics.shape, bool)
        import cv2
        p = self.path / rel
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if m is None:
            raise FormatError(p, "cannot decode mask image (corrupt or not an image)")
        if m.ndim != 2 or m.dtype != np.uint8:
            raise FormatError(p, f"a mask is an 8-bit single-channel PNG, got {m.dtype} with shape {m.shape}")
        if m.shape != self.intrinsics.shape:
            raise FormatError(p, f"mask is {m.shape[1]}x{m.shape[0]}, camera.json says "
                                 f"{self.intrinsics.width}x{self.intrinsics.height}")
        return m > 127

    def read_rgb(self, i: int) -> np.ndarray | None:
        rel = self.rgb_files[i]
        return None if rel is None else read_rgb_image(self.path / rel)

    def __getitem__(self, i: int) -> Frame:
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        pose = self.poses[i]
        return Frame(float(self.timestamps[i]), self.read_depth(i), self.read_rgb(i),
                     pose.copy() if np.all(np.isfinite(pose)) else None, i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]


def sequence_info(path: str | os.PathLike) -> dict:
    """What ``data info`` prints: frame count, duration, intrinsics, depth scale, sensor block,
    frames with a pose and the scene's size (reading the index and calibration files). An
    unfinished output folder of another command (a diagnosis, a batch report) that a killed run
    left is named as such instead of "depth.txt not found"."""
    from data_tools.outputs import incomplete_text, read_incomplete
    marker = read_incomplete(path)
    if marker is not None and not (Path(path) / "depth.txt").is_file():
        raise FormatError(path, f"{incomplete_text(marker)}; no sequence in it yet")
    seq = SequenceReader(path)
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
    marker = read_incomplete(seq.path)
    info["complete"] = marker is None
    if marker is not None:
        info["incomplete"] = incomplete_text(marker)
    return info


def link_or_copy(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Hard-link ``src`` to ``dst`` (a copy across file systems); an existing ``dst`` is kept.

    Used to put a sequence's images beside a derived sequence without doubling the disk use."""
    import shutil
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        return
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def spread_indices(n_total: int, n: int | None) -> list[int]:
    """``n`` indices evenly spread over ``range(n_total)``, first and last included (all of them
    when ``n`` is None or >= n_total; none when n is 0)."""
    if n is None or n >= n_total:
        return list(range(n_total))
    return sorted(set(np.linspace(0, n_total - 1, int(n)).round().astype(int).tolist()))


def encode_depth(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres -> uint16 PNG values; NaN, <= 0 and values beyond the uint16 range become 0."""
    d = np.multiply(depth_m, depth_scale, dtype=np.float64)   # a new array, worked on in place
    np.rint(d, out=d)
    with np.errstate(invalid="ignore"):
        ok = (d > 0) & (d <= 65535)                    # NaN and +-inf fail both tests
    np.copyto(d, 0.0, where=~ok)
    return d.astype(np.uint16)


def encode_depth_png(depth_m: np.ndarray, depth_scale: float) -> bytes:
    """The bytes of the 16-bit PNG file :class:`SequenceWriter` writes for ``depth_m``."""
    from data_tools.png import encode_png
    return encode_png(encode_depth(depth_m, depth_scale))


def encode_rgb_png(rgb: np.ndarray) -> bytes:
    """The bytes of the PNG file :class:`SequenceWriter` writes for an (H, W, 3) uint8 RGB image
    (:func:`data_tools.png.encode_png`)."""
    from data_tools.png import encode_png
    return encode_png(rgb)


def _link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link ``src`` to ``dst`` (replacing it), copying where the file system cannot link."""
    import shutil
    tmp = dst.with_name(f".{dst.name}.tmp{os.getpid()}")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def write_depth_png(path: str | os.PathLike, depth_m: np.ndarray, depth_scale: float) -> None:
    """Write depth (metres) as a 16-bit PNG (:func:`encode_depth`; the inverse of
    :func:`read_depth_png`); RealgapError naming the file when it cannot be written."""
    from data_tools.results import atomic_write_image
    atomic_write_image(path, encode_depth(depth_m, depth_scale))


class SequenceWriter:
    """Write a TUM-layout sequence frame by frame.

    Index files are appended and flushed after every frame, so an interrupted job keeps every
    frame it finished; ``resume=True`` reopens such a sequence and reports how many frames
    are already there (``len(writer)``) so the caller can skip them.

    With ``expected_frames`` the folder carries the unfinished marker of
    :mod:`data_tools.outputs` (``incomplete.json``: frames written / expected, updated after every
    frame) until that many frames are written; ``command`` names the writer in it.
    """

    def __init__(self, path: str | os.PathLike, camera: Camera, scene: SceneSpec | None = None,
                 rgb_ext: str = "png", resume: bool = False, overwrite: bool = False,
                 expected_frames: int | None = None, command: str = "realgap"):
        from data_tools.outputs import check_output_dir
        self.path = check_output_dir(path, what="sequence folder")
        self.camera = camera
        self.expected_frames = expected_frames
        self.command = command
        self.rgb_ext = rgb_ext
        exists = (self.path / "depth.txt").exists()
        if exists and not (resume or overwrite):
            raise RealgapError(f"{self.path}: already holds a sequence (use --overwrite or --resume)")
        if exists and overwrite:
            for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
                (self.path / name).unlink(missing_ok=True)
            exists = False
        (self.path / "rgb").mkdir(parents=True, exist_ok=True)
        (self.path / "depth").mkdir(parents=True, exist_ok=True)
        self._timestamps: list[float] = []
        if exists and resume:
            d_ts, _ = read_index(self.path / "depth.txt")
            self._timestamps = list(d_ts)
            self._truncate_to_complete()
        else:
            for name, head in (("rgb.txt", "rgb"), ("depth.txt", "depth")):
                (self.path / name).write_text(f"# {head} images\n# timestamp filename\n")
        write_camera_json(self.path / "camera.json", camera)
        if scene is not None:
            write_scene_json(self.path, scene)
        self._gt_path = self.path / "groundtruth.txt"
        self._update_marker()

    MARKER_INTERVAL_S = 0.5
    """The unfinished marker's frame count is rewritten at most this often (it is for people and
    ``data info``; resuming reads the index files)."""

    def _update_marker(self) -> None:
        if self.expected_frames is None:
            return
        import time
        from data_tools.outputs import clear_incomplete, mark_incomplete
        if len(self._timestamps) >= self.expected_frames:
            clear_incomplete(self.path)
        elif time.monotonic() - getattr(self, "_marker_t", -1e9) >= self.MARKER_INTERVAL_S:
            mark_incomplete(self.path, self.command, len(self._timestamps), self.expected_frames)
            self._marker_t = time.monotonic()

    def _truncate_to_complete(self) -> None:
        """After an interruption rgb.txt/groundtruth.txt may hold one entry more than depth.txt
        (they are written first): drop entries after the last complete frame."""
        last = self._timestamps[-1] if self._timestamps else -np.inf
        for name in ("rgb.txt", "groundtruth.txt"):
            p = self.path / name
            if not p.exists():
                continue
            keep = []
            for line in p.read_text().splitlines():
                s = line.split("#", 1)[0].split()
                if not s or float(s[0]) <= last + 1e-9:
                    keep.append(line)
            from data_tools.results import atomic_write_text
            atomic_write_text(p, "\n".join(keep) + "\n")

    def __len__(self) -> int:
        return len(self._timestamps)

    def __enter__(self) -> "SequenceWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    last_rgb_path: Path | None = None
    """The colour file of the last frame written (None: it had no colour)."""

    def write(self, frame: Frame, rgb_link: str | os.PathLike | None = None) -> None:
        """Append one frame (images first, then index lines, so the index never lists a missing file).

        ``rgb_link``: an existing file holding exactly ``frame.rgb`` encoded the same way (e.g. the
        same frame of another sequence): it is hard-linked (copied where links are not possible)
        instead of encoding the image again."""
        t = float(frame.timestamp)
        if self._timestamps and t <= self._timestamps[-1]:
            raise RealgapError(f"{self.path}: frame timestamp {t:.6f} is not after the previous one "
                               f"({self._timestamps[-1]:.6f})")
        h, w = self.camera.intrinsics.shape
        if frame.depth.shape != (h, w):
            raise RealgapError(f"{self.path}: frame depth is {frame.depth.shape}, camera is {(h, w)}")
        name = f"{t:.6f}"
        depth_rel = f"depth/{name}.png"
        enc = frame.encoded or {}
        from data_tools.results import atomic_write_bytes
        if enc.get("depth") is not None and enc.get("depth_scale") == self.camera.depth_scale:
            atomic_write_bytes(self.path / depth_rel, enc["depth"])
        else:
            write_depth_png(self.path / depth_rel, frame.depth, self.camera.depth_scale)
        rgb_rel = None
        self.last_rgb_path = None
        if frame.rgb is not None:
            rgb_rel = f"rgb/{name}.{self.rgb_ext}"
            if rgb_link is not None and Path(rgb_link).suffix == Path(rgb_rel).suffix:
                _link_or_copy(Path(rgb_link), self.path / rgb_rel)
            elif self.rgb_ext == "png":
                atomic_write_bytes(self.path / rgb_rel, enc["rgb"] if enc.get("rgb") is not None else
                                   encode_rgb_png(frame.rgb))
            else:
                from data_tools.results import atomic_write_image
                atomic_write_image(self.path / rgb_rel, frame.rgb[:, :, ::-1])
            self.last_rgb_path = self.path / rgb_rel
        if frame.pose is not None:
            from data_tools.geometry import pose_to_tum
            if not np.all(np.isfinite(frame.pose)):
                raise RealgapError(f"{self.path}: frame {t:.6f} has a NaN pose")
            row = pose_to_tum(frame.pose)
            if not self._gt_path.exists():
                self._gt_path.write_text("# ground truth trajectory (camera-to-world)\n# timestamp tx ty tz qx qy qz qw\n")
            with open(self._gt_path, "a") as f:
                f.write(f"{name} " + " ".join(f"{x:.9g}" for x in row) + "\n")
        if rgb_rel is not None:
            with open(self.path / "rgb.txt", "a") as f:
                f.write(f"{name} {rgb_rel}\n")
        with open(self.path / "depth.txt", "a") as f:
            f.write(f"{name} {depth_rel}\n")
        self._timestamps.append(t)
        self._update_marker()

    def close(self) -> None:
        pass

