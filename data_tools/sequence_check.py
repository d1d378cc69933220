"""Deep validation of a TUM-layout sequence (``realgap data info --deep``).

:func:`data_tools.sequence.sequence_info` reads the index and calibration files only. A
sequence can pass that and still be unusable: an 8-bit depth export, images of another size
than camera.json says, a truncated PNG from an interrupted copy, a depth scale off by the
factor between millimetres and TUM's 1/5000 m. :func:`check_sequence` opens every image the
index files list and reports every bad frame by file name, plus the median depth in metres (the
depth scale's plausibility check).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError
from data_tools.sequence import SequenceReader, read_depth_png, read_rgb_image

__all__ = ["SequenceCheck", "check_sequence", "PLAUSIBLE_MEDIAN_DEPTH_M"]

PLAUSIBLE_MEDIAN_DEPTH_M = (0.15, 8.0)
"""Median valid depth (metres) an RGB-D sensor plausibly sees; outside, the depth scale is
probably wrong (e.g. TUM's 5000 read as 1000 gives 5x the depth)."""
DEPTH_SAMPLE_FRAMES = 20
"""Frames (evenly spread) whose valid pixels give the median depth."""


@dataclass
class SequenceCheck:
    """What :func:`check_sequence` found."""

    path: str
    """The sequence folder."""
    depth_images: int = 0
    """Depth images checked."""
    rgb_images: int = 0
    """Colour images checked."""
    bad: list[dict] = field(default_factory=list)
    """Every bad image: ``{"file": relative path, "problem": one line}``, in index order."""
    median_depth_m: float | None = None
    """Median of the valid depth pixels of up to :data:`DEPTH_SAMPLE_FRAMES` frames, metres."""
    depth_scale_problem: str | None = None
    """Why the depth scale looks wrong (None: plausible)."""

    @property
    def ok(self) -> bool:
        return not self.bad and self.depth_scale_problem is None

    def to_json(self, max_listed: int = 10) -> dict:
        return {"depth_images": self.depth_images, "rgb_images": self.rgb_images, "bad_frames": len(self.bad),
                "bad": self.bad[:max_listed], "bad_not_listed": max(0, len(self.bad) - max_listed),
                "median_depth_m": self.median_depth_m, "depth_scale_problem": self.depth_scale_problem,
                "ok": self.ok}

    def summary(self, max_listed: int = 3) -> str:
        """One line: the problems, the first ``max_listed`` bad files by name, then a count."""
        parts = []
        if self.bad:
            shown = "; ".join(f"{b['file']}: {b['problem']}" for b in self.bad[:max_listed])
            more = f" (and {len(self.bad) - max_listed} more)" if len(self.bad) > max_listed else ""
            parts.append(f"{len(self.bad)} bad image(s): {shown}{more}")
        if self.depth_scale_problem:
            parts.append(self.depth_scale_problem)
        return f"{self.path}: " + ("; ".join(parts) if parts else "every image is readable and consistent")


def check_sequence(path: str | os.PathLike, progress: bool = True) -> SequenceCheck:
    """Open every depth and colour image of the sequence at ``path`` and check dtype (16-bit
    single-channel depth), size against camera.json and decodability; sample the median depth.
    Index problems (unsorted or duplicated timestamps, missing camera.json) raise as in
    :class:`~data_tools.sequence.SequenceReader`."""
    from data_tools.progress import progress_bar
    seq = SequenceReader(path, check_files=False)
    shape = seq.intrinsics.shape
    res = SequenceCheck(str(seq.path))
    n = len(seq)
    sample = set(np.linspace(0, n - 1, min(n, DEPTH_SAMPLE_FRAMES)).round().astype(int).tolist()) if n else set()
    depths = []
    seen_rgb = set()
    for i in progress_bar(range(n), desc="checking images", unit="frame", enabled=progress):
        rel = seq.depth_files[i]
        res.depth_images += 1
        try:
            d = read_depth_png(seq.path / rel, seq.camera.depth_scale, shape)
            if i in sample:
                v = d[d > 0]
                if v.size:
                    depths.append(v[:: max(1, v.size // 20000)])
        except FormatError as e:
            res.bad.append({"file": rel, "problem": e.problem})
        rgb = seq.rgb_files[i]
        if rgb is not None and rgb not in seen_rgb:
            seen_rgb.add(rgb)
            res.rgb_images += 1
            try:
                read_rgb_image(seq.path / rgb, shape)
            except FormatError as e:
                res.bad.append({"file": rgb, "problem": e.problem})
    if depths:
        med = float(np.median(np.concatenate(depths)))
        res.median_depth_m = med
        lo, hi = PLAUSIBLE_MEDIAN_DEPTH_M
        if not lo <= med <= hi:
            res.depth_scale_problem = (f"median depth {med:.3g} m is implausible for an RGB-D sensor "
                                       f"({lo}-{hi} m): is depth_scale {seq.camera.depth_scale:g} in camera.json "
                                       f"right? (1000 = millimetres, 5000 = TUM)")
    elif n:
        res.depth_scale_problem = "no valid depth pixel in the sampled frames"
    return res
