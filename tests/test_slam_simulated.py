"""Frame-to-model ICP on the simulated Kinect v1 room sequence of ``realgap demo`` (issue #5:
ATE <= 1 cm). Slow: rendering + the physical sensor simulation + ICP take about a minute."""
from __future__ import annotations

import pytest

from data_tools.sequence import SequenceReader
from slam.metrics import ate
from slam.pipeline import make_config, run_slam


@pytest.mark.slow
def test_icp_on_simulated_kinect_room_is_within_1_cm(tmp_path):
    """60 frames of the walkthrough (1.1 cm and 1.4 deg per frame at 30 Hz), seed 0: its first
    frames look at a round table on the floor, whose yaw is weakly constrained, so a model
    ray cast off by centimetres (Open3D's raw marcher) drifts by 36 cm there (7.3 cm ATE with
    the former defaults). With the verified, refined model: every frame tracked, ATE <= 1 cm."""
    from synth.sequence import SequenceConfig, generate_sensor_sequence
    ideal_dir, sim_dir = tmp_path / "ideal", tmp_path / "kinect"
    generate_sensor_sequence(SequenceConfig(scene="room", frames=60, seed=0), ideal_dir, sim_dir, "kinect_v1",
                             progress=False)
    ideal = SequenceReader(ideal_dir)
    res = run_slam(sim_dir, tmp_path / "run", make_config("icp"), progress=False)
    assert res.stats["frames_failed"] == 0
    err = ate(ideal.trajectory, res.trajectory, align="se3")
    assert err.pairs == 60
    assert err.stats["rmse"] <= 0.01
