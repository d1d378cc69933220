"""data_tools.png: our PNG writer decodes to the exact input in OpenCV and Pillow."""
from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from data_tools.errors import RealgapError
from data_tools.png import encode_png
from data_tools.results import atomic_write_image
from data_tools.sequence import encode_depth_png, encode_rgb_png, read_depth_png, write_depth_png


def _cv_decode(b: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize("shape,dtype", [((5, 7), np.uint8), ((5, 7), np.uint16), ((4, 3, 3), np.uint8),
                                         ((4, 3, 3), np.uint16), ((6, 2, 4), np.uint8), ((3, 9, 2), np.uint8),
                                         ((1, 1), np.uint16), ((480, 640), np.uint16)])
def test_round_trip_pillow_and_opencv(shape, dtype):
    rng = np.random.default_rng(3)
    a = rng.integers(0, np.iinfo(dtype).max + 1, size=shape, dtype=np.int64).astype(dtype)
    b = encode_png(a)
    with Image.open(io.BytesIO(b)) as im:
        im.load()
        got = np.array(im)
    if dtype == np.uint16 and a.ndim == 2:
        got = got.astype(np.uint16)  # Pillow reads 16-bit grey as mode I;16 / I
    assert got.shape == a.shape
    if not (dtype == np.uint16 and a.ndim == 3):  # Pillow reduces 16-bit colour to 8 bits
        np.testing.assert_array_equal(got, a)
    if a.ndim == 3 and a.shape[2] == 2:
        return  # OpenCV has no grey + alpha layout (it expands it to BGRA)
    d = _cv_decode(b)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        d = d[:, :, [2, 1, 0, 3][:a.shape[2]]]  # OpenCV returns BGR(A)
    np.testing.assert_array_equal(d, a)


def test_sub_filter_by_hand():
    # one row, two grey 8-bit pixels 10, 250: the Sub filter stores 10, 240; inflating the
    # IDAT chunk must give exactly filter byte 1 then those two bytes
    import zlib
    b = encode_png(np.array([[10, 250]], np.uint8))
    assert b[:8] == b"\x89PNG\r\n\x1a\n"
    i = b.index(b"IDAT")
    n = int.from_bytes(b[i - 4:i], "big")
    assert zlib.decompress(b[i + 4:i + 4 + n]) == bytes([1, 10, 240])


def test_depth_and_rgb_files_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 6.0, (48, 64)).astype(np.float32)
    depth[::7, ::5] = 0
    write_depth_png(tmp_path / "d.png", depth, 5000.0)
    back = read_depth_png(tmp_path / "d.png", 5000.0)
    np.testing.assert_allclose(back, np.rint(depth.astype(np.float64) * 5000) / 5000, atol=1e-6)
    assert (tmp_path / "d.png").read_bytes() == encode_depth_png(depth, 5000.0)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    np.testing.assert_array_equal(_cv_decode(encode_rgb_png(rgb))[:, :, ::-1], rgb)
    atomic_write_image(tmp_path / "c.png", rgb[:, :, ::-1])  # OpenCV convention: BGR in
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "c.png")), rgb[:, :, ::-1])


def test_bad_arrays_are_refused():
    with pytest.raises(RealgapError, match="float32"):
        encode_png(np.zeros((4, 4), np.float32))
    with pytest.raises(RealgapError, match="shape"):
        encode_png(np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(RealgapError, match="shape"):
        encode_png(np.zeros((0, 4), np.uint8))
