"""Pipelines that span packages (synth and slam meet only here, since neither may import the
other): the main demo and the worlds of the 3D neural memory. Commands in :mod:`app.commands` call these; a script can too."""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from data_tools.errors import ConfigError
from data_tools.results import atomic_write_json


def run_demo(out: str | Path = "demo_out", frames: int = 60, sensor: str = "kinect_v1", seed: int = 0,
             log: Callable[[str], None] = print) -> dict:
    """Room -> simulated ``sensor`` (physical pipeline) -> frame-to-model ICP + TSDF -> ATE
    (SE(3) alignment) against the ground truth. Writes ``out/summary.json`` and returns it.
    Re-running resumes every step."""
    from data_tools.sequence import SequenceReader
    from data_tools.trajectory import read_tum
    from slam.metrics import ate
    from slam.pipeline import make_config, run_slam
    from synth.sequence import SequenceConfig, generate_sensor_sequence

    if frames < 3:
        raise ConfigError(f"demo: --frames must be at least 3 (the ATE alignment needs 3 poses), got {frames}")
    from data_tools.outputs import check_output_dir
    check_output_dir(out, what="demo folder")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    ideal_dir, sim_dir, run_dir = out / "room_ideal", out / f"room_{sensor}", out / "slam_icp"

    log(f"[1/4] rendering the built-in room ({frames} frames, ideal depth) -> {ideal_dir}")
    log(f"[2/4] simulating a {sensor} on the same poses (physical pipeline) -> {sim_dir}")
    cfg = SequenceConfig(scene="room", frames=frames, seed=seed)
    generate_sensor_sequence(cfg, ideal_dir, sim_dir, sensor, resume=True)
    ideal = SequenceReader(ideal_dir)
    traj = ideal.trajectory

    log(f"[3/4] registering the simulated sequence with frame-to-model ICP + TSDF -> {run_dir}")
    res = run_slam(sim_dir, run_dir, make_config("icp"), resume=True)

    log("[4/4] evaluating the estimated trajectory against the ground truth")
    est = read_tum(run_dir / "trajectory.txt")
    m = ate(traj, est, align="se3")
    m.save(out / "ate")
    summary = {"frames": len(ideal), "sensor": sensor, "ate_rmse_m": m.stats["rmse"],
               "ate_pairs": m.stats.get("pairs", m.pairs), "frames_failed": res.stats["frames_failed"],
               "frames_relocalised": res.stats["frames_relocalised"], "seconds": round(time.time() - t0, 1),
               "ideal_sequence": str(ideal_dir), "simulated_sequence": str(sim_dir),
               "slam_run": str(run_dir), "mesh": str(run_dir / "mesh.ply")}
    atomic_write_json(out / "summary.json", summary)
    return summary


def simulate_planar_room(seed: int, frames: int, out: str | Path, progress: bool = True) -> None:
    """A world of the 3D neural memory (:data:`slam.neural.data3d.Simulator`): ``procedural_room`` ``seed``
    explored along a ``planar`` trajectory, measured by the full ``kinect_v1`` simulator, into ``out``
    (the ideal sequence in ``out/ideal``); an unfinished one resumes."""
    from synth.sequence import SequenceConfig, generate_simulated_sequence
    out = Path(out)
    cfg = SequenceConfig(scene="procedural_room", frames=frames, trajectory="planar", seed=seed)
    generate_simulated_sequence(cfg, out, "kinect_v1", resume=out.exists(), progress=progress)
