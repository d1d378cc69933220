"""Dot pattern generator and pattern image loading."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from conftest import shared_path
from data_tools.errors import ConfigError, FormatError
from synth.sensor.pattern import generate_dot_pattern, load_pattern


def _components(img):
    import cv2
    n, _, stats, _ = cv2.connectedComponentsWithStats((img > 0).astype(np.uint8), connectivity=8)
    return n - 1, stats[1:, 4]


def test_generated_pattern_is_kinect_like():
    p = generate_dot_pattern(seed=3)
    assert p.size == (633, 495)
    img = p.image
    assert abs(img.mean() - 0.111) < 0.002
    t = img[:165, :211]
    for i in range(3):
        for j in range(3):
            assert np.array_equal(img[i * 165:(i + 1) * 165, j * 211:(j + 1) * 211], t)  # identical tiles
    assert np.array_equal(t, t[::-1, ::-1])  # centrally symmetric tile
    n, areas = _components(img)
    assert np.all(areas == 1), "dots are isolated single pixels, also across tile borders"
    assert n == int(img.sum())


def test_generated_pattern_is_deterministic_and_seeded():
    a, b, c = generate_dot_pattern(seed=1), generate_dot_pattern(seed=1), generate_dot_pattern(seed=2)
    assert np.array_equal(a.image, b.image)
    assert not np.array_equal(a.image, c.image)


def test_generated_pattern_is_locally_unique():
    """A 9x9 window must identify its position along a row within the search range (no
    repeats within one tile width): compare windows at many shifts."""
    img = generate_dot_pattern(seed=0).image
    rng = np.random.default_rng(0)
    for _ in range(30):
        y, x = rng.integers(10, 150), rng.integers(10, 100)
        w = img[y:y + 9, x:x + 9]
        for dx in range(1, 100):
            assert not np.array_equal(w, img[y:y + 9, x + dx:x + dx + 9])


def test_load_shared_kinect_pattern():
    path = shared_path("patterns", "kinect_v1_pattern_3x3.png")
    p = load_pattern(path, (633, 495))
    assert p.image.dtype == np.float32 and p.image.shape == (495, 633)
    assert set(np.unique(p.image)) <= {0.0, 1.0}
    n, areas = _components(p.image)
    assert 34000 < n < 35500 and np.all(areas == 1)


def test_load_pattern_errors(tmp_path):
    img = (np.random.default_rng(0).random((50, 60)) > 0.9).astype(np.uint8) * 255
    path = tmp_path / "p.png"
    Image.fromarray(img).save(path)
    assert load_pattern(path).size == (60, 50)
    with pytest.raises(ConfigError, match="60x50 px but the projector expects 633x495"):
        load_pattern(path, (633, 495))
    with pytest.raises(FormatError, match="not found"):
        load_pattern(tmp_path / "missing.png")
    Image.fromarray(np.zeros((20, 20), np.uint8)).save(tmp_path / "dark.png")
    with pytest.raises(FormatError, match="dark"):
        load_pattern(tmp_path / "dark.png")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(FormatError, match="cannot read"):
        load_pattern(tmp_path / "junk.png")


def test_bad_generator_arguments():
    with pytest.raises(ConfigError):
        generate_dot_pattern(density=0.5)
    with pytest.raises(ConfigError):
        generate_dot_pattern(tile_size=(4, 4))
