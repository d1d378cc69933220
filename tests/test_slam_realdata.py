"""Accuracy on real sequences from ../shared/data (skipped when the data is absent)."""
from __future__ import annotations

import pytest

from data_tools.camera import Camera, Intrinsics
from data_tools.sequence import SequenceReader
from slam.metrics import ate
from slam.pipeline import make_config, run_slam
from tests.conftest import shared_path

FR1 = Camera(Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3), 5000.0)
"""TUM fr1 depth camera (the shared folder has no camera.json)."""


@pytest.mark.shared_data
@pytest.mark.parametrize("backend", ["icp", "rgbd_odometry"])
def test_tum_fr1_xyz_ate_below_1_5_cm(tmp_path, backend):
    seq = shared_path("tum_fr1_xyz_10")
    res = run_slam(seq, tmp_path / "run", make_config(backend), camera=FR1, progress=False)
    assert res.stats["frames_failed"] == 0
    err = ate(SequenceReader(seq, camera=FR1).trajectory, res.trajectory)
    assert err.pairs == 10
    assert err.stats["rmse"] <= 0.015


@pytest.mark.slow
@pytest.mark.shared_data
def test_sevenscenes_chess_icp_ate_below_3_cm(tmp_path):
    """1000 frames of 7-Scenes chess (about 3-4 minutes on 2 cores) against its reference
    trajectory, which is KinectFusion's own output (not a metric ground truth), with the
    default configuration (the one that also meets the simulated and TUM targets): 2.86 cm.
    Needs the camera's sensor block (Kinect v1, written by the converter) for the depth-noise
    weights; unweighted, the refined model drifted sideways to 4.48 cm (see
    ``ICPConfig.disparity_noise_px``)."""
    from data_tools.sevenscenes import convert_7scenes
    seq = tmp_path / "chess"
    convert_7scenes(shared_path("sevenscenes_chess_1000"), seq, progress=False)
    cfg = make_config("icp")
    res = run_slam(seq, tmp_path / "run", cfg, progress=False)
    err = ate(SequenceReader(seq).trajectory, res.trajectory)
    assert res.stats["frames_failed"] <= 5
    assert err.stats["rmse"] <= 0.03


@pytest.mark.shared_data
def test_tum_fr1_xyz_colmap_baseline(tmp_path):
    """COLMAP on 4 keyframes (every 3rd frame), metric scale from depth, the other frames
    interpolated: an independent colour-only trajectory within 1.5 cm."""
    pytest.importorskip("pycolmap")
    seq = shared_path("tum_fr1_xyz_10")
    cfg = make_config("colmap", "default", {"backend_config.keyframe_step": 3, "backend_config.num_threads": 1})
    res = run_slam(seq, tmp_path / "run", cfg, camera=FR1, progress=False)
    reasons = [r["reason"] for r in res.stats["per_frame"]]
    assert reasons.count("keyframe") == 4 and reasons.count("interpolated") == 6
    err = ate(SequenceReader(seq, camera=FR1).trajectory, res.trajectory)
    assert err.pairs == 10 and err.stats["rmse"] <= 0.015
    assert (tmp_path / "run" / "mesh.ply").is_file()
