"""The 3D decoder refinement (slam.neural.refine): pool bookkeeping, training, exact resume, CLI errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from slam.neural.config import RefineConfig

from slam.neural.refine import _pairs, build_pool, refine_decoder
from tests.test_neural_topview import _Bank as _TopviewBank
from tests.test_neural_topview import _tiny_model

SHIPPED = Path(__file__).resolve().parents[1] / "slam" / "neural" / "weights"


class _Bank(_TopviewBank):
    """The top-view tests' stand-in WorldBank (one colour per sample, random cells) with the exact poses recall
    needs: the allocentric ones, as reals."""

    def __init__(self):
        super().__init__(7, 4, 4, 6)

    def sample(self, rng, batch, steps):
        imgs, cells, allo, _ = super().sample(rng, batch, steps)
        return np.ascontiguousarray(imgs), cells, allo, allo

    def exact(self, P):
        return np.asarray(P, np.float64)


def test_pairs_read_the_right_memory_pose_and_view():
    """Slots 0..T-1 recall view t from the self-registered memory s; slots T.. recall view observe + j from the
    filled memory N + s - checked on a pool whose every entry encodes its own index."""
    N, T, k, U = 5, 4, 2, 3
    pool = {"mem": torch.arange(2 * N, dtype=torch.float16).view(-1, 1, 1, 1).expand(2 * N, 1, U, U).clone(),
            "poses": torch.tensor([[[s, t, 0.0] for t in range(T)] for s in range(N)]),
            "images": torch.tensor([[[[[100.0 * s + t]]] for t in range(T)] for s in range(N)], dtype=torch.float16),
            "observe": k}
    mem, poses, y = _pairs(pool, np.random.default_rng(0), 400)
    m = mem[:, 0, 0, 0].numpy()
    s, t = poses[:, 0].numpy(), poses[:, 1].numpy()
    hallu = m >= N
    assert hallu.any() and (~hallu).any()
    np.testing.assert_array_equal(np.where(hallu, m - N, m), s)           # the memory of the pose's own sample
    assert (t[hallu] >= k).all()                                           # hallucination: only unseen views
    np.testing.assert_array_equal(y[:, 0, 0, 0].numpy(), 100 * s + t)     # the target is that view
    assert set(np.unique(t[~hallu])) == set(range(T))


def test_pool_shapes_and_memories():
    model = _tiny_model()
    pool = build_pool(model, _Bank(), 2, 3, 4, 2, seed=0, progress=False)
    assert pool["mem"].shape == (12, 4, 15, 15) and pool["mem"].dtype == torch.float16
    assert pool["poses"].shape == (6, 4, 3) and pool["images"].shape == (6, 4, 4, 4, 6)
    # the second half is the hole-filled partial memory, not a copy of the full one
    assert not torch.equal(pool["mem"][:6], pool["mem"][6:])


def test_refinement_lowers_the_loss_and_changes_only_the_decoder():
    model = _tiny_model()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    rc = RefineConfig(pool_batches=3, steps=60, batch=8, lr=4e-3, ssim_weight=0.5)
    info = refine_decoder(model, _Bank(), rc, 4, 2, progress=False)
    log = info["log"]
    assert log[-1]["l1"] < 0.5 * log[0]["l1"], log
    changed = {k for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and all(k.startswith("decoder.") for k in changed), changed
    assert all(p.requires_grad for p in model.parameters())
    assert info["config"]["ssim_weight"] == 0.5


def test_refinement_resumes_exactly(tmp_path, monkeypatch):
    import slam.neural.refine as refine
    rc = RefineConfig(pool_batches=2, steps=10, batch=4, lr=2e-3, checkpoint_every=5)
    whole = _tiny_model()
    refine_decoder(whole, _Bank(), rc, 4, 2, progress=False)
    ck = tmp_path / "ck.pt"
    calls = {"n": 0}
    real = refine._pairs

    def interrupted(*a):
        calls["n"] += 1
        if calls["n"] == 8:
            raise KeyboardInterrupt
        return real(*a)
    monkeypatch.setattr(refine, "_pairs", interrupted)
    marks = []                          # on_checkpoint: what the command's progress marker is told
    with pytest.raises(KeyboardInterrupt):
        refine_decoder(_tiny_model(), _Bank(), rc, 4, 2, checkpoint=ck, progress=False, on_checkpoint=marks.append)
    assert marks == [5]
    monkeypatch.setattr(refine, "_pairs", real)
    again = _tiny_model()
    info = refine_decoder(again, _Bank(), rc, 4, 2, checkpoint=ck, progress=False, on_checkpoint=marks.append)
    assert info["resumed_from_step"] == 5 and marks == [5, 5]      # the last step is not checkpointed
    for (k, a), b in zip(whole.state_dict().items(), again.state_dict().values()):
        assert torch.equal(a, b), k


@pytest.mark.parametrize("field,value", [("steps", -1), ("rooms", 0), ("batch", 0), ("ssim_weight", -1.0),
                                         ("ssim_weight", float("nan")), ("lr", 0.0)])
def test_config_validation(field, value):
    from data_tools.errors import ConfigError
    with pytest.raises(ConfigError, match=field):
        RefineConfig(**{field: value}).validate()


@pytest.mark.parametrize("extra,msg", [(["--steps", "0"], "steps must be >= 1"),
                                       (["--ssim-weight", "-1"], "ssim_weight")])
def test_cli_errors_are_one_line(tmp_path, capsys, extra, msg):
    from app.cli import main
    out = tmp_path / "refined"
    assert main(["neural", "refine-decoder", str(SHIPPED / "front_2d"), "--out", str(out), "--no-progress",
                 *extra]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and msg in err, err
    assert not out.exists()


def test_cli_refuses_to_write_into_the_model_itself(capsys):
    from app.cli import main
    m = SHIPPED / "planar_3d"
    before = (m / "weights.pt").read_bytes()
    assert main(["neural", "refine-decoder", str(m), "--out", str(m), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and ("the model folder itself" in err or "is the input MODEL" in err), err
    assert (m / "weights.pt").read_bytes() == before


def test_train_with_refinement_then_refine_a_copy(tmp_path, tiny_worlds):
    """``neural train`` with ``refine.steps`` runs the refinement after the memory phases and records it; ``neural
    refine-decoder`` on the result writes a copy whose weights differ from the model's in the decoder only, with
    the earlier refinement kept in its info (one tiny simulated room)."""
    import json

    from slam.neural.config import MemoryConfig, NeuralTrainConfig, RefineConfig
    from slam.neural.run import refine_folder, train_to_folder
    worlds, world, sim = tiny_worlds
    cfg = NeuralTrainConfig(mode="3d", model=MemoryConfig(features=4, width=4), batch=2, steps=4, observe=2,
                            iterations=4, pretrain_steps=2, teacher_steps=2, hallucination_from=3, log_every=1,
                            topview_steps=0, refine=RefineConfig(steps=3, rooms=1, pool_batches=1), world=world,
                            worlds_dir=str(worlds))
    train_to_folder(cfg, tmp_path / "m", progress=False, simulate=sim)
    info = json.loads((tmp_path / "m" / "neural.json").read_text())["info"]
    assert info["decoder_refinement"]["log"][-1]["step"] == 3
    assert not (tmp_path / "m" / "refine_checkpoint.pt").exists()
    (tmp_path / "worlds2").symlink_to(worlds)           # --worlds: used, not written into the model
    refine_folder(tmp_path / "m", tmp_path / "m2", RefineConfig(rooms=1, steps=2, pool_batches=1), progress=False,
                  simulate=sim, worlds=str(tmp_path / "worlds2"))
    a = torch.load(tmp_path / "m" / "weights.pt", weights_only=True)
    b = torch.load(tmp_path / "m2" / "weights.pt", weights_only=True)
    changed = {k for k in a if not torch.equal(a[k], b[k])}
    assert changed and all(k.startswith("decoder.") for k in changed), changed
    info2 = json.loads((tmp_path / "m2" / "neural.json").read_text())["info"]
    assert info2["decoder_refinement"]["config"]["steps"] == 2
    assert info2["earlier_decoder_refinement"]["config"]["steps"] == 3
    assert json.loads((tmp_path / "m2" / "neural.json").read_text())["train"]["worlds_dir"] == str(worlds)


def test_2d_refinement_on_walks_changes_only_the_decoder():
    """2D: the pool holds training walks of the model's agent (integer poses), the loss is on the view field; the
    decoder learns (L1 falls) and nothing else moves."""
    from slam.neural.config import MemoryConfig
    from slam.neural.memory import NeuralMemory
    from slam.neural.data import Walks2D
    torch.manual_seed(0)
    model = NeuralMemory(MemoryConfig(channels=3, features=4, view=15, memory=71, width=4, search=16))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    walks = Walks2D("front", 43)
    imgs, cells, allo, poses = walks.sample(np.random.default_rng(0), 2, 4)
    assert cells is None and imgs.shape == (2, 4, 3, 15, 15) and allo.dtype == np.int64
    info = refine_decoder(model, walks, RefineConfig(pool_batches=2, steps=100, batch=8, lr=4e-3), 4, 2,
                          progress=False)
    assert info["log"][-1]["l1"] < info["log"][0]["l1"], info["log"]
    changed = {k for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and all(k.startswith("decoder.") for k in changed), changed
