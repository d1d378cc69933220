"""Pipelines that span packages (synth and slam meet only here, since neither may import the
other): the worlds of the 3D neural memory (the demo lives in :mod:`app.demo`). Commands in :mod:`app.commands` call these; a script can too."""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from data_tools.errors import ConfigError
from data_tools.results import atomic_write_json


def simulate_planar_room(seed: int, frames: int, out: str | Path, progress: bool = True) -> None:
    """A world of the 3D neural memory (:data:`slam.neural.data3d.Simulator`): ``procedural_room`` ``seed``
    explored along a ``planar`` trajectory, measured by the full ``kinect_v1`` simulator, into ``out``
    (the ideal sequence in ``out/ideal``); an unfinished one resumes."""
    from synth.sequence import SequenceConfig, generate_simulated_sequence
    out = Path(out)
    cfg = SequenceConfig(scene="procedural_room", frames=frames, trajectory="planar", seed=seed)
    generate_simulated_sequence(cfg, out, "kinect_v1", resume=out.exists(), progress=progress)
