"""Image folders SynDA reads (A's background bank, the colour test set's textures and backgrounds): one
resolution of a folder name (``skimage``: scikit-image's sample images) and one suffix list. No torch."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from data_tools.errors import FormatError

__all__ = ["IMAGE_SUFFIXES", "image_folder", "image_files"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""Image files read from a folder."""


def image_folder(source: str, what: str = "image") -> Path:
    """The folder ``source`` names (``skimage``: the one holding scikit-image's sample images); a one-line
    error naming ``what`` (e.g. "background image") when it is not a folder."""
    if source == "skimage":
        import skimage.data
        folder = Path(skimage.data.__file__).parent
    else:
        folder = Path(source)
    if not folder.is_dir():
        raise FormatError(folder, f"{what} folder not found")
    return folder


def image_files(source: str, recursive: bool = False, limit: int | None = None) -> list[Path]:
    """Sorted 8-bit image files of folder ``source`` (``skimage``: scikit-image's sample images; 16-bit PNGs, i.e.
    depth images, left out); at most ``limit``, evenly spaced. One-line error when there is none."""
    folder = image_folder(source)
    it = folder.rglob("*") if recursive else folder.iterdir()
    files = sorted(f for f in it if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file() and _eight_bit(f))
    if not files:
        raise FormatError(folder, f"no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    if limit is not None and len(files) > limit:
        files = [files[int(i)] for i in np.linspace(0, len(files) - 1, limit).round()]
    return files


def _eight_bit(f: Path) -> bool:
    """False for a PNG of 16-bit samples (a depth image beside the colour frames, as in 7-Scenes folders)."""
    if f.suffix.lower() != ".png":
        return True
    with open(f, "rb") as fh:
        head = fh.read(26)
    return len(head) < 26 or head[24] == 8
