"""Shared pytest set-up: the --runslow option, the location of ../shared/data, the neural memory's tiny 3D world
and model (simulated and made once per session)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("REALGAP_SHARED_DATA", REPO.parent / "shared" / "data"))


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="run tests marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow test: run with --runslow (make test-slow)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data, or skip: a user's fresh clone has no shared/ folder."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"reference data not found at {SHARED_DATA} (set REALGAP_SHARED_DATA)")
    return SHARED_DATA


def shared_path(*parts: str) -> Path:
    """A path inside the shared data folder, or skip the test with the reason."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"reference data {p} not found (shared/data is absent in a plain clone)")
    return p


@pytest.fixture(scope="session")
def tiny_worlds(tmp_path_factory):
    """(folder, world, simulate) of the neural memory's tests in 3D: one tiny kinect_v1 planar training room
    (``train_000``: 16 frames, 15 x 20 network images, seed 0) simulated once per session into ``folder``, its
    :class:`slam.neural.config.World3DConfig`, and the simulator that makes any other room a test asks for (the
    evaluation's test room lands in the same folder). Every training test reads the same room, so the suite
    simulates it once instead of once per test."""
    pytest.importorskip("torch")
    from app.pipelines import simulate_planar_room
    from slam.neural.config import World3DConfig
    from slam.neural.data3d import build_worlds
    root = tmp_path_factory.mktemp("neural_worlds")
    world = World3DConfig(image_h=15, image_w=20, rooms=1, test_rooms=1, frames=16, stride_min=1, stride_max=2)

    def simulate(seed, frames, out):
        simulate_planar_room(seed, frames, out, progress=False)
    build_worlds(root, world, "train", simulate=simulate)
    return root, world, simulate


@pytest.fixture(scope="session")
def tiny_3d_model(tmp_path_factory, tiny_worlds):
    """A tiny untrained 3D neural-memory model folder (features 4, width 4, 15 x 20 images; seeded weights and an
    untrained top-view decoder) whose test rooms are 40-frame rooms of :func:`tiny_worlds`' folder: the plumbing of
    the backend, the render and the evaluation is tested on it, not the accuracy."""
    import torch

    from slam.neural.config import MemoryConfig, NeuralTrainConfig
    from slam.neural.io import save_model
    from slam.neural.memory import NeuralMemory
    from slam.neural.topview import TopViewDecoder, save_topview
    from slam.neural.config import World3DConfig
    root = tiny_worlds[0]
    world = World3DConfig(image_h=15, image_w=20, rooms=1, test_rooms=1, frames=40, stride_min=2, stride_max=3)
    cfg = NeuralTrainConfig(mode="3d", model=MemoryConfig(features=4, width=4), world=world,
                            worlds_dir=str(root)).resolved()
    folder = tmp_path_factory.mktemp("tiny_3d") / "model"
    torch.manual_seed(0)
    save_model(folder, NeuralMemory(cfg.model), cfg)
    save_topview(folder, TopViewDecoder(4, 4))
    return folder
