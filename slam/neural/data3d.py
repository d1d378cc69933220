"""3D worlds for the neural memory (thesis 4.4.3): RGB-D sequences of a ground robot in simulated rooms.

Training and test worlds are ``procedural_room`` scenes (a random furnished room per seed; test
seeds start at :data:`TEST_SEED0`, never used in training) explored along ``planar`` trajectories
(camera 1 m above the floor, pitch -10 deg, moving on the floor with yaw turns) and measured by
the full ``kinect_v1`` simulator (``synth sequence --sensor kinect_v1``): the memory is trained on
depth with the sensor's holes, noise and quantisation, never on ideal depth.

Each frame becomes (:func:`frame_arrays`):

* an image (4, H, W) in [-1, 1]: RGB and depth (0 .. ``max_range_m`` -> -1 .. 1; no measurement
  = -1), resized from 640 x 480 by block averaging (depth: the median of the valid pixels of each
  block, holes where fewer than a quarter are valid);
* the flat egocentric cell of each of its pixels (:func:`slam.neural.geometry3d.egocentric_cells`),
  using the level frame of the sequence's first pose (height, pitch, roll are fixed).

A training sample is ``steps`` frames ``stride`` apart (``stride`` drawn in ``stride_range``) of one
sequence; its allocentric poses (cells, heading index) are those of the frames in the first
frame's egocentric grid, rounded to the grid (the memory's resolution, as MapNet).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from data_tools.errors import FormatError
from slam.neural.config import World3DConfig

__all__ = ["default_worlds_dir", "view_geometry", "cache_name", "TEST_SEED0", "frame_arrays", "load_sequence_arrays", "build_worlds", "WorldBank",
           "sequence_geometry"]

TEST_SEED0 = 100_000
"""First ``procedural_room`` seed of the test worlds (training uses seeds 0 .. rooms - 1)."""


def block_resize(rgb: np.ndarray | None, depth: np.ndarray, H: int, W: int):
    """(colour (H, W, 3) float32 in [0, 1], depth (H, W) metres, 0 = none) of a full-size frame: colour by area
    averaging, depth by the median of each block's valid pixels (none where fewer than a quarter are valid)."""
    import cv2
    h0, w0 = depth.shape
    by, bx = h0 // H, w0 // W
    d = depth[:by * H, :bx * W].reshape(H, by, W, bx).transpose(0, 2, 1, 3).reshape(H, W, by * bx).astype(np.float32)
    valid = d > 0
    dn = np.where(valid, d, np.nan)
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(dn, axis=2)
    med = np.where(valid.mean(2) >= 0.25, med, 0.0)
    med = np.nan_to_num(med, nan=0.0)
    if rgb is None:
        col = np.zeros((H, W, 3), np.float32)
    else:
        col = cv2.resize(rgb, (W, H), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    return col, med


def frame_arrays(rgb: np.ndarray | None, depth_m: np.ndarray, intr, R_c_L: np.ndarray, cfg: World3DConfig):
    """(image (4, H, W) float32 in [-1, 1], cells (r, H * W) int64: the pixels' cells in the egocentric grid
    turned by k / r of a turn, k = 0 .. r - 1) of one frame (see the module docstring)."""
    from slam.neural.geometry3d import downsample_intrinsics, egocentric_cells
    col, d = block_resize(rgb, depth_m, cfg.image_h, cfg.image_w)
    small = downsample_intrinsics(intr, cfg.image_w, cfg.image_h)
    cells = egocentric_cells(d, small, R_c_L, cfg.cell_m, cfg.view, cfg.max_range_m, rotations=cfg.rotations)
    dch = np.where(d > 0, np.clip(d / cfg.max_range_m, 0, 1) * 2 - 1, -1.0)
    img = np.concatenate([np.transpose(col, (2, 0, 1)) * 2 - 1, dch[None]], 0).astype(np.float32)
    return img, cells


def view_geometry(intr, T0: np.ndarray | None, cfg: World3DConfig):
    """(R_c_L, view wedge (q, q) bool) of a camera with full-size intrinsics ``intr`` whose first pose is
    ``T0``: the level frame of T0 (an upright camera when None) and the view field of the network's image."""
    from slam.neural.geometry3d import downsample_intrinsics, level_rotation, view_wedge
    R_c_L = level_rotation(T0) if T0 is not None else np.eye(3)
    small = downsample_intrinsics(intr, cfg.image_w, cfg.image_h)
    return R_c_L, view_wedge(small, R_c_L, cfg.cell_m, cfg.view, cfg.max_range_m)


def sequence_geometry(reader, cfg: World3DConfig):
    """(R_c_L, view wedge (q, q) bool, first pose or None) of a sequence: :func:`view_geometry` of its first
    ground-truth pose."""
    poses = reader.poses
    ok = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    T0 = poses[int(np.argmax(ok))] if ok.any() else None
    return (*view_geometry(reader.intrinsics, T0, cfg), T0)


def cache_name(cfg: World3DConfig) -> str:
    """File name of a sequence's prepared arrays (:func:`load_sequence_arrays`) for this configuration."""
    return f"neural_{cfg.image_w}x{cfg.image_h}_q{cfg.view}_c{cfg.cell_m:g}_m{cfg.max_range_m:g}_r{cfg.rotations}.npz"


def load_sequence_arrays(seq_dir: str | Path, cfg: World3DConfig, cache: str | Path | None = None,
                         progress: bool = False) -> dict:
    """{images (N, 4, H, W) float16, cells (N, r, H*W) int16, poses (N, 4, 4), timestamps (N,), wedge (q, q)}
    of a sequence folder, cached in ``cache`` (an .npz, rebuilt when missing)."""
    from data_tools.sequence import SequenceReader
    if cache is not None and Path(cache).is_file():
        with np.load(cache) as z:
            return {k: z[k] for k in z.files}
    reader = SequenceReader(seq_dir)
    R_c_L, wedge, _ = sequence_geometry(reader, cfg)
    imgs, cells = [], []
    it = range(len(reader))
    if progress:
        from data_tools.progress import progress_bar
        it = progress_bar(it, desc=f"preparing {Path(seq_dir).name}", unit="frame")
    for i in it:
        img, c = frame_arrays(reader.read_rgb(i), reader.read_depth(i), reader.intrinsics, R_c_L, cfg)
        imgs.append(img.astype(np.float16))
        cells.append(c.astype(np.int16 if cfg.view ** 2 < 32767 else np.int32))
    out = {"images": np.stack(imgs), "cells": np.stack(cells), "poses": reader.poses.copy(),
           "timestamps": reader.timestamps.copy(), "wedge": wedge}
    if cache is not None:
        from data_tools.results import atomic_write_bytes
        import io
        buf = io.BytesIO()
        np.savez(buf, **out)
        atomic_write_bytes(Path(cache), buf.getvalue())
    return out


Simulator = Callable[[int, int, Path], None]
"""``simulate(seed, frames, out)``: write the planar kinect_v1 sequence of ``procedural_room`` ``seed`` with
``frames`` frames into ``out`` (resuming an unfinished one). ``slam`` does not import ``synth``: the
application passes :func:`app.pipelines.simulate_planar_room`."""


def build_worlds(folder: str | Path, cfg: World3DConfig, split: str = "train", simulate: Simulator | None = None,
                 log: Callable[[str], None] | None = None) -> list[Path]:
    """The ``split`` rooms' sequences in ``folder`` (``train_NNN`` / ``test_NNN``), simulated by ``simulate``
    where missing or unfinished. Returns the sequence folders."""
    folder = Path(folder)
    n = cfg.rooms if split == "train" else cfg.test_rooms
    seed0 = 0 if split == "train" else TEST_SEED0
    out = []
    for i in range(n):
        seq = folder / f"{split}_{i:03d}"
        done = (seq / "groundtruth.txt").is_file() and not (seq / "incomplete.json").exists() and \
            (seq / "depth.txt").is_file()
        if not done:
            if simulate is None:
                raise FormatError(seq, f"{split} room {i} is not simulated yet (run 'realgap neural train --mode 3d' "
                                       "or pass --worlds to a folder that has them)")
            if log is not None:
                log(f"simulating {split} room {i + 1}/{n} (kinect_v1, {cfg.frames} frames) in {seq}")
            simulate(seed0 + i, cfg.frames, seq)
        out.append(seq)
    return out


def default_worlds_dir(cfg: World3DConfig) -> Path:
    """Where the simulated rooms live unless a folder is given: ``$REALGAP_CACHE`` (default
    ``~/.cache/realgap``) ``/neural_worlds/f<frames>`` - shared by training and evaluation (the rooms
    depend only on the seeds and the frame count)."""
    import os
    return Path(os.environ.get("REALGAP_CACHE", "~/.cache/realgap")).expanduser() / "neural_worlds" / f"f{cfg.frames}"


class WorldBank:
    """The prepared sequences of one split and the sampler of training/test samples."""

    def __init__(self, seqs: list[dict], cfg: World3DConfig, folders: list[Path] | None = None):
        if not seqs:
            raise FormatError("worlds", "no sequences to sample from")
        self.seqs = seqs
        self.cfg = cfg
        self.folders = list(folders or [])
        """The sequence folders of ``seqs`` (when known)."""
        self.wedge = seqs[0]["wedge"].astype(bool)

    def allocentric(self, poses: np.ndarray) -> np.ndarray:
        """(T, 3) int64 allocentric (row, col, heading index) of (T, 4, 4) poses, rounded to the grid."""
        from slam.neural.geometry3d import grid_pose
        return np.array([grid_pose(poses[0], P, self.cfg.cell_m, self.cfg.rotations) for P in poses], np.int64)

    def exact(self, poses: np.ndarray) -> np.ndarray:
        """(T, 3) float64 allocentric (row, col in cells, heading in units of 2 pi / r) of (T, 4, 4) poses, not
        rounded (recall reads the memory at them, rounded)."""
        from slam.neural.geometry3d import planar_relative
        step = 2 * np.pi / self.cfg.rotations
        out = np.array([planar_relative(poses[0], P, self.cfg.cell_m) for P in poses], np.float64)
        out[:, 2] /= step
        return out

    def sample(self, rng: np.random.Generator, batch: int, steps: int):
        """(images (B, T, 4, H, W) float32, cells (B, T, r, H*W) int64, allocentric (B, T, 3) int64,
        poses (B, T, 4, 4))."""
        imgs, cells, allo, poses = [], [], [], []
        for _ in range(batch):
            s = self.seqs[int(rng.integers(len(self.seqs)))]
            stride = int(rng.integers(self.cfg.stride_min, self.cfg.stride_max + 1))
            N = len(s["images"])
            span = stride * (steps - 1)
            if span >= N:
                stride = max(1, (N - 1) // max(steps - 1, 1))
                span = stride * (steps - 1)
            a = int(rng.integers(0, N - span))
            idx = a + stride * np.arange(steps)
            if rng.random() < 0.5:          # walk the path backwards too
                idx = idx[::-1]
            imgs.append(s["images"][idx].astype(np.float32))
            cells.append(s["cells"][idx].astype(np.int64))
            poses.append(s["poses"][idx])
            allo.append(self.allocentric(s["poses"][idx]))
        return np.stack(imgs), np.stack(cells), np.stack(allo), np.stack(poses)
