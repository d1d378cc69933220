"""Registration backends on rendered pairs: known motion recovered, agreement with Open3D's
ICP, failure checks (black frame, no overlap, implausible motion)."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.sequence import Frame
from slam.backends._pyramid import Pyramid, icp_point_to_plane
from slam.backends.icp import ICPBackend, ICPConfig
from slam.backends.rgbd_odometry import RGBDOdometryBackend, RGBDOdometryConfig
from slam.registration import (TrackResult, get_backend, backend_names, implausible_motion,
                               rotation_angle_deg)
from slam.tsdf import TSDFConfig, TSDFVolume
from tests.slam_scenes import INTR, camera_path, render_frames, room_scene


@pytest.fixture(scope="module")
def pair():
    scene = room_scene()
    poses = camera_path(2, step_m=0.02, step_deg=1.0)
    return scene, poses, render_frames(scene, poses)


def _err(T_est, T_true):
    D = np.linalg.inv(T_true) @ T_est
    return np.linalg.norm(D[:3, 3]), rotation_angle_deg(D)


def test_projective_icp_recovers_known_motion(pair):
    """Frame-to-frame point-to-plane ICP on noise-free rendered depth: < 1 mm, < 0.1 deg."""
    _, poses, fr = pair
    true = np.linalg.inv(poses[0]) @ poses[1]          # source (frame 1) -> target (frame 0)
    t_err0, r_err0 = _err(np.eye(4), true)
    assert t_err0 > 0.015 and r_err0 > 0.5             # the motion is not trivial
    src = Pyramid(fr[1].depth, INTR, 3, 0.1, 5.0)
    tgt = Pyramid(fr[0].depth, INTR, 3, 0.1, 5.0)
    levels = [2, 1, 0]
    sol = icp_point_to_plane([src[l] for l in levels], [(tgt[l].vertex(), tgt[l].normal(), tgt[l].K()) for l in levels],
                             np.eye(4), [10, 10, 10], [0.1, 0.05, 0.02])
    t_err, r_err = _err(sol.transformation, true)
    assert t_err < 1e-3 and r_err < 0.1
    assert sol.fitness > 0.8 and sol.inlier_rmse < 1e-3


def _track_pair(backend_cls, cfg, fr, tsdf):
    vol = TSDFVolume(tsdf)
    b = backend_cls(cfg, INTR, tsdf)
    r0 = b.track(fr[0], vol)
    assert not r0.failed and np.allclose(r0.pose, np.eye(4))
    vol.integrate(fr[0].depth, fr[0].rgb, INTR, r0.pose)
    return b, vol, b.track(fr[1], vol)


def test_frame_to_model_icp_recovers_known_motion(pair):
    """The icp backend (ray-cast TSDF model of frame 0, frame 1 tracked against it) with the
    sub-voxel model refinement: < 1 mm, < 0.1 deg."""
    _, poses, fr = pair
    tsdf = TSDFConfig(voxel_size_m=0.005, block_resolution=16, integrate_color=False)
    _, _, r1 = _track_pair(ICPBackend, ICPConfig(raycast_scale=1.0, refine_model=True), fr, tsdf)
    assert not r1.failed, r1.reason
    t_err, r_err = _err(r1.pose, np.linalg.inv(poses[0]) @ poses[1])
    assert t_err < 1e-3 and r_err < 0.1
    assert r1.fitness > 0.5 and r1.inlier_rmse < 0.005


def test_frame_to_model_icp_raw_raycast_is_within_a_voxel_and_the_default_is_better(pair):
    """``refine_model = false`` tracks against Open3D's raw ray cast (as Open3D's dense SLAM
    does), whose surface is up to one voxel off: the pose error stays below one voxel; the
    default (verified, refined model) is more accurate."""
    _, poses, fr = pair
    tsdf = TSDFConfig(voxel_size_m=0.005, block_resolution=16, integrate_color=False)
    true = np.linalg.inv(poses[0]) @ poses[1]
    assert ICPConfig().refine_model
    _, _, raw = _track_pair(ICPBackend, ICPConfig(raycast_scale=1.0, refine_model=False), fr, tsdf)
    _, _, ref = _track_pair(ICPBackend, ICPConfig(raycast_scale=1.0), fr, tsdf)
    assert not raw.failed, raw.reason
    assert _err(raw.pose, true)[0] < tsdf.voxel_size_m
    assert _err(ref.pose, true)[0] < _err(raw.pose, true)[0]


def test_frame_to_model_icp_agrees_with_open3d_registration_icp(pair):
    """Same inputs (frame-1 points, the model view of frame 0 with its normals), Open3D's
    nearest-neighbour point-to-plane ``registration_icp`` converges to our projective result."""
    import open3d as o3d
    from data_tools.geometry import unproject
    from slam.backends._pyramid import smooth_normal_map
    _, poses, fr = pair
    tsdf = TSDFConfig(voxel_size_m=0.005, block_resolution=16, integrate_color=False)
    b, vol, r1 = _track_pair(ICPBackend, ICPConfig(raycast_scale=1.0, refine_model=True), fr, tsdf)
    ours = r1.pose                                      # frame-1 camera -> frame-0 camera (= world)
    view = vol.raycast(INTR, np.eye(4), with_color=False, refine=True)
    d = view.depth.copy()
    d[d <= 0] = np.nan
    nrm = smooth_normal_map(d, INTR.K, tsdf.sdf_trunc_m * 2)
    tgt_pts = unproject(np.nan_to_num(d), INTR)
    ok = np.isfinite(d) & np.isfinite(nrm).all(-1)
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt_pts[ok]))
    target.normals = o3d.utility.Vector3dVector(nrm[ok].astype(np.float64))
    src = unproject(fr[1].depth, INTR).reshape(-1, 3)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src[src[:, 2] > 0]))
    reg = o3d.pipelines.registration
    res = reg.registration_icp(source, target, 0.05, np.eye(4), reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(1e-10, 1e-10, 100))
    t_diff, r_diff = _err(ours, res.transformation)
    assert res.fitness > 0.8
    assert t_diff < 1e-3 and r_diff < 0.05


def test_rgbd_odometry_recovers_known_motion(pair):
    _, poses, fr = pair
    tsdf = TSDFConfig(voxel_size_m=0.01)
    _, _, r1 = _track_pair(RGBDOdometryBackend, RGBDOdometryConfig(levels=(2, 1, 0)), fr, tsdf)
    assert not r1.failed, r1.reason
    t_err, r_err = _err(r1.pose, np.linalg.inv(poses[0]) @ poses[1])
    # the photometric term associates to the nearest pixel (Open3D kernel): ~1 mm at 320x240
    assert t_err < 2e-3 and r_err < 0.1


@pytest.mark.parametrize("name", ["icp", "rgbd_odometry"])
def test_black_frame_is_a_failure_and_tracking_continues(pair, name):
    _, poses, fr = pair
    B = get_backend(name)
    tsdf = TSDFConfig(voxel_size_m=0.01)
    extra = {"raycast_scale": 1.0, "refine_model": True} if name == "icp" else {"levels": (2, 1, 0)}
    b = B(B.Config(**extra), INTR, tsdf)
    vol = TSDFVolume(tsdf)
    r0 = b.track(fr[0], vol)
    vol.integrate(fr[0].depth, fr[0].rgb, INTR, r0.pose)
    black = Frame(fr[0].timestamp + 1 / 30, np.zeros_like(fr[0].depth), np.zeros_like(fr[0].rgb), None, 1)
    rb = b.track(black, vol)
    assert rb.failed and rb.pose is None and "valid depth" in rb.reason
    nxt = Frame(fr[1].timestamp + 1 / 30, fr[1].depth, fr[1].rgb, None, 2)
    r2 = b.track(nxt, vol)
    assert not r2.failed, r2.reason
    t_err, _ = _err(r2.pose, np.linalg.inv(poses[0]) @ poses[1])
    assert t_err < 3e-3


@pytest.mark.parametrize("name", ["icp", "rgbd_odometry"])
def test_no_overlap_is_a_failure_not_a_silent_pose(pair, name):
    """A frame of a different place (the camera turned to look at the other corner) must not
    be accepted: Open3D's odometry alone would still return a transformation."""
    from data_tools.geometry import look_at
    scene, poses, fr = pair
    away = look_at(np.array([-1.0, 1.0, 1.6]), np.array([1.5, -1.5, 0.8]))
    far = render_frames(scene, [away])[0]
    B = get_backend(name)
    tsdf = TSDFConfig(voxel_size_m=0.01)
    b = B(B.Config(relocalise=False), INTR, tsdf)
    vol = TSDFVolume(tsdf)
    r0 = b.track(fr[0], vol)
    vol.integrate(fr[0].depth, fr[0].rgb, INTR, r0.pose)
    f = Frame(fr[0].timestamp + 1 / 30, far.depth, far.rgb, None, 1)
    r = b.track(f, vol)
    assert r.failed and r.pose is None and r.reason


def test_implausible_motion_check():
    T = np.eye(4)
    T2 = np.eye(4)
    T2[0, 3] = 0.2
    assert implausible_motion(T, T2, 1 / 30, 1.5, 150) != ""
    assert implausible_motion(T, T2, 1.0, 1.5, 150) == ""
    assert implausible_motion(T, T, float("nan"), 1.5, 150) == ""


def test_registry_lists_and_rejects_backends():
    from data_tools.errors import ConfigError
    names = backend_names()
    assert {"icp", "rgbd_odometry"} <= set(names)
    assert get_backend("icp") is ICPBackend
    with pytest.raises(ConfigError, match="unknown registration backend"):
        get_backend("nope")


def test_track_result_record_is_json_ready():
    import json
    r = TrackResult(np.eye(4), np.float32(0.5), 0.001, False)
    row = r.record(1.5, 3)
    assert json.loads(json.dumps(row)) == row and set(row) >= {"timestamp", "fitness", "inlier_rmse", "failed"}


def test_backend_configs_share_the_failure_check_fields():
    """Both online backends take the failure-check/re-localisation options from one base class
    (same names on the command line), with their own defaults and the same validation."""
    from data_tools.errors import ConfigError
    from slam.registration import TrackingCheckConfig, config_from_dict
    import dataclasses
    shared = {f.name for f in dataclasses.fields(TrackingCheckConfig)}
    for cls in (ICPConfig, RGBDOdometryConfig):
        assert issubclass(cls, TrackingCheckConfig)
        assert shared <= {f.name for f in dataclasses.fields(cls)}
        with pytest.raises(ConfigError, match=f"{cls.__name__}.motion_model"):
            cls(motion_model="teleport").validate()
        with pytest.raises(ConfigError, match="max_speed_m_s"):
            config_from_dict(cls, {"max_speed_m_s": 0})
    assert (ICPConfig().min_fitness, RGBDOdometryConfig().min_fitness) == (0.2, 0.3)
    assert (ICPConfig().min_correspondences, RGBDOdometryConfig().min_correspondences) == (1000, 500)
    assert config_from_dict(ICPConfig, {"relocalise": False, "fitness_drop_ratio": 0.4}).fitness_drop_ratio == 0.4


def test_tracking_checks_shared_by_the_online_backends():
    """TrackingCheckConfig.check_solution / predict: each check on a hand-made solution."""
    from types import SimpleNamespace

    from slam.registration import TrackingCheckConfig
    c = TrackingCheckConfig(min_correspondences=100, min_fitness=0.3, max_rmse_m=0.01, max_speed_m_s=1.0)
    I = np.eye(4)
    good = SimpleNamespace(ok=True, message="", inliers=500, fitness=0.8, inlier_rmse=0.004)
    assert c.check_solution(good, I, I, 1 / 30) == ""
    assert "diverged" in c.check_solution(SimpleNamespace(**{**vars(good), "ok": False, "message": "diverged"}),
                                          I, I, 1 / 30)
    assert "too few correspondences" in c.check_solution(SimpleNamespace(**{**vars(good), "inliers": 50}), I, I, 0.03)
    assert "low fitness" in c.check_solution(SimpleNamespace(**{**vars(good), "fitness": 0.2}), I, I, 0.03)
    assert "residual" in c.check_solution(SimpleNamespace(**{**vars(good), "inlier_rmse": 0.02}), I, I, 0.03)
    moved = np.eye(4)
    moved[0, 3] = 0.1  # 10 cm in one frame period = 3 m/s
    assert c.check_solution(good, I, moved, 1 / 30) != ""
    assert "fitness dropped" in c.check_solution(good, I, I, 1 / 30, [0.9, 0.95, 1.0, 1.0], 0.9)
    assert c.check_solution(good, I, I, 1 / 30, [0.9, 0.95], 0.9) == ""  # fewer than 3: no drop check
    # constant velocity repeats the last motion unless the last frame failed
    assert np.allclose(c.predict(moved, I, after_failure=False)[0, 3], 0.2)
    assert np.allclose(c.predict(moved, I, after_failure=True), moved)
    assert np.allclose(TrackingCheckConfig(motion_model="static").predict(moved, I, False), moved)
    assert c.valid_depth_fraction(np.array([[0.0, 1.0], [np.nan, 9.0]]), 0.3, 5.0) == 0.25
