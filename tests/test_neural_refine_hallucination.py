"""Retraining the occupancy mask and the hallucination module on a frozen memory
(slam.neural.refine_hallucination): what it learns, what it leaves alone, exact resume, the folder command."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from slam.neural.config import HallucinationConfig

from slam.neural.refine_hallucination import refine_hallucination
from slam.neural.config import MemoryConfig, NeuralTrainConfig

SHIPPED = Path(__file__).resolve().parents[1] / "slam" / "neural" / "weights"
_CFG = NeuralTrainConfig(batch=4, steps=4, observe=2)


def _tiny_2d():
    from slam.neural.config import MemoryConfig
    from slam.neural.memory import NeuralMemory
    torch.manual_seed(0)
    return NeuralMemory(MemoryConfig(channels=3, features=4, view=15, memory=71, width=4, search=16))


def _walks():
    from slam.neural.data import Walks2D
    return Walks2D("front", 43)


def test_mask_learns_the_observed_cells_and_only_mask_and_module_change():
    """Stage 1 drives L_occ down and the mask b = (h + 1) / 2 apart on observed / never-observed cells (the untrained
    sigmoid mask cannot leave (0.27, 0.73)); the filled memory then keeps the observed cells (b ~ 1 there); no
    weight outside the occupancy LSTM and the module moves."""
    model = _tiny_2d()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    info = refine_hallucination(model, _walks(), _CFG, HallucinationConfig(occ_steps=75, steps=4), progress=False)
    occ = [h["occ"] for h in info["occ_log"]]
    assert occ[-1] < 0.5 * occ[0] and occ[-1] < 0.1, info["occ_log"]
    assert model.cfg.occupancy == "affine"
    changed = {k for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and all(k.startswith(("occ_lstm.", "hallucinator.")) for k in changed), changed
    assert any(k.startswith("occ_lstm.") for k in changed) and any(k.startswith("hallucinator.") for k in changed)
    assert all(p.requires_grad for p in model.parameters())
    from slam.neural.data2d import AGENTS, make_batch, view_mask
    _, obs, _, allo = make_batch(np.random.default_rng(5), 3, AGENTS["front"], 4, 43)
    vm = torch.from_numpy(view_mask(AGENTS["front"]).astype(np.float32))
    with torch.no_grad():
        out = model(torch.from_numpy(obs), vm, torch.from_numpy(allo))
        filled = model.hallucinate(out["psi"], out["occ"])
    seen = out["seen"].bool()
    # measured: 0.74 on observed cells, 0.011 on the others (a sigmoid mask cannot go below 0.27)
    assert out["occ"][seen].mean() > 0.6 and out["occ"][~seen].mean() < 0.05
    d = (filled - out["psi"]).abs().mean(1, keepdim=True)
    assert d[seen].mean() < 0.5 * d[~seen].mean(), (d[seen].mean(), d[~seen].mean())      # measured 0.030 vs 0.104
    assert info["log"][-1]["step"] == 79 and {"hallu", "corrupt", "disc"} <= set(info["log"][-1])


def test_resumes_exactly(tmp_path, monkeypatch):
    """Interrupted in stage 2 and re-run on its checkpoint, it ends with the weights of an uninterrupted run."""
    from slam.neural.data import Walks2D
    hc = HallucinationConfig(occ_steps=4, steps=6, checkpoint_every=3)
    whole = _tiny_2d()
    refine_hallucination(whole, _walks(), _CFG, hc, progress=False)
    ck = tmp_path / "ck.pt"
    calls = {"n": 0}
    real = Walks2D.sample

    def interrupted(self, *a):
        calls["n"] += 1
        if calls["n"] == 8:
            raise KeyboardInterrupt
        return real(self, *a)
    monkeypatch.setattr(Walks2D, "sample", interrupted)
    marks = []                          # on_checkpoint: what the command's progress marker is told
    with pytest.raises(KeyboardInterrupt):
        refine_hallucination(_tiny_2d(), _walks(), _CFG, hc, checkpoint=ck, progress=False, on_checkpoint=marks.append)
    assert marks == [3, 6]
    monkeypatch.setattr(Walks2D, "sample", real)
    again = _tiny_2d()
    info = refine_hallucination(again, _walks(), _CFG, hc, checkpoint=ck, progress=False, on_checkpoint=marks.append)
    assert info["resumed_from_step"] == 6 and marks[2:] == [6, 9, 10]
    for (k, a), b in zip(whole.state_dict().items(), again.state_dict().values()):
        assert torch.equal(a, b), k


@pytest.mark.parametrize("field,value", [("steps", 0), ("occ_steps", -1), ("checkpoint_every", 0), ("lr", 0.0),
                                         ("lr", float("nan"))])
def test_config_validation(field, value):
    from data_tools.errors import ConfigError
    with pytest.raises(ConfigError, match=field):
        HallucinationConfig(**{field: value}).validate()


@pytest.mark.parametrize("extra,msg", [(["--steps", "0"], "--steps: must be >= 1, got 0"),
                                       (["--topview-steps", "-1"], "must be >= 0, got -1")])
def test_cli_errors_are_one_line(tmp_path, capsys, extra, msg):
    from app.cli import main
    out = tmp_path / "retrained"
    assert main(["neural", "refine-hallucination", str(SHIPPED / "planar_3d"), "--out", str(out), "--no-progress",
                 *extra]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and msg in err, err
    assert not out.exists()


def test_cli_refuses_to_write_into_the_model_itself(capsys):
    from app.cli import main
    m = SHIPPED / "planar_3d"
    before = (m / "weights.pt").read_bytes()
    assert main(["neural", "refine-hallucination", str(m), "--out", str(m), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and ("the model folder itself" in err or "is the input MODEL" in err), err
    assert (m / "weights.pt").read_bytes() == before


def test_3d_folder_copy_with_a_new_topview(tmp_path, tiny_worlds):
    """On a tiny trained 3D model: the copy differs in the occupancy LSTM and the module only, says ``affine`` in its
    neural.json, loads, records the stage, and has a top-view decoder trained on the new mask."""
    from slam.neural.io import load_model
    from slam.neural.run import refine_hallucination_folder, train_to_folder
    from slam.neural.topview import TOPVIEW_FILE
    worlds, world, sim = tiny_worlds
    cfg = NeuralTrainConfig(mode="3d", model=MemoryConfig(features=4, width=4), batch=2, steps=4, observe=2,
                            iterations=3, pretrain_steps=1, teacher_steps=1, hallucination_from=2, log_every=1,
                            topview_steps=0, world=world, worlds_dir=str(worlds))
    train_to_folder(cfg, tmp_path / "m", progress=False, simulate=sim)
    assert not (tmp_path / "m" / TOPVIEW_FILE).exists()
    refine_hallucination_folder(tmp_path / "m", tmp_path / "m2", HallucinationConfig(occ_steps=3, steps=2, topview_steps=2),
                                progress=False, simulate=sim)
    a = torch.load(tmp_path / "m" / "weights.pt", weights_only=True)
    b = torch.load(tmp_path / "m2" / "weights.pt", weights_only=True)
    changed = {k for k in a if not torch.equal(a[k], b[k])}
    assert changed and all(k.startswith(("occ_lstm.", "hallucinator.")) for k in changed), changed
    meta = json.loads((tmp_path / "m2" / "neural.json").read_text())
    assert meta["train"]["model"]["occupancy"] == "affine"
    hinfo = meta["info"]["hallucination_retraining"]
    assert hinfo["config"]["steps"] == 2 and hinfo["topview"]["steps"] == 2
    assert (tmp_path / "m2" / TOPVIEW_FILE).is_file()
    assert not (tmp_path / "m2" / "hallucination_checkpoint.pt").exists()
    model, _, _ = load_model(tmp_path / "m2")
    assert model.cfg.occupancy == "affine"
