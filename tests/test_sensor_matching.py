"""Block matching: OpenCV path vs a transparent numpy SAD/census matcher; disparity <-> depth."""
from __future__ import annotations

import numpy as np
import pytest

from synth.sensor import SensorSimulator, get_preset
from synth.sensor.matching import MatcherParams, MatchSetup, match, sad_block_match
from synth.sensor.testscenes import camera_pose, wall_scene


def _texture(h, w, seed=0, blur=1.0):
    import cv2
    img = np.random.default_rng(seed).random((h, w)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), blur)
    img = (img - img.min()) / (img.max() - img.min())
    return img * 255


def _shift(img, d):
    """R with L(u) = R(u - d): R(x) = L(x + d)."""
    import cv2
    h, w = img.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(img, u + np.float32(d), v, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def _bm_setup(min_disp, num_disp, block=9):
    return MatchSetup(1.0, None, 1.0, min_disp, num_disp, 0, 0, block, 1 / 16)


@pytest.mark.parametrize("d_true", [7.0, 5.25, -3.5])
def test_opencv_bm_agrees_with_reference_sad(d_true):
    L = _texture(60, 120, seed=1)
    R = _shift(L, d_true)
    ref = sad_block_match(L, R, -16, 32, 9, uniqueness_ratio=5)
    cv = match(np.clip(L, 0, 255).astype(np.uint8), np.clip(R, 0, 255).astype(np.uint8), _bm_setup(-16, 32),
               "bm", MatcherParams(prefilter="xsobel", uniqueness_ratio=5, speckle_window_px=0))
    inner = (slice(10, 50), slice(30, 90))
    a, b = ref[inner], cv[inner]
    ok = np.isfinite(a) & np.isfinite(b)
    assert ok.mean() > 0.95
    assert np.median(np.abs(a[ok] - d_true)) < 0.1
    assert np.median(np.abs(b[ok] - d_true)) < 0.1
    assert np.mean(np.abs(a[ok] - b[ok]) < 0.25) > 0.95


def test_census_matcher_integer_shift():
    L = _texture(40, 90, seed=2)
    R = _shift(L, 6.0)
    d = sad_block_match(L, R, 0, 16, 7, census=True)
    inner = d[8:32, 25:80]
    assert np.nanmedian(np.abs(inner - 6.0)) < 0.1 and np.isfinite(inner).mean() > 0.9


def test_disparity_depth_round_trip_and_range():
    k = get_preset("kinect_v1")
    s = MatchSetup.for_preset(k)
    z = np.array([0.45, 0.7, 1.0, 2.0, 4.0, 8.0], np.float32)
    d = s.depth_to_disparity(z)
    assert d[2] == pytest.approx(0.0)  # the reference plane at 1 m has disparity 0
    np.testing.assert_allclose(s.disparity_to_depth(d), z, rtol=1e-5)
    assert s.min_disp <= d.min() and d.max() <= s.min_disp + s.num_disp - 1
    assert s.num_disp % 16 == 0
    st = MatchSetup.for_preset(get_preset("realsense_d435"))
    assert st.z0 is None and st.pad_before == 0
    np.testing.assert_allclose(st.depth_to_disparity(np.float32(2.0)), 428 * 0.05 / 2.0, rtol=1e-6)


@pytest.mark.parametrize("z", [0.8, 1.6, 3.1])
def test_physical_fronto_wall_median_within_one_step(z):
    pre = get_preset("kinect_v1").cropped(160, 120)
    res = SensorSimulator(pre, None, wall_scene(z)).simulate(camera_pose(), seed=0)
    err = (res.depth - res.ideal_depth)[res.valid]
    step = z * z * 0.125 / pre.fb
    assert res.valid_fraction > 0.8
    assert abs(np.median(err)) <= step
    assert np.mean(np.abs(err) < 4 * step) > 0.97


@pytest.mark.parametrize("preset", ["structure", "realsense_d435"])
def test_other_triangulating_presets_measure_a_wall(preset):
    pre = get_preset(preset)
    pre = pre.cropped(pre.width // 4, pre.height // 4) if preset == "structure" else pre.cropped(424, 120)
    res = SensorSimulator(pre, None, wall_scene(1.5)).simulate(camera_pose(), seed=0)
    err = (res.depth - res.ideal_depth)[res.valid]
    assert res.valid_fraction > 0.5
    assert abs(np.median(err)) < 0.03 * 1.5   # D435 spec: < 2 % at 2 m (SGBM pixel-locking adds ~1 %)


def test_compiled_quantised_depth_equals_the_setup_methods():
    """block_matching's one-pass kernel = MatchSetup.quantize + disparity_to_depth + the validity
    rule (bit for bit; NaN, negative, huge and half-step disparities included)."""
    from synth.sensor.effects.block_matching import _quantised_depth
    from synth.sensor.presets import get_preset
    setup = MatchSetup.for_preset(get_preset("kinect_v1"))
    rng = np.random.default_rng(0)
    d = (rng.standard_normal((60, 80)) * 40).astype(np.float32)
    d.flat[:50] = np.arange(50, dtype=np.float32) * np.float32(setup.step / 2) - 40   # exact half steps
    d.flat[50:60] = np.nan
    d.flat[60:70] = [-43.5, -43.4, -1e9, 1e9, np.inf, -np.inf, 0.0, -0.0, 43.5, -50.0]
    q = setup.quantize(d)
    z_ref = setup.disparity_to_depth(q)
    valid_ref = np.isfinite(q) & (z_ref > 0)
    z_ref[~valid_ref] = 0
    q[~valid_ref] = np.nan
    dd = d.copy()
    z = np.empty_like(d)
    valid = np.empty(d.shape, bool)
    _quantised_depth(dd, np.float32(setup.step), np.float32(1.0 / setup.z0), np.float32(setup.fb), z, valid)
    assert np.array_equal(valid, valid_ref) and np.array_equal(z, z_ref) and np.array_equal(dd, q, equal_nan=True)
    assert 0.2 < valid.mean() < 0.9


def test_compiled_window_normalisation_equals_numpy():
    import cv2

    from synth.sensor.matching import _normalized
    img = np.random.default_rng(1).integers(0, 256, (48, 70), dtype=np.uint8)
    img[10:20, 10:30] = 7                                   # a flat patch: the variance floor of 1
    f = img.astype(np.float32)
    m = cv2.blur(f, (9, 9))
    ref = (f - m) / np.sqrt(np.maximum(cv2.blur(f * f, (9, 9)) - m * m, np.float32(1.0)))
    assert np.array_equal(_normalized(img, 9), ref)
