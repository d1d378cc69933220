"""Disparity-lattice detection from the measurement alone (issue 43 item 2): hand-made Kinect-like
disparities (seeded numpy), quantised with a known step and phase after noise, stored as depth
rounded to 1/5000 m (a TUM depth PNG) and read back as f b / z."""
import numpy as np
import pytest

from synth.sensor.lattice import detect_lattice

FB = 580.0 * 0.075      # Kinect v1 at VGA, px m


def _measure(ratio, step=0.125, phase=0.3, seed=0, n=6000, quantise=True):
    rng = np.random.default_rng(seed)
    z_true = rng.uniform(0.6, 4.0, n)
    d_ideal = FB / z_true
    d = d_ideal + rng.normal(0.0, step / ratio, n)
    if quantise:
        d = (np.round(d / step - phase) + phase) * step
    z = np.round(FB / d * 5000.0) / 5000.0            # the depth PNG's rounding
    return FB / z, d_ideal


@pytest.mark.parametrize("ratio", [1.5, 2.0, 4.0, 8.0])
@pytest.mark.parametrize("step", [0.125])
def test_lattice_step_recovered_within_3_percent(ratio, step):
    d, di = _measure(ratio, step=step, seed=int(ratio * 10))
    lat = detect_lattice(d, di, fb=FB)
    assert lat is not None
    assert abs(lat.step_px - step) / step < 0.03, lat
    # the phase of the absolute disparity (0.3 of a step), circular distance
    assert min(abs(lat.phase - 0.3), 1 - abs(lat.phase - 0.3)) < 0.1, lat
    assert lat.concentration > lat.expected + 0.3


def test_small_step_and_no_ideal_disparities():
    d, di = _measure(2.0, step=0.07, seed=5)
    lat = detect_lattice(d, di, fb=FB)
    assert lat is not None and abs(lat.step_px - 0.07) / 0.07 < 0.03


def test_lattice_without_ideal_disparities():
    d, _ = _measure(2.0, seed=3)
    lat = detect_lattice(d, fb=FB)
    assert lat is not None and abs(lat.step_px - 0.125) / 0.125 < 0.03


@pytest.mark.parametrize("ratio", [2.0, 8.0])
def test_no_lattice_no_detection(ratio):
    d, di = _measure(ratio, quantise=False, seed=7)
    assert detect_lattice(d, di, fb=FB) is None
    assert detect_lattice(d, fb=FB) is None
