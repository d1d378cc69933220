"""Projector dot patterns: a Kinect-like pseudo-random generator and loading a pattern image.

A pattern is the radiant intensity image of the projector: ``(Hp, Wp)`` float32 in [0, 1], one
value per projector pixel (a diffractive element's output, seen through a pinhole). The Kinect v1
pattern is ~34,700 single-pixel dots on a 633 x 495 grid made of 3 x 3 identical 211 x 165 tiles
(Konolige & Mihelich, "Technical description of Kinect calibration", ROS wiki 2011; the shared
reference image ``patterns/kinect_v1_pattern_3x3.png`` has exactly this structure: 11.1 % of the
pixels lit, no two dots 8-adjacent, each tile centrally symmetric).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError


@dataclass(frozen=True)
class DotPattern:
    """A projector pattern image and where it came from."""

    image: np.ndarray
    """(Hp, Wp) float32 relative radiant intensity per projector pixel, in [0, 1]."""
    source: str
    """``generated(seed=..., ...)`` or the file path it was loaded from."""

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in projector pixels."""
        return (int(self.image.shape[1]), int(self.image.shape[0]))


def generate_dot_pattern(tile_size: tuple[int, int] = (211, 165), tiles: tuple[int, int] = (3, 3),
                         density: float = 0.111, seed: int = 0, symmetric: bool = True,
                         center_gain: float = 1.0) -> DotPattern:
    """Pseudo-random single-pixel dot pattern, tiled like the Kinect v1 projector.

    Dots are placed in random order, rejecting any candidate 8-adjacent to an existing dot (so
    every dot stays an isolated spot the matcher can localise), until ``density`` of the tile
    is lit. ``symmetric`` makes each tile equal to its 180-degree rotation (as in the Kinect
    DOE). ``tiles`` = (columns, rows) repeats; ``center_gain`` scales the central tile (the
    Kinect's zero-order tile is slightly brighter; 1.0 disables). Deterministic in ``seed``.

    Args:
        tile_size: (width, height) of one tile in projector pixels.
        tiles: (columns, rows) of identical tiles.
        density: fraction of lit pixels, in (0, 0.2].
    """
    tw, th = int(tile_size[0]), int(tile_size[1])
    if tw < 8 or th < 8:
        raise ConfigError(f"dot pattern tile must be at least 8x8 pixels, got {tw}x{th}")
    if not 0.0 < density <= 0.2:
        raise ConfigError(f"dot pattern density must be in (0, 0.2] (isolated dots), got {density}")
    rng = np.random.default_rng(seed)
    tile = np.zeros((th, tw), dtype=bool)
    target = int(round(density * tw * th))
    order = rng.permutation(tw * th)
    count = 0

    def free(y: int, x: int) -> bool:  # no lit pixel in the 3x3 neighbourhood (wrapping: tiles repeat)
        return not tile[np.ix_([(y - 1) % th, y, (y + 1) % th], [(x - 1) % tw, x, (x + 1) % tw])].any()

    for idx in order:
        y, x = divmod(int(idx), tw)
        if not free(y, x):
            continue
        ys, xs = [y], [x]
        if symmetric:
            y2, x2 = th - 1 - y, tw - 1 - x
            if (y2, x2) != (y, x):
                dy, dx = min(abs(y2 - y), th - abs(y2 - y)), min(abs(x2 - x), tw - abs(x2 - x))
                if (dy <= 1 and dx <= 1) or not free(y2, x2):
                    continue
                ys.append(y2)
                xs.append(x2)
        tile[ys, xs] = True
        count += len(ys)
        if count >= target:
            break
    t = tile.astype(np.float32)
    img = np.tile(t, (int(tiles[1]), int(tiles[0])))
    if center_gain != 1.0 and tiles[0] >= 3 and tiles[1] >= 3:
        cy, cx = int(tiles[1]) // 2, int(tiles[0]) // 2
        img[cy * th:(cy + 1) * th, cx * tw:(cx + 1) * tw] *= center_gain
        img /= max(1.0, float(img.max()))
    src = (f"generated(seed={seed}, tile={tw}x{th}, tiles={tiles[0]}x{tiles[1]}, "
           f"density={density}, symmetric={symmetric})")
    return DotPattern(np.ascontiguousarray(img, dtype=np.float32), src)


def load_pattern(path: str | os.PathLike, expected_size: tuple[int, int] | None = None,
                 channel: int = 0) -> DotPattern:
    """Load a pattern image (8/16-bit grey, RGB or RGBA; one ``channel`` is used) as a DotPattern.

    Values are scaled to [0, 1] by the image's bit depth. ``expected_size`` = (width, height)
    the projector of the sensor preset has; a different size raises a ConfigError (a pattern of
    another size would change the projector's field of view and dot pitch silently).
    """
    from PIL import Image
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "pattern image not found")
    try:
        with Image.open(path) as im:
            arr = np.asarray(im)
    except Exception as e:  # PIL raises several types for corrupt files
        raise FormatError(path, f"cannot read pattern image ({type(e).__name__}: {e})") from None
    if arr.ndim == 3:
        if not 0 <= channel < arr.shape[2]:
            raise FormatError(path, f"pattern image has {arr.shape[2]} channels, channel {channel} requested")
        arr = arr[:, :, channel]
    if arr.ndim != 2 or arr.size == 0:
        raise FormatError(path, f"pattern image must be a 2-D image, got shape {arr.shape}")
    h, w = arr.shape
    if expected_size is not None and (w, h) != tuple(int(v) for v in expected_size):
        raise ConfigError(f"{path}: pattern image is {w}x{h} px but the projector expects "
                          f"{int(expected_size[0])}x{int(expected_size[1])} px")
    scale = 65535.0 if arr.dtype == np.uint16 else (255.0 if arr.dtype == np.uint8 else max(1.0, float(arr.max())))
    img = np.clip(arr.astype(np.float32) / scale, 0.0, 1.0)
    if not img.any():
        raise FormatError(path, "pattern image is entirely dark (wrong channel?)")
    return DotPattern(np.ascontiguousarray(img), str(path))
