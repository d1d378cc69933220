"""KITTI, EuRoC and Open3D .log trajectories: write -> read round trips, the same poses as evo
(KITTI, EuRoC, TUM) and Open3D (.log) read from the same file, format detection, bad files, and
the Open3D intrinsic JSON as a camera."""
from __future__ import annotations

import json

import numpy as np
import pytest

from data_tools.errors import FormatError
from data_tools.trajectory import Trajectory
from data_tools.trajectory_formats import detect_format, read_trajectory, write_trajectory


def _traj(n: int = 12, seed: int = 3) -> Trajectory:
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.6, size=(n, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    return Trajectory(100.0 + 0.1 * np.arange(n), poses)


@pytest.mark.parametrize("name, fmt", [("t.txt", "tum"), ("t.kitti", "kitti"), ("k.txt", "kitti"),
                                       ("t.csv", "euroc"), ("t.log", "log")])
def test_round_trip_and_detection(tmp_path, name, fmt):
    t = _traj()
    p = write_trajectory(tmp_path / name, t, fmt)
    assert detect_format(p) == fmt
    back = read_trajectory(p)
    np.testing.assert_allclose(back.poses, t.poses, atol=1e-6)
    if fmt in ("tum", "euroc"):
        np.testing.assert_allclose(back.timestamps, t.timestamps, atol=1e-6)
    else:  # no time in the file: pose k at t = k (as evo pairs such files)
        np.testing.assert_array_equal(back.timestamps, np.arange(len(t)))


def test_same_poses_as_evo(tmp_path):
    fi = pytest.importorskip("evo.tools.file_interface")
    t = _traj()
    k = write_trajectory(tmp_path / "a.kitti", t)
    np.testing.assert_allclose(read_trajectory(k).poses, np.array(fi.read_kitti_poses_file(str(k)).poses_se3),
                               atol=1e-12)
    e = write_trajectory(tmp_path / "a.csv", t)
    ev = fi.read_euroc_csv_trajectory(str(e))
    ours = read_trajectory(e)
    np.testing.assert_allclose(ours.timestamps, ev.timestamps, atol=1e-9)
    np.testing.assert_allclose(ours.poses, np.array(ev.poses_se3), atol=1e-9)
    u = write_trajectory(tmp_path / "a.txt", t)
    np.testing.assert_allclose(read_trajectory(u).poses, np.array(fi.read_tum_trajectory_file(str(u)).poses_se3),
                               atol=1e-9)


def test_log_as_open3d_reads_and_writes_it(tmp_path):
    o3d = pytest.importorskip("open3d")
    t = _traj()
    p = write_trajectory(tmp_path / "a.log", t)
    cams = o3d.io.read_pinhole_camera_trajectory(str(p))
    # Open3D keeps extrinsics (world -> camera): the inverse of the pose in the file
    ext = np.array([c.extrinsic for c in cams.parameters])
    np.testing.assert_allclose(np.linalg.inv(ext), t.poses, atol=1e-6)
    o3d.io.write_pinhole_camera_trajectory(str(tmp_path / "o3d.log"), cams)
    np.testing.assert_allclose(read_trajectory(tmp_path / "o3d.log").poses, t.poses, atol=1e-6)


def test_ate_of_kitti_files_equals_tum(tmp_path):
    """The same poses in KITTI files give the ATE of the TUM files (pairing by index)."""
    from slam.metrics import ate
    ref = _traj(20, 1)
    est = Trajectory(ref.timestamps, ref.poses.copy())
    est.poses[:, :3, 3] += np.random.default_rng(0).normal(scale=0.01, size=(20, 3))
    for name, tr in (("ref", ref), ("est", est)):
        write_trajectory(tmp_path / f"{name}.kitti", tr)
    a = ate(read_trajectory(tmp_path / "ref.kitti"), read_trajectory(tmp_path / "est.kitti"), "se3")
    b = ate(ref, est, "se3")
    assert a.rmse == pytest.approx(b.rmse, abs=1e-9)


@pytest.mark.parametrize("name, text, words", [
    ("a.kitti", "1 0 0 0 0 1 0 0 0 0 1\n", ["line 1", "12 values"]),
    ("a.kitti", "2 0 0 0 0 1 0 0 0 0 1 0\n", ["line 1", "not a rotation"]),
    ("a.kitti", "1 0 0 nan 0 1 0 0 0 0 1 0\n", ["line 1", "NaN"]),
    ("a.csv", "#t,x\n2,0,0,0,1,0,0,0\n1,0,0,0,1,0,0,0\n", ["not sorted"]),
    ("a.csv", "1,0,0,0,2,0,0,0\n", ["line 1", "unit length"]),
    ("a.log", "0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", ["blocks of 5"]),
    ("a.log", "0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 2\n", ["0 0 0 1"]),
    ("a.txt", "1 2 3 4 5\n", ["5 values", "--format"]),
    ("a.txt", "", ["no poses"]),
])
def test_bad_files_name_file_and_line(tmp_path, name, text, words):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(FormatError) as e:
        read_trajectory(p)
    msg = str(e.value)
    assert str(p) in msg and "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_folder_given_as_trajectory(tmp_path):
    with pytest.raises(FormatError, match="is a folder"):
        read_trajectory(tmp_path)


def test_open3d_intrinsic_json_is_a_camera(tmp_path):
    o3d = pytest.importorskip("open3d")
    from data_tools.camera import read_camera_json
    path = tmp_path / "intr.json"
    o3d.io.write_pinhole_camera_intrinsic(str(path), o3d.camera.PinholeCameraIntrinsic(640, 480, 525.0, 520.0,
                                                                                       319.5, 239.5))
    with pytest.warns(UserWarning, match="no depth scale"):
        cam = read_camera_json(path)
    i = cam.intrinsics
    assert (i.width, i.height, i.fx, i.fy, i.cx, i.cy) == (640, 480, 525.0, 520.0, 319.5, 239.5)
    assert cam.depth_scale == 1000.0
    d = json.loads(path.read_text())
    d["depth_scale"] = 5000.0
    path.write_text(json.dumps(d))
    assert read_camera_json(path).depth_scale == 5000.0


def test_eval_ate_reads_every_format(tmp_path, capsys):
    from app.cli import main
    ref = _traj(20, 1)
    est = Trajectory(ref.timestamps, ref.poses.copy())
    est.poses[:, :3, 3] += 0.01
    write_trajectory(tmp_path / "ref.csv", ref)
    write_trajectory(tmp_path / "est.txt", est)
    assert main(["eval", "ate", str(tmp_path / "ref.csv"), str(tmp_path / "est.txt"), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["pairs"] == 20 and printed["rmse"] < 1e-6        # the ate.json object
