"""The mystery sensor (synth/lab/mystery.py), the independent hidden-effect generator of issue #43:
deterministic, its Kinect raw-disparity conversion exact, its noise and depth right on a plane, its
analytic scene identical to the mesh the lab renders, its answer naming the hidden effect in the
lab's parameter names, its output readable by the lab."""
from __future__ import annotations

import json

import numpy as np
import pytest

from synth.lab import mystery as my


def _sensor(effect=None, **hidden):
    m = my.Mystery(160, 120, 580.0, 1.0, (0.0, 0.0), 3.1, -0.0029, 0.5, 0.5, 4.5, effect, hidden)
    return m


def test_raw_disparity_round_trips():
    """z = 1 / (c0 + c1 d) and d = (1/z - c0) / c1 invert each other over the 11-bit range; the
    invalid code 2047 and disparities past 1/z = 0 read as no measurement."""
    c0, c1 = 3.1, -0.0029
    d = np.arange(0, 1060, dtype=np.float64)            # up to 1/z ~ 0.026 (38 m)
    z = my.raw_to_depth(d, c0, c1)
    assert np.all(z > 0) and np.all(np.diff(z) > 0)
    assert np.allclose(my.depth_to_raw(z, c0, c1), d, atol=1e-7)
    zz = np.linspace(0.4, 8.0, 200)
    assert np.allclose(my.raw_to_depth(my.depth_to_raw(zz, c0, c1), c0, c1), zz, rtol=1e-12)
    assert my.raw_to_depth(np.array([2047.0, 1100.0]), c0, c1).tolist() == [0.0, 0.0]
    assert float(my.depth_to_raw(np.array(0.0), c0, c1)) == 2047.0
    # hand value: d = 500 -> 1/z = 3.1 - 1.45 = 1.65
    assert float(my.raw_to_depth(np.array(500.0), c0, c1)) == pytest.approx(1 / 1.65, rel=1e-12)


def test_baseline_follows_from_c1():
    """c1 = -1 / (8 f b): one raw unit is 1/8 native pixel of disparity, so the lab's f b / z in output
    pixels changes by width/640/8 per raw unit."""
    m = _sensor()
    assert m.baseline == pytest.approx(1.0 / (8 * 580.0 * 0.0029))
    z1, z2 = my.raw_to_depth(np.array([600.0, 601.0]), m.c0, m.c1)
    assert m.fb / z1 - m.fb / z2 == pytest.approx(m.raw_px) and m.raw_px == pytest.approx(160 / 640 / 8)


def test_static_plane_depth_and_noise():
    """A fronto-parallel wall at 2.5 m, static camera, 40 frames: mean depth 2.5 m within 1 mm and
    the per-pixel std z^2 sigma_raw |c1| (the answer's noise at 2.5 m) within 5 %; a wall past the
    maximum range gives no measurement."""
    m = _sensor()
    wall = my.Solid("rect", {"c": np.array([0.0, 2.5, 1.0]), "a1": np.array([1.0, 0, 0]),
                             "a2": np.array([0, 0, 1.0]), "h": (5.0, 5.0)}, 0.6, "wall")
    T = my.look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 3.0, 1.0]))
    frames = np.stack([my.render_frame(m, [wall], T, np.random.default_rng(i))[0] for i in range(40)])
    assert np.all(frames > 0)
    assert float(frames.mean()) == pytest.approx(2.5, abs=1e-3)
    expected = 2.5 ** 2 * m.sigma_raw * abs(m.c1)
    assert float(frames.std(0).mean()) == pytest.approx(expected, rel=0.05)
    far = my.Solid("rect", {**wall.p, "c": np.array([0.0, 4.8, 1.0])}, 0.6, "far")
    assert not my.render_frame(m, [far], T, np.random.default_rng(0))[0].any()


def test_deterministic_per_seed(tmp_path):
    """The same seed writes byte-identical depth PNGs and answer; another seed does not."""
    a = my.generate(tmp_path / "a", "incidence_dropout", seed=7, n_frames=2, width=80, height=60)
    b = my.generate(tmp_path / "b", "incidence_dropout", seed=7, n_frames=2, width=80, height=60)
    c = my.generate(tmp_path / "c", "incidence_dropout", seed=8, n_frames=2, width=80, height=60)
    assert a == b and a != c
    pa, pb = sorted((tmp_path / "a" / "depth").iterdir()), sorted((tmp_path / "b" / "depth").iterdir())
    assert [p.read_bytes() for p in pa] == [p.read_bytes() for p in pb]
    assert pa[0].read_bytes() != sorted((tmp_path / "c" / "depth").iterdir())[0].read_bytes()


@pytest.mark.parametrize("effect", my.EFFECTS)
def test_answer_names_the_effect_in_the_labs_terms(tmp_path, effect):
    """answer.json names the hidden effect; its parameters are parameters of the lab's effect of that
    name (the lab never reads the file); the lab loads the sequence and renders the same ideal depth
    as the analytic cast (the lens-distorted case differs by design: the lab is not told)."""
    from data_tools.sequence import sequence_info
    from synth.lab import MeasuredSequence
    seed = 3 + my.EFFECTS.index(effect)
    ans = my.generate(tmp_path / "s", effect, seed=seed, n_frames=2, width=80, height=60)
    on_disk = json.loads((tmp_path / "s" / "answer.json").read_text())
    assert on_disk["effect"] == effect == ans["effect"]
    assert sequence_info(tmp_path / "s")["frames"] == 2
    ms = MeasuredSequence.load(tmp_path / "s")
    lab_params = ms.default_config([effect]).effect(effect).params
    extra = {"jump_px", "level_phase"}      # the mystery sensor's own form; the phase lives in the preset
    assert all(hasattr(lab_params, k) for k in on_disk["params"] if k not in extra), on_disk["params"]
    rng = np.random.default_rng([seed, 4242])             # re-draw what generate drew, in its order
    m = my.draw_sensor(rng, effect, 80, 60)
    solids = my.draw_scene(rng)
    poses = my.draw_trajectory(rng, 2, bool(rng.random() < 0.5) or effect == "rolling_shutter")
    _, z, _, _ = my.render_frame(m, solids, poses[1], np.random.default_rng(0))
    r = ms.render(1).depth                                # rolling shutter: global-shutter z at the pose
    if effect != "lens_distortion":
        assert np.mean((z > 0) == (r > 0)) > 0.995
        both = (z > 0) & (r > 0)
        assert np.median(np.abs(z - r)[both]) < 1e-4


def test_quantised_disparities_lie_on_the_answers_lattice(tmp_path):
    """With disparity_quantization hidden, every measured f b / z sits on (k + level_phase) step_px
    (to the depth PNG's 1/5000 m rounding); without it, the same sequence does not."""
    from synth.lab import MeasuredSequence

    def lattice_dev(path, ans, step, phase):
        ms = MeasuredSequence.load(path)
        d = ms.measured_depth(0)
        x = (ans["sensor"]["fb"] / d[d > 0] / step - phase) % 1.0
        return np.minimum(x, 1 - x)
    a = my.generate(tmp_path / "q", "disparity_quantization", seed=4, n_frames=1, width=160, height=120)
    step, phase = a["params"]["step_px"], a["params"]["level_phase"]
    assert np.percentile(lattice_dev(tmp_path / "q", a, step, phase), 95) < 0.05
    b = my.generate(tmp_path / "n", None, seed=4, n_frames=1, width=160, height=120)
    assert np.median(lattice_dev(tmp_path / "n", b, step, phase)) > 0.15


def test_unknown_effect_is_refused():
    with pytest.raises(ValueError, match="unknown hidden effect"):
        my.draw_sensor(np.random.default_rng(0), "wobble", 80, 60)


def test_rolling_shutter_shifts_rows_by_the_motion(tmp_path):
    """A camera moving sideways at 1 m/s, readout 0.03 s: the first row is the global-shutter image,
    the last row is taken 0.03 m further along - the vertical edge of a panel at 1 m moves by
    f 0.03 / 1 = 4.35 px between the first and the last row."""
    m = _sensor("rolling_shutter", readout_s=0.03)
    m.sigma_raw = 1e-9
    wall = my.Solid("rect", {"c": np.array([0.0, 2.0, 1.0]), "a1": np.array([1.0, 0, 0]),
                             "a2": np.array([0, 0, 1.0]), "h": (5.0, 5.0)}, 0.6, "wall")
    step = my.Solid("rect", {"c": np.array([0.5, 1.0, 1.0]), "a1": np.array([1.0, 0, 0]),
                             "a2": np.array([0, 0, 1.0]), "h": (0.5, 5.0)}, 0.6, "step")   # x <= 0 edge
    pose_at = lambda t: my.look_at(np.array([1.0 * t, 0.0, 1.0]), np.array([1.0 * t, 3.0, 1.0]))  # noqa: E731
    depth = my.render_frame(m, [wall, step], pose_at(0.0), np.random.default_rng(0), pose_at, 0.0)[0]
    first = np.argmax(depth[0] < 1.75)
    last = np.argmax(depth[-1] < 1.75)
    shift = m.intrinsics[0] * 1.0 * 0.03 / 1.0
    assert first - last == pytest.approx(shift, abs=1.0)
    glob = my.render_frame(m, [wall, step], pose_at(0.0), np.random.default_rng(0))[0]
    assert np.argmax(glob[-1] < 1.75) == first
