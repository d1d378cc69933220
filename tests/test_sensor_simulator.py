"""SensorSimulator: determinism, replay, outputs, camera block, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.errors import ConfigError, RealgapError
from data_tools.scene_spec import SceneSpec
from synth.sensor import SensorConfig, SensorSimulator, get_preset
from synth.sensor.testscenes import box_before_wall_scene, camera_pose, wall_scene

SMALL = get_preset("kinect_v1").cropped(160, 120)


@pytest.fixture(scope="module")
def box_scene():
    return box_before_wall_scene(2.0, 1.5, 0.2)


def _same(a, b):
    for k in ("depth", "valid", "ir", "disparity"):
        x, y = getattr(a, k), getattr(b, k)
        if x is None:
            assert y is None
        else:
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("model", ["physical", "direct"])
def test_seed_determinism_and_replay(box_scene, model):
    sim = SensorSimulator(SMALL, model, box_scene)
    T = camera_pose()
    a, b = sim.simulate(T, seed=5), sim.simulate(T, seed=5)
    _same(a, b)
    c = sim.simulate(T, seed=6)
    assert not np.array_equal(a.depth, c.depth)
    r = sim.simulate(T, seed=None, draws=a.draws)  # replay from the stored draws only
    _same(a, r)
    assert r.seed is None and a.seed == 5


def test_outputs_shapes_and_types(box_scene):
    sim = SensorSimulator(SMALL, None, box_scene)
    res = sim.simulate(camera_pose(), seed=0)
    H, W = 120, 160
    assert res.depth.shape == (H, W) and res.depth.dtype == np.float32
    assert res.valid.dtype == bool and np.array_equal(res.valid, res.depth > 0)
    assert res.ir.shape == (H, W) and res.ir.dtype == np.uint16
    assert res.ideal_depth.shape == (H, W) and res.normals.shape == (H, W, 3)
    assert set(np.unique(res.instance_ids)) == {1, 2}
    assert np.all(np.isnan(res.disparity[~res.valid]))
    assert 0.8 < res.valid_fraction < 1.0
    assert "block_matching" in res.log["timings_ms"]
    f = res.to_frame(1.5, 3)
    assert f.timestamp == 1.5 and f.index == 3 and "ideal_depth" in f.extra and "ir" in f.extra


def test_effect_draws_are_independent_of_other_effects(box_scene):
    """Switching one effect off must not change another effect's random draw."""
    sim = SensorSimulator(SMALL, "direct", box_scene)
    a = sim.simulate(camera_pose(), seed=3)
    sim.set_enabled("incidence_dropout", False)
    b = sim.simulate(camera_pose(), seed=3)
    np.testing.assert_array_equal(a.draws["axial_noise"]["n"], b.draws["axial_noise"]["n"])
    assert "incidence_dropout" not in b.draws
    with pytest.raises(ConfigError, match="unknown sensor effect"):
        sim.set_enabled("no_such_effect", False)


def test_direct_model_from_ideal_depth_step_by_step(box_scene):
    """A model built effect by effect: no effects = ideal depth; then noise; then quantisation."""
    T = camera_pose()
    ideal = SensorSimulator(SMALL, [], box_scene).simulate(T, seed=0)
    np.testing.assert_array_equal(ideal.depth, ideal.ideal_depth)
    noisy = SensorSimulator(SMALL, ["axial_noise"], box_scene).simulate(T, seed=0)
    assert np.any(noisy.depth != ideal.depth)
    q = SensorSimulator(SMALL, ["axial_noise", "disparity_quantization"], box_scene).simulate(T, seed=0)
    assert len(np.unique(q.depth[q.valid])) < len(np.unique(noisy.depth[noisy.valid]))


def test_camera_block():
    sim = SensorSimulator("kinect_v1", None, None)
    cam = sim.camera()
    assert cam.intrinsics.width == 640 and cam.intrinsics.fx == 580.0 and cam.depth_scale == 5000.0
    assert cam.sensor.type == "structured_light" and cam.sensor.baseline_m == 0.075
    assert cam.sensor.projector_offset_m == (0.075, 0.0, 0.0)
    assert cam.sensor.extra["preset"] == "kinect_v1" and "block_matching" in cam.sensor.extra["effects"]
    from data_tools.camera import camera_from_dict
    assert camera_from_dict(cam.to_json()).sensor.extra["preset"] == "kinect_v1"
    sim2 = SensorSimulator("kinect_v1", ["lens_distortion"], None)
    sim2.config.effects[0].params.coefficients = (-0.1, 0.05, 0.0, 0.0, 0.0)
    assert sim2.camera().intrinsics.distortion == (-0.1, 0.05, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("preset,model", [(SMALL, None), (SMALL, "direct"),
                                          (get_preset("kinect_v2").cropped(128, 106), None)])
def test_no_geometry_in_view_is_reported_not_a_crash(preset, model):
    scene = wall_scene(2.0)
    sim = SensorSimulator(preset, model, scene)
    T = camera_pose().copy()
    T[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # looking away from the wall
    res = sim.simulate(T, seed=0)
    assert not res.valid.any() and np.all(res.depth == 0)
    assert any("no geometry in view" in w for w in res.warnings)
    moving = T.copy()
    moving[0, 3] = 0.01
    res = sim.simulate(T, seed=0, prev_pose=moving)          # motion effects with nothing to see
    assert not res.valid.any() and any("no geometry in view" in w for w in res.warnings)
    empty = SensorSimulator(SMALL, None, SceneSpec([], {}))
    res = empty.simulate(camera_pose(), seed=0)
    assert not res.valid.any() and res.warnings


def test_bad_input():
    with pytest.raises(ConfigError, match="baseline"):
        SensorSimulator(get_preset("kinect_v1").replace(baseline_m=-0.1), None, None)
    with pytest.raises(RealgapError, match="4x4"):
        SensorSimulator(SMALL, "direct", wall_scene()).simulate(np.eye(3), seed=0)
    with pytest.raises(ConfigError):
        SensorSimulator(SMALL, ["block_matching"], wall_scene()).simulate(camera_pose(), seed=0)
    with pytest.raises(ConfigError, match="known effects"):
        SensorSimulator("kinect_v1", ["shot_noise"], None)


def test_bad_pattern_inputs(tmp_path):
    from synth.sensor import generate_dot_pattern
    from data_tools.errors import FormatError
    small = generate_dot_pattern((50, 40), (2, 2), 0.1, seed=1)          # 100x80 px, preset wants 633x495
    with pytest.raises(ConfigError, match="100x80 px but preset 'kinect_v1' expects 633x495"):
        SensorSimulator(SMALL, None, wall_scene(), pattern=small).simulate(camera_pose(), seed=0)
    dark = tmp_path / "dark.png"
    from PIL import Image
    Image.fromarray(np.zeros((495, 633), np.uint8)).save(dark)
    with pytest.raises(FormatError, match="entirely dark"):
        SensorSimulator(SMALL.replace(pattern=str(dark)), None, wall_scene()).simulate(camera_pose(), seed=0)
    with pytest.raises(FormatError, match="not found"):
        SensorSimulator(SMALL.replace(pattern=str(tmp_path / "none.png")), None, wall_scene()).simulate(
            camera_pose(), seed=0)


def test_wrong_size_pattern_image(tmp_path):
    from PIL import Image
    p = tmp_path / "pattern.png"
    Image.fromarray(((np.random.default_rng(0).random((100, 120)) > 0.9) * 255).astype(np.uint8)).save(p)
    sim = SensorSimulator(SMALL.replace(pattern=str(p)), None, wall_scene())
    with pytest.raises(ConfigError, match="expects 633x495"):
        sim.simulate(camera_pose(), seed=0)


def test_config_round_trip_gives_identical_frames(box_scene):
    sim = SensorSimulator(SMALL, "direct", box_scene)
    sim.effect("axial_noise").params.sigma2_per_m = 0.004
    again = SensorSimulator(SensorConfig.from_json(sim.config.to_json()), None, box_scene)
    _same(sim.simulate(camera_pose(), seed=2), again.simulate(camera_pose(), seed=2))


def test_shared_kinect_pattern_image(box_scene):
    from conftest import shared_path
    path = shared_path("patterns", "kinect_v1_pattern_3x3.png")
    sim = SensorSimulator(SMALL.replace(pattern=str(path)), None, box_scene)
    res = sim.simulate(camera_pose(), seed=0)
    assert sim.pattern().source == str(path)
    err = (res.depth - res.ideal_depth)[res.valid]
    assert res.valid_fraction > 0.8 and np.median(np.abs(err)) < 0.01


def test_simulate_trajectory_writes_and_resumes(box_scene, tmp_path):
    from data_tools.sequence import SequenceReader, SequenceWriter
    from synth.sensor import simulate_trajectory
    poses = np.stack([camera_pose()] * 4)
    for i in range(4):
        poses[i, 0, 3] = 0.01 * i
    ts = np.arange(4) / 30.0
    sim = SensorSimulator(SMALL, "direct", box_scene)
    with SequenceWriter(tmp_path / "a", sim.camera(), box_scene) as w:
        assert simulate_trajectory(sim, poses[:2], ts[:2], w, progress=False) == 2
    with SequenceWriter(tmp_path / "a", sim.camera(), box_scene, resume=True) as w:
        assert simulate_trajectory(sim, poses, ts, w, progress=False) == 2
    with SequenceWriter(tmp_path / "b", sim.camera(), box_scene) as w:
        simulate_trajectory(sim, poses, ts, w, progress=False)
    a, b = SequenceReader(tmp_path / "a"), SequenceReader(tmp_path / "b")
    assert len(a) == 4 and a.camera.sensor.extra["preset"] == "kinect_v1"
    for i in range(4):
        np.testing.assert_array_equal(a[i].depth, b[i].depth)


def test_simulation_pool_gives_the_serial_results_in_order(box_scene):
    from synth.sensor.pool import SimulationPool
    sim = SensorSimulator(SMALL, "physical", box_scene)
    T = camera_pose()
    T2 = T.copy()
    T2[0, 3] += 0.01  # 1 cm in one frame period: a moving camera, motion effects on
    poses, seeds, prevs = [T, T2, T], [3, 4, 5], [None, T, None]
    with SimulationPool(sim, workers=2) as pool:
        got = list(pool.map(poses, seeds, prevs, max_in_flight=3))
        with pytest.raises(RealgapError, match="2 poses, 1 seeds"):
            list(pool.map(poses[:2], seeds[:1]))
    with SimulationPool(sim, workers=1, slot_bytes=0) as pool:  # results too big for a slot: pickled
        pickled = list(pool.map(poses, seeds, prevs))
        lean = list(pool.map(poses, seeds, prevs, keep_draws=False))  # frames only (synth sequence)
    for a, b in zip(lean, pickled):
        assert a.draws == {} and b.draws
        np.testing.assert_array_equal(a.depth, b.depth)
    assert len(got) == 3
    for P, s, prev, g, p in zip(poses, seeds, prevs, got, pickled):
        ref = sim.simulate(P, seed=s, prev_pose=prev)
        _same(ref, g)
        _same(ref, p)
        for res in (g, p):
            np.testing.assert_array_equal(res.normals, ref.normals)
            np.testing.assert_array_equal(res.draws["ir_capture"]["noise"], ref.draws["ir_capture"]["noise"])
    assert not np.array_equal(got[0].depth, got[1].depth)
