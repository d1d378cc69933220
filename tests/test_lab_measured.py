"""MeasuredSequence (load, derived preset, cached renders, seeded simulation, observations),
model files and their error messages. Fixture: a tiny sequence (160x120, 4 frames) written by
the independent generator of tests/hidden_effects.py."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from data_tools.errors import ConfigError, FormatError
from synth.lab import MeasuredSequence, compare, load_model, save_model
from synth.lab.model import load_fit_info

from tests import hidden_effects as he


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    out = tmp_path_factory.mktemp("lab_measured") / "seq"
    params = he.generate(out, None, seed=5, n_frames=4, width=160, height=120)
    return out, params


def test_load_derives_the_preset_from_camera_json(seq):
    path, _ = seq
    ms = MeasuredSequence.load(path)
    assert len(ms) == 4 and ms.frame_indices == [0, 1, 2, 3] and ms.skipped_no_pose == 0
    p = ms.preset
    assert (p.width, p.height, p.fx, p.cx) == (160, 120, 145.0, 79.5)
    assert p.type == "structured_light" and p.baseline_m == pytest.approx(0.075)
    assert p.projector_offset_m == pytest.approx((0.075, 0.0, 0.0))
    assert p.min_depth_m == 0.45  # kept from kinect_v1
    assert ms.poses.shape == (4, 4, 4) and ms.prev_poses[1] is not None
    np.testing.assert_allclose(ms.prev_poses[1], ms.poses[0])
    # the first frame has no previous one: the next frame's motion extrapolated one period back
    # (constant velocity: the translation steps back by what the next frame moves forward)
    P0 = ms.prev_poses[0]
    np.testing.assert_allclose(P0[:3, 3], 2 * ms.poses[0][:3, 3] - ms.poses[1][:3, 3], atol=1e-4)   # timestamps to 1 us
    np.testing.assert_allclose(P0[:3, :3] @ P0[:3, :3].T, np.eye(3), atol=1e-9)
    d = ms.measured_depth(2)
    assert d.shape == (120, 160) and d.dtype == np.float32 and (d > 0).mean() > 0.5


def test_renders_are_cast_once_and_match_the_measured_geometry(seq):
    path, params = seq
    ms = MeasuredSequence.load(path)
    r1 = ms.render(1)
    assert ms.render(1) is r1
    m = ms.measured_depth(1)
    both = (m > 0) & (r1.depth > 0)
    # base effects only: measured = ideal + disparity noise, |error| / (z^2 sigma_d / f b) is half-normal
    z = r1.depth[both].astype(np.float64)
    sigma = z * z * params["sigma_d_px"] / (ms.preset.fx * ms.preset.baseline_m)
    assert np.median(np.abs(m[both] - z) / sigma) == pytest.approx(0.6745, rel=0.1)


def test_max_frames_spreads_evenly(seq):
    ms = MeasuredSequence.load(seq[0], max_frames=2)
    assert ms.frame_indices == [0, 3]
    with pytest.raises(ConfigError):
        MeasuredSequence.load(seq[0], max_frames=0)


def test_frame_positions_select_any_subset(seq):
    # a cross-validation fold's complement (positions 0, 1, 3) is no slice; the order given is kept
    ms = MeasuredSequence.load(seq[0], frames=[0, 1, 3])
    assert ms.frame_indices == [0, 1, 3]
    assert MeasuredSequence.load(seq[0], frame_slice="1::2", frames=[1]).frame_indices == [3]
    np.testing.assert_array_equal(ms.measured_depth(2), MeasuredSequence.load(seq[0]).measured_depth(3))
    for bad in ([], [4], [-1]):
        with pytest.raises(ConfigError, match="frame positions|no frame positions"):
            MeasuredSequence.load(seq[0], frames=bad)


def test_k_fold_splits_hold_every_frame_out_once():
    from benchmarks.bench_plane_noise import splits
    folds = splits(10, "kfold", 5)
    held = np.concatenate([h for _, h in folds])
    np.testing.assert_array_equal(held, np.arange(10))          # each frame held out once, in order
    for fit, h in folds:
        assert len(h) == 2 and not set(fit) & set(h) and len(fit) + len(h) == 10
    (fit, h), = splits(10, "alternate", 5)
    assert list(fit) == [0, 2, 4, 6, 8] and list(h) == [1, 3, 5, 7, 9]
    (fit, h), = splits(9, "halves", 5)
    assert list(fit) == [0, 1, 2, 3] and list(h) == [4, 5, 6, 7, 8]
    with pytest.raises(SystemExit, match="--folds 11"):
        splits(10, "kfold", 11)


def test_simulation_seed_follows_the_frame_index(seq):
    ms = MeasuredSequence.load(seq[0])
    cfg = ms.default_config(["axial_noise", "range_limits"])
    full = ms.simulate(cfg, seed=3)
    part = ms.simulate(cfg, seed=3, frames=[2])
    assert np.array_equal(full[2], part[0])
    assert not np.array_equal(full[1], ms.simulate(cfg, seed=4, frames=[1])[0])
    sub = MeasuredSequence.load(seq[0], max_frames=2)     # frames 0 and 3 of the sequence
    assert np.array_equal(sub.simulate(cfg, seed=3)[1], full[3])
    obs = ms.observations(full)
    assert [o.index for o in obs] == [0, 1, 2, 3] and obs[0].projector_offset_m == (0.075, 0.0, 0.0)
    assert compare(obs).gap > 0


def test_missing_or_bad_files_name_the_file(seq, tmp_path):
    src, _ = seq
    for name, needle in (("scene.json", "scene.json"), ("groundtruth.txt", "groundtruth.txt"),
                         ("camera.json", "camera.json")):
        bad = tmp_path / name.replace(".", "_")
        shutil.copytree(src, bad)
        (bad / name).unlink()
        with pytest.raises(FormatError, match=needle):
            MeasuredSequence.load(bad)
    # a structured-light projector off the camera x axis is impossible for the preset
    bad = tmp_path / "offaxis"
    shutil.copytree(src, bad)
    cam = json.loads((bad / "camera.json").read_text())
    cam["sensor"]["projector_offset_m"] = [0.0, 0.075, 0.0]
    (bad / "camera.json").write_text(json.dumps(cam))
    with pytest.raises(FormatError, match="camera.json"):
        MeasuredSequence.load(bad)
    with pytest.raises(FormatError, match="not found"):
        MeasuredSequence.load(tmp_path / "nope")


def test_frames_without_pose_are_skipped_and_counted(seq, tmp_path):
    bad = tmp_path / "halfpose"
    shutil.copytree(seq[0], bad)
    gt = bad / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    data = [ln for ln in lines if not ln.startswith("#")]
    gt.write_text("\n".join([ln for ln in lines if ln.startswith("#")] + data[:2]) + "\n")
    ms = MeasuredSequence.load(bad)
    assert ms.frame_indices == [0, 1] and ms.skipped_no_pose == 2


def test_model_file_round_trip_and_errors(seq, tmp_path):
    ms = MeasuredSequence.load(seq[0])
    cfg = ms.default_config(["axial_noise", "range_limits"]).with_params({"axial_noise.sigma2_per_m": 0.003})
    p = save_model(cfg, tmp_path / "m" / "model.json", {"gap": 0.5})
    back = load_model(p)
    assert back.to_json() == cfg.to_json()
    assert load_fit_info(p) == {"gap": 0.5}
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(FormatError, match="bad.json"):
        load_model(tmp_path / "bad.json")
    (tmp_path / "wrong.json").write_text(json.dumps({"preset": "kinect_v1", "effects": ["no_such_effect"]}))
    with pytest.raises(FormatError, match="wrong.json.*no_such_effect"):
        load_model(tmp_path / "wrong.json")


def test_previous_pose_of_a_lone_frame_is_none_and_a_gap_is_not_bridged():
    from synth.lab.measured import _previous_pose
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, 0, 3] = [0.0, 0.01, 0.02]
    t = np.array([0.0, 1 / 30, 2 / 30])
    assert _previous_pose(T[:1], t[:1], 0, 1 / 30) is None                 # a single frame: static
    np.testing.assert_allclose(_previous_pose(T, t, 0, 1 / 30)[0, 3], -0.01)
    np.testing.assert_allclose(_previous_pose(T, t, 2, 1 / 30)[0, 3], 0.01)
    far = np.array([0.0, 0.5, 0.6])                                        # the next frame 15 periods later
    assert _previous_pose(T, far, 0, 1 / 30) is None
