"""The SLAM run loop and RUN folder: outputs, failures, resume, configuration, CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from data_tools.errors import ConfigError, RealgapError
from data_tools.sequence import SequenceReader
from data_tools.trajectory import read_tum
from slam.pipeline import SlamConfig, load_run, make_config, run_slam
from slam.registration import config_to_dict
from tests.slam_scenes import camera_path, render_frames, room_scene, write_sequence

N_FRAMES = 8


def _small(backend="icp", **over):
    """A configuration sized for the 320x240 test sequences."""
    o = {"tsdf.voxel_size_m": 0.01, "tsdf.mesh_weight_threshold": 1.0}
    o.update({"backend_config.raycast_scale": 1.0} if backend == "icp" else
             {"backend_config.levels": [2, 1, 0]})
    o.update(over)
    return make_config(backend, "default", o)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    root = tmp_path_factory.mktemp("slamseq")
    frames = render_frames(room_scene(), camera_path(N_FRAMES, 0.02, 1.0))
    return write_sequence(root / "seq", frames)


@pytest.fixture(scope="module")
def seq_black(tmp_path_factory):
    """The same sequence with frame 3 dropped to an all-zero (black) depth and colour image."""
    root = tmp_path_factory.mktemp("slamseq_black")
    frames = render_frames(room_scene(), camera_path(N_FRAMES, 0.02, 1.0))
    frames[3].depth[:] = 0
    frames[3].rgb[:] = 0
    return write_sequence(root / "seq", frames)


def _ate(run_traj, seq_path):
    from slam.metrics import ate
    return ate(SequenceReader(seq_path).trajectory, run_traj).stats["rmse"]


@pytest.mark.parametrize("backend", ["icp", "rgbd_odometry"])
def test_run_writes_the_run_folder(tmp_path, seq, backend):
    res = run_slam(seq, tmp_path / "run", _small(backend), progress=False)
    run = tmp_path / "run"
    for name in ("trajectory.txt", "stats.json", "config.json", "camera.json", "mesh.ply"):
        assert (run / name).is_file(), name
    assert not (run / "checkpoint.json").exists()
    stats = json.loads((run / "stats.json").read_text())
    assert stats["backend"] == backend and stats["complete"] is True
    assert stats["frames"] == N_FRAMES and stats["frames_failed"] == 0 and stats["failed_timestamps"] == []
    assert stats["frames_per_second"] > 0
    assert len(stats["per_frame"]) == N_FRAMES
    assert {"timestamp", "fitness", "inlier_rmse", "failed"} <= set(stats["per_frame"][1])
    assert 0.5 < stats["per_frame"][1]["fitness"] <= 1.0
    traj = read_tum(run / "trajectory.txt")
    assert len(traj) == N_FRAMES
    np.testing.assert_allclose(traj.poses[0], np.eye(4), atol=1e-7)
    assert _ate(traj, seq) < 0.003                      # 3 mm on noise-free data
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["config"]["backend"] == backend and cfg["sequence"] == str(seq.resolve())
    assert res.frames_per_second == pytest.approx(stats["frames_per_second"])


@pytest.mark.parametrize("backend", ["icp", "rgbd_odometry"])
def test_black_depth_frame_is_reported_not_a_crash(tmp_path, seq_black, backend):
    res = run_slam(seq_black, tmp_path / "run", _small(backend), progress=False)
    ts = SequenceReader(seq_black).timestamps
    assert res.failed_timestamps == [pytest.approx(ts[3])]
    row = res.stats["per_frame"][3]
    assert row["failed"] and "valid depth" in row["reason"]
    assert len(res.trajectory) == N_FRAMES - 1
    assert not np.any(np.isclose(res.trajectory.timestamps, ts[3]))
    assert _ate(res.trajectory, seq_black) < 0.005


def test_unreadable_frame_stops_the_run_unless_skipped(tmp_path, seq):
    """A corrupt input frame is an error naming the file (frames before it are checkpointed, a
    re-run continues); with skip_unreadable it is a failed frame of the result."""
    import shutil
    from data_tools.errors import FormatError
    from data_tools.outputs import read_incomplete
    s = tmp_path / "seq"
    shutil.copytree(seq, s)
    victim = sorted((s / "depth").iterdir())[2]
    victim.write_bytes(b"not a png")
    with pytest.raises(FormatError, match=f"{victim.name}.*--skip-unreadable"):
        run_slam(s, tmp_path / "stop", _small(), progress=False)
    marker = read_incomplete(tmp_path / "stop")
    assert marker is not None and marker["done"] == 2 and marker["total"] == N_FRAMES
    res = run_slam(s, tmp_path / "run", _small(), progress=False, skip_unreadable=True)
    assert res.stats["frames_failed"] == 1 and "unreadable" in res.stats["per_frame"][2]["reason"]
    assert read_incomplete(tmp_path / "run") is None


def test_runs_are_bit_reproducible(tmp_path, seq):
    """Same input and settings, default threads: the same trajectory and mesh bytes (Open3D's odometry
    sums run on one thread; the mesh is written in canonical order)."""
    a = run_slam(seq, tmp_path / "a", _small(), progress=False)
    b = run_slam(seq, tmp_path / "b", _small(), progress=False)
    assert a.complete and b.complete
    for f in ("trajectory.txt", "mesh.ply"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f


def test_interrupted_run_resumes_to_the_same_result(tmp_path, seq):
    cfg = _small(checkpoint_every=2)
    full = run_slam(seq, tmp_path / "full", cfg, progress=False)
    part = run_slam(seq, tmp_path / "part", cfg, progress=False, stop_after=3)
    assert not part.complete and (tmp_path / "part" / "checkpoint.json").is_file()
    assert not (tmp_path / "part" / "trajectory.txt").exists()
    seen = []
    done = run_slam(seq, tmp_path / "part", cfg, progress=False, on_frame=lambda i, r: seen.append(i))
    assert seen == list(range(3, N_FRAMES))            # continued, did not restart
    assert done.complete
    # the checkpoint keeps poses exactly and re-integration rebuilds the same volume
    np.testing.assert_array_equal(done.trajectory.poses, full.trajectory.poses)
    again = run_slam(seq, tmp_path / "part", cfg, progress=False, on_frame=lambda i, r: seen.append(i))
    assert again.complete and seen == list(range(3, N_FRAMES))     # finished runs are not redone


def test_ctrl_c_leaves_a_checkpoint(tmp_path, seq):
    cfg = _small()

    def boom(i, r):
        if i == 4:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_slam(seq, tmp_path / "run", cfg, progress=False, on_frame=boom)
    ck = json.loads((tmp_path / "run" / "checkpoint.json").read_text())
    assert ck["next"] == 5
    res = run_slam(seq, tmp_path / "run", cfg, progress=False)
    assert res.complete and len(res.trajectory) == N_FRAMES


def test_existing_run_with_another_config_is_refused(tmp_path, seq):
    run_slam(seq, tmp_path / "run", _small(), progress=False, stop_after=2)
    other = _small(**{"tsdf.voxel_size_m": 0.02})
    with pytest.raises(RealgapError, match="different configuration.*voxel_size_m"):
        run_slam(seq, tmp_path / "run", other, progress=False)
    res = run_slam(seq, tmp_path / "run", other, progress=False, overwrite=True)
    assert res.complete and load_run(tmp_path / "run").config.tsdf.voxel_size_m == 0.02


def test_config_round_trip_and_errors():
    cfg = make_config("rgbd_odometry", "fast", {"backend_config.method": "point_to_plane", "max_frames": 5})
    d = json.loads(json.dumps(cfg.to_dict()))
    back = SlamConfig.from_dict(d)
    assert config_to_dict(back) == d and back.tsdf.voxel_size_m == 0.02
    assert back.backend_config.method == "point_to_plane" and back.backend_config.levels == (3, 2, 1)
    with pytest.raises(ConfigError, match="unknown option"):
        make_config("icp", "default", {"tsdf.voxel": 1})
    with pytest.raises(ConfigError, match="min_fitness"):
        make_config("icp", "default", {"backend_config.min_fitness": "abc"})
    with pytest.raises(ConfigError, match="preset"):
        make_config("icp", "nope")
    with pytest.raises(ConfigError, match="unknown option"):
        SlamConfig.from_dict({"backend": "icp", "bogus": 1})


def test_cli_run_and_render(tmp_path, seq, capsys):
    run = tmp_path / "run"
    rc = main(["slam", "run", str(seq), "--backend", "icp", "--out", str(run), "--no-progress",
               "--tsdf.voxel_size_m", "0.01", "--tsdf.mesh-weight-threshold", "1",
               "--icp.raycast_scale", "1", "--icp.iterations", "10,5,4"])
    assert rc == 0
    out = capsys.readouterr().out
    assert f"{N_FRAMES}/{N_FRAMES} frames registered" in out
    cfg = load_run(run).config
    assert cfg.backend_config.iterations == (10, 5, 4) and cfg.tsdf.mesh_weight_threshold == 1.0
    from data_tools.results import read_result
    res = read_result(run)   # stats.json with the result header
    assert res.kind == "slam.run" and res.header["inputs"][0]["role"] == "sequence"
    assert res.header["parameters"]["backend"] == "icp" and res.metrics["frames_tracked"] == N_FRAMES
    # re-running the finished command is refused before any work, naming --overwrite (the re-run rule)
    before = (run / "trajectory.txt").read_bytes()
    assert main(["slam", "run", str(seq), "--backend", "icp", "--out", str(run), "--no-progress",
                 "--tsdf.voxel_size_m", "0.01", "--tsdf.mesh-weight-threshold", "1",
                 "--icp.raycast_scale", "1", "--icp.iterations", "10,5,4"]) == 1
    assert (run / "trajectory.txt").read_bytes() == before
    png = tmp_path / "view.png"
    assert main(["slam", "render", str(run), "--frame", "2", "--out", str(png)]) == 0
    assert png.is_file() and (tmp_path / "view_depth.png").is_file() and (tmp_path / "view.json").is_file()


def test_cli_errors_are_one_line(tmp_path, seq, capsys):
    rc = main(["slam", "run", str(seq), "--backend", "icp", "--out", str(tmp_path / "r"),
               "--rgbd_odometry.method", "hybrid"])
    assert rc == 1
    assert "option of backend rgbd_odometry" in capsys.readouterr().err
    rc = main(["slam", "run", str(tmp_path / "missing"), "--out", str(tmp_path / "r2")])
    assert rc == 1
    assert "sequence folder not found" in capsys.readouterr().err


def test_backend_with_the_old_three_argument_init_still_gets_the_sensor():
    from slam.pipeline import _make_backend
    from slam.registration import RegistrationBackend

    class Old(RegistrationBackend):
        def __init__(self, config, intrinsics, tsdf_config):  # written before `sensor` existed
            super().__init__(config, intrinsics, tsdf_config)

    class New(RegistrationBackend):
        pass

    for cls in (Old, New):
        b = _make_backend(cls, None, "intr", "tsdf", sensor="S")
        assert b.sensor == "S" and b.intrinsics == "intr" and b.tsdf_config == "tsdf"
