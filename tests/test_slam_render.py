"""Novel-view rendering of a reconstruction (slam.render)."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError
from data_tools.geometry import look_at, pose_to_tum
from data_tools.mesh import TriMesh
from slam.pipeline import make_config, run_slam
from slam.render import UNOBSERVED_RGB, parse_pose, render_mesh, render_run, render_volume, save_view
from slam.tsdf import TSDFConfig, TSDFVolume
from tests.slam_scenes import INTR, camera_path, render_frames, room_scene, write_sequence


def _plane(z: float) -> TriMesh:
    v = np.array([[-5, -5, z], [5, -5, z], [5, 5, z], [-5, 5, z]], float)
    c = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    return TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]]), vertex_colors=c)


def test_render_mesh_depth_is_z_depth_and_colours_interpolate():
    intr = Intrinsics(40, 30, 30.0, 30.0, 19.5, 14.5)
    view = render_mesh(_plane(2.0), intr, np.eye(4))
    np.testing.assert_allclose(view.depth, 2.0, atol=1e-5)        # z-depth, not ray length
    assert view.coverage == 1.0
    # barycentric interpolation: the centre of the plane (world origin) is the mean of the
    # two triangles' shared diagonal end points' colours ((1,0,0) and (0,0,1)) halfway
    centre = view.rgb[14:16, 19:21].reshape(-1, 3).mean(0) / 255
    np.testing.assert_allclose(centre, [0.5, 0.0, 0.5], atol=0.04)


def test_unobserved_pixels_are_magenta():
    intr = Intrinsics(40, 30, 30.0, 30.0, 19.5, 14.5)
    T = np.eye(4)
    T[:3, :3] = np.diag([1, -1, -1])                               # looking away from the plane
    view = render_mesh(_plane(2.0), intr, T)
    assert view.coverage == 0.0 and np.all(view.depth == 0)
    assert np.all(view.rgb == np.array(UNOBSERVED_RGB, np.uint8))


def test_volume_and_mesh_renders_agree_with_the_scene():
    scene = room_scene()
    poses = camera_path(3)
    frames = render_frames(scene, poses)
    vol = TSDFVolume(TSDFConfig(voxel_size_m=0.01, mesh_weight_threshold=1.0))
    for f, T in zip(frames, poses):
        vol.integrate(f.depth, f.rgb, INTR, T)
    # a pose between two observed ones
    T = poses[1].copy()
    T[:3, 3] += [0.0, 0.05, 0.0]
    truth = render_mesh(scene, INTR, T)
    for view in (render_volume(vol, INTR, T), render_mesh(vol.extract_mesh(), INTR, T)):
        m = view.mask & truth.mask
        assert m.mean() > 0.6
        assert np.median(np.abs(view.depth[m] - truth.depth[m])) < 0.005
        colour_err = np.abs(view.rgb[m].astype(float) - truth.rgb[m].astype(float)).mean()
        assert colour_err < 40                                  # fused colour of the texture
        assert np.all(view.rgb[~view.mask] == np.array(UNOBSERVED_RGB, np.uint8))


def test_render_run_and_save_view(tmp_path):
    frames = render_frames(room_scene(), camera_path(4))
    seq = write_sequence(tmp_path / "seq", frames)
    cfg = make_config("icp", "default", {"tsdf.mesh_weight_threshold": 1.0, "backend_config.raycast_scale": 1.0,
                                         "save_volume": True})
    res = run_slam(seq, tmp_path / "run", cfg, progress=False)
    pose = res.trajectory.poses[2]
    for source in ("mesh", "volume"):
        view = render_run(tmp_path / "run", pose, source=source)
        assert view.depth.shape == (INTR.height, INTR.width)
        m = view.mask & (frames[2].depth > 0)
        assert m.mean() > 0.7
        assert np.median(np.abs(view.depth[m] - frames[2].depth[m])) < 0.01
    paths = save_view(view, tmp_path / "out" / "v.png", depth_scale=5000.0)
    rgb = cv2.imread(paths["colour"])[:, :, ::-1]
    np.testing.assert_array_equal(rgb, view.rgb)
    d = cv2.imread(paths["depth"], cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.uint16
    np.testing.assert_allclose(d / 5000.0, view.depth, atol=1.1e-4)
    meta = json.loads((tmp_path / "out" / "v.json").read_text())
    assert meta["coverage"] == pytest.approx(view.coverage)
    half = render_run(tmp_path / "run", pose, scale=0.5)
    assert half.depth.shape == (INTR.height // 2, INTR.width // 2)


def test_parse_pose():
    T = look_at(np.array([1.0, 2.0, 3.0]), np.zeros(3))
    text = " ".join(f"{x:.12f}" for x in pose_to_tum(T))
    np.testing.assert_allclose(parse_pose(text), T, atol=1e-9)
    for bad in ("1 2 3", "a b c d e f g", "0 0 0 0 0 0 0", "0 0 0 0 0 0 5"):
        with pytest.raises(RealgapError):
            parse_pose(bad)
