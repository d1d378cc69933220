"""Trajectory generators, sequence generation (write -> read, resume, empty views) and the CLI."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from app.cli import main
from data_tools.errors import ConfigError, RealgapError
from data_tools.geometry import is_rigid, look_at
from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material, SceneSpec
from data_tools.sequence import SequenceReader
from data_tools.trajectory import Trajectory
from synth.scenes import builtin as scenes_mod
from synth.scenes import registry as scene_registry
from synth import trajectories as traj_mod
from synth.render import IdealRenderer, build_raycasting_scene
from synth.scenes import build_scene
from synth.sequence import SequenceConfig, generate_sequence, make_sequence_trajectory
from synth.trajectories import handheld_jitter, orbit, walkthrough

SMALL = SequenceConfig(frames=3).with_resolution(160, 120)


# --------------------------------------------------------------------------- trajectories

def test_orbit_geometry():
    c = np.array([0.5, -0.2, 0.4])
    tr = orbit(c, 1.5, 0.8, 12, fps=10.0, start_angle_rad=0.3)
    assert np.allclose(tr.timestamps, np.arange(12) / 10.0)
    rel = tr.positions - c
    assert np.allclose(np.linalg.norm(rel[:, :2], axis=1), 1.5)
    assert np.allclose(rel[:, 2], 0.8)
    assert math.atan2(rel[0, 1], rel[0, 0]) == pytest.approx(0.3)
    for T in tr.poses:
        assert is_rigid(T)
        to_c = (c - T[:3, 3]) / np.linalg.norm(c - T[:3, 3])
        assert np.allclose(T[:3, 2], to_c)  # optical axis points at the centre
        assert T[2, 1] < 0  # image y (down) points down: upright
    # a full circle does not repeat its first pose; the angular step is 2 pi / n
    step = np.diff(np.unwrap(np.arctan2(rel[:, 1], rel[:, 0])))
    assert np.allclose(step, 2 * np.pi / 12)
    with pytest.raises(ConfigError):
        orbit(c, 0.0, 1.0, 5)


def test_walkthrough_stays_clear_smooth_and_looks_at_content():
    import open3d as o3d
    scene = build_scene("room")
    tr = walkthrough(scene, 150, seed=3)
    assert len(tr) == 150 and np.allclose(np.diff(tr.timestamps), 1 / 30)
    p = tr.positions
    rs, _ = build_raycasting_scene(scene)
    clearance = rs.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
    assert clearance.min() >= 0.35 - 1e-3  # no wall or furniture within the clearance
    assert np.all((p[:, :2] > [-2.5, -2.0]) & (p[:, :2] < [2.5, 2.0]))
    assert np.all((p[:, 2] >= 1.2 - 1e-6) & (p[:, 2] <= 1.6 + 1e-6))
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1) * 30
    assert speed.max() < 1.5  # m/s: walking pace
    z = tr.poses[:, :3, 2]
    turn = np.degrees(np.arccos(np.clip(np.sum(z[1:] * z[:-1], axis=1), -1, 1))) * 30
    assert turn.max() < 120  # deg/s: no jumps
    assert all(is_rigid(T) for T in tr.poses[::10])
    # the views show furniture, not just walls
    r = IdealRenderer(scene)
    from data_tools.camera import Intrinsics
    intr = Intrinsics(64, 48, 58.0, 58.0, 31.5, 23.5)
    structure = {k + 1 for k, m in enumerate(scene.meshes)
                 if m.name in ("floor", "ceiling", "wall_north", "wall_south", "wall_east", "wall_west")}
    for T in tr.poses[::30]:
        ids = r.render(T, intr, with_rgb=False).instance_ids
        assert np.isin(ids, list(structure), invert=True).mean() > 0.05


def test_walkthrough_avoids_obstacles_at_eye_height():
    import open3d as o3d
    room = build_scene("room")
    pillar = scenes_mod.merge_parts([scenes_mod.box((2.4, 1.6, 2.6), scenes_mod.pose_matrix(None, (0.3, 0.0, 1.3)))],
                                    "pillar", "white_wall")
    scene = SceneSpec(room.meshes + [pillar], room.materials)
    rs, _ = build_raycasting_scene(scene)
    for seed in range(3):
        p = walkthrough(scene, 450, seed=seed, clearance_m=0.3).positions
        d = rs.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
        assert d.min() >= 0.3 - 1e-3


def test_walkthrough_is_replayable_from_its_seed():
    scene = build_scene("room")
    a, b, c = walkthrough(scene, 40, seed=7), walkthrough(scene, 40, seed=7), walkthrough(scene, 40, seed=8)
    assert np.array_equal(a.poses, b.poses)
    assert not np.allclose(a.poses, c.poses)
    one = walkthrough(scene, 1, seed=7)
    assert len(one) == 1 and is_rigid(one.poses[0])


def test_short_walkthrough_turns_no_faster_than_a_long_one():
    """A walk of a few frames has one short segment: its look-at target may not jump the 60 deg
    a 2 s segment allows (that made `realgap demo --frames 12` lose track in 11 of 12 frames)."""
    scene = build_scene("room")
    rates = []
    for seed in range(5):
        for n in (6, 12):
            R = walkthrough(scene, n, seed=seed).poses[:, :3, :3]
            total = math.degrees(math.acos(np.clip((np.trace(R[0].T @ R[-1]) - 1) / 2, -1, 1)))
            rates.append(total / ((n - 1) / 30.0))
    assert max(rates) < 90.0, rates  # deg/s; 45 deg/s per segment plus the eye's own motion
    assert traj_mod._turn_towards(np.array([1.0, 0, 0]), np.array([-1.0, 0, 0]), math.radians(30)) @ \
        np.array([1.0, 0, 0]) == pytest.approx(math.cos(math.radians(30)))


def test_handheld_jitter_statistics():
    n = 3000
    base = Trajectory(np.arange(n) / 30.0, np.tile(np.eye(4), (n, 1, 1)))
    assert np.allclose(handheld_jitter(base, 0, 0.0, 0.0).poses, base.poses)
    j = handheld_jitter(base, seed=1, trans_sigma_m=0.004, rot_sigma_rad=0.002, correlation_s=0.2)
    assert np.array_equal(j.poses, handheld_jitter(base, seed=1, trans_sigma_m=0.004, rot_sigma_rad=0.002,
                                                   correlation_s=0.2).poses)
    t = j.positions
    assert np.allclose(t.std(axis=0), 0.004, rtol=0.3)
    from scipy.spatial.transform import Rotation
    rv = Rotation.from_matrix(j.poses[:, :3, :3]).as_rotvec()
    assert np.allclose(rv.std(axis=0), 0.002, rtol=0.3)
    lag1 = np.corrcoef(t[1:, 0], t[:-1, 0])[0, 1]
    assert lag1 > 0.9  # smooth (correlated over 0.2 s = 6 frames), not white noise
    assert all(is_rigid(T) for T in j.poses[::100])


def test_orbit_kind_stays_inside_the_room():
    scene = build_scene("room")
    tr = traj_mod.make_trajectory("orbit", scene, 20, seed=0)
    p = tr.positions
    assert np.all((np.abs(p[:, 0]) < 2.5) & (np.abs(p[:, 1]) < 2.0) & (p[:, 2] < 2.6))
    with pytest.raises(ConfigError, match="known: loop, orbit, planar, walkthrough"):
        traj_mod.make_trajectory("spiral", scene, 5)


def test_loop_kind_returns_to_its_start_and_sees_it_again():
    """The loop walks 1.15 turns: frame k and frame k + n / 1.15 stand at the same place looking
    the same way (the start is seen again); every eye keeps 0.35 m from the geometry."""
    scene = build_scene("room")
    n = 116
    tr = traj_mod.make_trajectory("loop", scene, n, seed=0)
    k = round((n - 1) / 1.15)          # one full turn later
    np.testing.assert_allclose(tr.poses[k], tr.poses[0], atol=1e-9)
    assert np.linalg.norm(tr.positions[n // 2] - tr.positions[0]) > 1.0     # it went somewhere
    clear = traj_mod._Clearance(scene)
    assert np.all(clear.distance(tr.positions) >= 0.35 - 1e-6)
    with pytest.raises(ConfigError, match="turns"):
        traj_mod.loop(scene, 10, turns=0.5)


# --------------------------------------------------------------------------- sequences

def test_generated_sequence_reads_back_identically(tmp_path):
    out = tmp_path / "seq"
    res = generate_sequence(SMALL, out, progress=False)
    assert (res.frames_total, res.frames_written, res.frames_skipped, res.empty_frames) == (3, 3, 0, 0)
    seq = SequenceReader(out)
    assert len(seq) == 3
    assert seq.intrinsics == SMALL.intrinsics() and seq.camera.depth_scale == 5000.0
    assert seq.camera.sensor is None  # ideal depth: no sensor block
    assert json.loads((out / "config.json").read_text()) == SMALL.to_json()
    assert SequenceConfig.from_json(json.loads((out / "config.json").read_text())) == SMALL
    # re-render independently and compare
    scene = build_scene("room", seed=0)
    traj = make_sequence_trajectory(SMALL, scene)
    r = IdealRenderer(scene)
    for i, frame in enumerate(seq):
        ref = r.render(traj.poses[i], SMALL.intrinsics())
        assert np.abs(frame.depth - ref.depth).max() <= 1.0 / SMALL.depth_scale
        assert np.array_equal(frame.rgb, ref.rgb)
        assert np.allclose(frame.pose, traj.poses[i], atol=1e-6)
        assert frame.timestamp == pytest.approx(i / 30.0, abs=1e-6)
    # scene.json reloads with the same meshes
    back = seq.scene
    assert [m.name for m in back.meshes] == [m.name for m in scene.meshes]
    assert back.materials == {k: v for k, v in scene.materials.items()}
    for a, b in zip(back.meshes, scene.meshes):
        assert a.material == b.material and np.array_equal(a.triangles, b.triangles)
        assert np.allclose(a.vertices, b.vertices, atol=1e-6)


def _truncate_index(path, keep: int) -> None:
    lines = path.read_text().splitlines()
    data = [ln for ln in lines if ln and not ln.startswith("#")]
    head = [ln for ln in lines if ln.startswith("#")]
    path.write_text("\n".join(head + data[:keep]) + "\n")


def test_resume_continues_after_the_written_frames(tmp_path):
    cfg = SequenceConfig(frames=5).with_resolution(80, 60)
    full = tmp_path / "full"
    part = tmp_path / "part"
    generate_sequence(cfg, full, progress=False)
    generate_sequence(cfg, part, progress=False)
    for name in ("depth.txt", "rgb.txt", "groundtruth.txt"):  # simulate a run stopped after 2 frames
        _truncate_index(part / name, 2)
    with pytest.raises(RealgapError, match="already holds a sequence"):
        generate_sequence(cfg, part, progress=False)
    res = generate_sequence(cfg, part, resume=True, progress=False)
    assert (res.frames_skipped, res.frames_written, res.frames_total) == (2, 3, 5)
    a, b = SequenceReader(full), SequenceReader(part)
    assert np.array_equal(a.timestamps, b.timestamps)
    for fa, fb in zip(a, b):
        assert np.array_equal(fa.depth, fb.depth) and np.array_equal(fa.rgb, fb.rgb)
        assert np.allclose(fa.pose, fb.pose, atol=1e-9)
    again = generate_sequence(cfg, part, resume=True, progress=False)  # complete: nothing to do
    assert again.frames_written == 0 and again.frames_total == 5
    with pytest.raises(ConfigError, match="differs .* seed"):
        generate_sequence(SequenceConfig(frames=5, seed=1).with_resolution(80, 60), part, resume=True,
                          progress=False)
    res = generate_sequence(cfg, part, overwrite=True, progress=False)
    assert res.frames_written == 5 and len(SequenceReader(part)) == 5


def test_empty_views_are_written_and_counted(tmp_path, monkeypatch):
    def one_plane(seed: int = 0) -> SceneSpec:
        q = TriMesh([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], [[0, 1, 2], [0, 2, 3]], "ground", "m")
        return SceneSpec([q], {"m": Material(0.4, 0.0)})

    def half_sky(scene, n, seed, fps):  # even frames look down at the plane, odd frames at the sky
        poses = [look_at([0, 0, 1.5], [0.1, 0, 0] if i % 2 == 0 else [0.1, 0, 3.0]) for i in range(n)]
        return Trajectory(np.arange(n) / fps, np.stack(poses))

    monkeypatch.setitem(scene_registry.SCENES, "test_plane", one_plane)
    monkeypatch.setitem(traj_mod.TRAJECTORY_KINDS, "test_half_sky", half_sky)
    cfg = SequenceConfig(scene="test_plane", trajectory="test_half_sky", frames=4, jitter_trans_m=0,
                         jitter_rot_rad=0).with_resolution(40, 30)
    res = generate_sequence(cfg, tmp_path / "s", progress=False)
    assert res.frames_total == 4 and res.empty_frames == 2
    seq = SequenceReader(tmp_path / "s")
    assert len(seq) == 4
    assert np.all(seq[1].depth == 0) and np.all(seq[3].depth == 0)
    assert np.all(seq[0].depth > 0) and seq[1].pose is not None


def test_sequence_config_validation():
    with pytest.raises(ConfigError):
        SequenceConfig(frames=0)
    with pytest.raises(ConfigError):
        SequenceConfig(fx=-1.0)
    c = SequenceConfig().with_resolution(320, 240)
    assert (c.fx, c.cx, c.cy) == (290.0, 159.5, 119.5)


# --------------------------------------------------------------------------- CLI

def test_cli_sequence_and_scenes(tmp_path, capsys):
    out = tmp_path / "cli_seq"
    argv = ["synth", "sequence", "--scene", "room", "--frames", "3", "--out", str(out),
            "--width", "160", "--height", "120", "--seed", "2"]
    assert main(argv) == 0
    assert "wrote 3 frames" in capsys.readouterr().out
    seq = SequenceReader(out)
    assert len(seq) == 3 and seq.intrinsics.width == 160 and seq.intrinsics.fx == pytest.approx(145.0)
    assert json.loads((out / "config.json").read_text())["seed"] == 2
    assert main(argv) == 1  # finished, neither --resume nor --overwrite: the re-run rule
    assert "--overwrite" in capsys.readouterr().err
    assert main(argv + ["--resume"]) == 0
    assert "kept 3" in capsys.readouterr().out
    assert main(["synth", "sequence", "--scene", "nowhere", "--out", str(tmp_path / "x")]) == 1
    assert "unknown scene 'nowhere'" in capsys.readouterr().err
    assert main(["synth", "scenes"]) == 0
    listing = capsys.readouterr().out
    for name in ("room", "chair_a", "chair_c", "scenenet_room", "tless_obj"):
        assert name in listing
    assert "path=<required>" in listing


def test_cli_sensor_sequence_writes_simulated_and_ideal(tmp_path):
    from app.cli import main as cli_main
    from data_tools.sequence import SequenceReader
    out = tmp_path / "sim"
    assert cli_main(["synth", "sequence", "--scene", "room", "--frames", "2", "--sensor", "kinect_v1",
                     "--out", str(out)]) == 0
    sim, ideal = SequenceReader(out), SequenceReader(out / "ideal")
    assert len(sim) == len(ideal) == 2
    assert sim.camera.sensor is not None and sim.camera.sensor.type == "structured_light"
    assert (out / "sensor_config.json").exists() and sim.has_scene
    # frame 0 has no previous pose (no motion effects); a 2-frame walkthrough jumps across the
    # room between frames, so frame 1 is dominated by rolling shutter / motion on that jump
    d_sim, d_ideal = sim[0].depth, ideal[0].depth
    both = (d_sim > 0) & (d_ideal > 0)
    assert both.mean() > 0.3                      # the sensor sees most of the room
    assert not np.array_equal(d_sim, d_ideal)     # and is not the ideal depth
    assert np.median(np.abs(d_sim[both] - d_ideal[both])) < 0.02
    np.testing.assert_allclose(sim.poses, ideal.poses, atol=1e-7)
    # ideal/config.json describes the images it holds (the sensor's grid, not the preset's size)
    import json
    c = json.loads((out / "ideal" / "config.json").read_text())
    assert (c["height"], c["width"]) == d_ideal.shape == d_sim.shape


def test_cli_sensor_sequence_workers_write_the_same_frames(tmp_path):
    """--workers 2 (SimulationPool) writes the same depth PNGs as the serial run."""
    from app.cli import main as cli_main
    args = ["synth", "sequence", "--scene", "room", "--frames", "3", "--sensor", "kinect_v1"]
    assert cli_main([*args, "--out", str(tmp_path / "serial")]) == 0
    assert cli_main([*args, "--workers", "2", "--out", str(tmp_path / "pool")]) == 0
    a = sorted((tmp_path / "serial" / "depth").iterdir())
    b = sorted((tmp_path / "pool" / "depth").iterdir())
    assert [p.name for p in a] == [p.name for p in b] and len(a) == 3
    for pa, pb in zip(a, b):
        assert pa.read_bytes() == pb.read_bytes(), pa.name
