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


def test_real_kinect_v1_depth_is_on_one_disparity_lattice():
    """Real Kinect v1 captures of two datasets (TUM fr1/xyz: 1/5000 m PNG; 7-Scenes chess: mm PNG),
    from the measured depth alone, both lie on a lattice in f b / z, and on the same one: the
    device's 1/8 px code (0.125 px). f b = 580 px x 0.075 m is assumed for both (the step scales
    with it). Ported from the alternative lattice of branch lab2 (its detector: R 0.86 / 0.95,
    step 0.1254 / 0.1260 px). Skipped without ../shared."""
    import cv2

    from tests.conftest import shared_path
    fb = 580.0 * 0.075
    out = []
    for folder, pattern, unit in (("tum_fr1_xyz_10", "depth/*.png", 1 / 5000.0),
                                  ("sevenscenes_chess_1000", "frame-*.depth.png", 1 / 1000.0)):
        files = sorted(shared_path(folder).glob(pattern))[:5]
        assert files, folder
        z = np.concatenate([cv2.imread(str(f), cv2.IMREAD_UNCHANGED).astype(np.float64).ravel() for f in files])
        z = z[(z > 0) & (z < 65535)] * unit
        r = detect_lattice(fb / z, fb=fb, depth_unit_m=unit)
        assert r is not None and r.concentration > 0.5, (folder, r)
        out.append(r.step_px)
    assert out[0] == pytest.approx(out[1], rel=0.03) and out[0] == pytest.approx(0.125, rel=0.03), out


def test_phase_of_a_fine_step_far_from_the_origin():
    """The phase is that of the ABSOLUTE disparity, so a step read 2e-4 off moves it by 2e-4 x d / step
    (a third of a step at d ~ 5 px with 0.03125 px steps: a 160 px Kinect, f b ~ 10.5 px m): the
    step must be refined beyond the fine grid's 0.05 % for the phase to hold (the mystery generator's
    quantisation at 160 px, step / noise 2)."""
    fb, step, phase = 10.5, 0.03125, 0.33
    rng = np.random.default_rng(11)
    z_true = rng.uniform(1.8, 4.0, 20000)
    di = fb / z_true
    d = di + rng.normal(0.0, step / 2.0, di.size)
    d = (np.round(d / step - phase) + phase) * step
    z = np.round(fb / d * 5000.0) / 5000.0
    lat = detect_lattice(fb / z, di, fb=fb, max_samples=20000)
    assert lat is not None
    assert lat.step_px == pytest.approx(step, rel=2e-5), lat
    assert min(abs(lat.phase - phase), 1 - abs(lat.phase - phase)) < 0.01, lat


def test_a_step_read_off_the_lattice_is_searched_only_near_it():
    """fit_start's step_source "lattice" narrows the step's search bounds to LATTICE_WINDOW around it
    (a free search traded the step for noise); "search" keeps the FITTABLE range."""
    from synth.lab.params import param_specs
    from synth.sensor.config import SensorConfig
    from synth.sensor.effects.disparity_quantization import LATTICE_WINDOW
    cfg = SensorConfig.build("kinect_v1", ["axial_noise", "disparity_quantization"])
    free = {s.key: s for s in param_specs(cfg)}["disparity_quantization.step_px"]
    assert (free.low, free.high) == (0.0, 1.0)
    locked = cfg.with_params({"disparity_quantization.step_px": 0.03125,
                              "disparity_quantization.step_source": "lattice"})
    s = {s.key: s for s in param_specs(locked)}["disparity_quantization.step_px"]
    assert s.low == pytest.approx(0.03125 * (1 - LATTICE_WINDOW)) and s.high == pytest.approx(0.03125 * (1 + LATTICE_WINDOW))
    assert s.value == pytest.approx(0.03125)


def _golden_reference(f, a, b, rel_tol=1e-7):
    """Plain golden-section maximiser (the module's earlier hand-written one), the reference."""
    g = (np.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    while b - a > rel_tol * abs(b):
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return 0.5 * (a + b)


@pytest.mark.parametrize("ratio", [1.5, 8.0])
def test_scalar_search_finds_the_golden_sections_peak(monkeypatch, ratio):
    """The step's refinement (bounded Brent search, scipy) lands where plain golden section did,
    to its 1e-7 tolerance, with the same concentration and phase."""
    import synth.sensor.lattice as lattice
    d, di = _measure(ratio, step=0.125, seed=int(ratio * 10))
    new = detect_lattice(d, di, fb=FB)
    monkeypatch.setattr(lattice, "_scalar_max", _golden_reference)
    ref = detect_lattice(d, di, fb=FB)
    assert new.step_px == pytest.approx(ref.step_px, rel=1e-7)
    assert new.phase == pytest.approx(ref.phase, abs=1e-3)
    assert new.concentration == pytest.approx(ref.concentration, abs=1e-7)
