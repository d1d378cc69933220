"""The 3D memory's top-view decoder (slam.neural.topview): targets, training, save -> load, CLI errors."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from slam.neural.topview import (TopViewDecoder, load_topview, project_sum, save_topview, topview_targets,
                                 train_topview)


def test_project_sum_hand_computed():
    vals = torch.tensor([[[1.0, 2.0, 4.0, 8.0]]])          # (B=1, c=1, 4 pixels)
    cells = torch.tensor([[0, 0, 3, -1]])                   # two pixels in cell 0, one in cell 3, one dropped
    s, n = project_sum(vals, cells, 2)
    np.testing.assert_array_equal(s[0, 0].numpy(), [[3.0, 0.0], [0.0, 4.0]])
    np.testing.assert_array_equal(n[0, 0].numpy(), [[2.0, 0.0], [0.0, 1.0]])


def _one_pixel(q, r, ego_cell, colour, heading_cell=None):
    """imgs (1, 1, 4, 1, 1) with one pixel of ``colour`` in ego cell ``ego_cell`` of the unturned grid (and
    ``heading_cell[k]`` of the turned ones)."""
    imgs = torch.tensor(list(colour) + [0.0]).view(1, 1, 4, 1, 1)
    cells = torch.full((1, 1, r, 1), -1, dtype=torch.long)
    for k in range(r):
        cells[0, 0, k, 0] = ego_cell if heading_cell is None else heading_cell[k]
    return imgs, cells


def test_targets_paste_each_view_at_its_allocentric_pose():
    """The view's centre cell lands on memory cell (row + U // 2, col + U // 2), as the memory's own
    registration places it; a point 2 cells ahead lands 2 rows up; the heading picks its turned grid."""
    q, r, U = 5, 4, 11
    c = q // 2
    imgs, cells = _one_pixel(q, r, c * q + c, (0.5, -0.5, 0.25))
    tgt, seen = topview_targets(imgs, cells, torch.tensor([[[2, -1, 0]]]), r, q, U)
    assert seen.sum() == 1 and seen[0, 0, U // 2 + 2, U // 2 - 1]
    np.testing.assert_allclose(tgt[0, :, U // 2 + 2, U // 2 - 1].numpy(), [0.5, -0.5, 0.25])
    ahead = (c - 2) * q + c
    imgs, cells = _one_pixel(q, r, None, (1.0, 1.0, 1.0), heading_cell=[ahead, c * q + c - 2, -1, -1])
    _, seen0 = topview_targets(imgs, cells, torch.tensor([[[0, 0, 0]]]), r, q, U)
    assert seen0[0, 0, U // 2 - 2, U // 2]
    _, seen1 = topview_targets(imgs, cells, torch.tensor([[[0, 0, 1]]]), r, q, U)   # heading 1: turned grid 1
    assert seen1[0, 0, U // 2, U // 2 - 2] and seen1.sum() == 1


def test_targets_average_views():
    q, r, U = 5, 4, 9
    c = q // 2
    a, ca = _one_pixel(q, r, c * q + c, (1.0, 0.0, 0.0))
    b, cb = _one_pixel(q, r, c * q + c, (0.0, 1.0, 0.0))
    imgs, cells = torch.cat([a, b], 1), torch.cat([ca, cb], 1)
    tgt, seen = topview_targets(imgs, cells, torch.tensor([[[0, 0, 0], [0, 0, 2]]]), r, q, U)
    np.testing.assert_allclose(tgt[0, :, U // 2, U // 2].numpy(), [0.5, 0.5, 0.0])


class _Bank:
    """A stand-in for slam.neural.data3d.WorldBank: rooms of one colour (plus a little noise), views of random
    cells (the memory is teacher-forced, so what it could not localise does not matter)."""

    def __init__(self, q, r, H, W):
        self.q, self.r, self.H, self.W = q, r, H, W
        self.wedge = np.ones((q, q), bool)

    def sample(self, rng, batch, steps):
        col = (np.array([0.6, -0.4, 0.2]).reshape(1, 1, 3, 1, 1)
               + rng.normal(0, 0.05, (batch, 1, 3, 1, 1))).astype(np.float32)
        imgs = np.concatenate([np.broadcast_to(col, (batch, steps, 3, self.H, self.W)),
                               np.zeros((batch, steps, 1, self.H, self.W), np.float32)], 2)
        cells = rng.integers(0, self.q * self.q, (batch, steps, self.r, self.H * self.W)).astype(np.int64)
        allo = np.stack([rng.integers(-1, 2, (batch, steps)), rng.integers(-1, 2, (batch, steps)),
                         rng.integers(0, self.r, (batch, steps))], -1).astype(np.int64)
        allo[:, 0] = 0
        return imgs, cells, allo, None


def _tiny_model():
    from slam.neural.config import MemoryConfig
    from slam.neural.memory import NeuralMemory
    torch.manual_seed(0)
    return NeuralMemory(MemoryConfig(channels=4, features=4, view=7, memory=15, width=4, rotations=4, search=2,
                                     input="image", image_size=(4, 6)))


def test_training_lowers_the_loss_and_leaves_the_memory_alone():
    model = _tiny_model()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    dec, hist, _ = train_topview(model, _Bank(7, 4, 4, 6), 100, batch=4, seq_steps=3, lr=2e-3, progress=False)
    assert hist[-1]["topview_l1"] < 0.5 * hist[0]["topview_l1"], hist
    for k, v in model.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert all(p.requires_grad for p in model.parameters())


def test_save_load_identical_and_errors(tmp_path):
    from data_tools.errors import FormatError
    torch.manual_seed(3)
    dec = TopViewDecoder(4, 8)
    save_topview(tmp_path, dec, {"steps": 1})
    back = load_topview(tmp_path, 4)
    psi, occ = torch.randn(1, 4, 9, 9), torch.rand(1, 1, 9, 9)
    with torch.no_grad():
        assert torch.equal(dec.eval()(psi, occ), back(psi, occ))
    assert load_topview(tmp_path / "none", 4) is None
    with pytest.raises(FormatError, match="for 4 memory features, the model has 8"):
        load_topview(tmp_path, 8)
    (tmp_path / "topview.pt").write_bytes(b"not torch")
    with pytest.raises(FormatError, match="unreadable top-view decoder"):
        load_topview(tmp_path, 4)


def test_train_topview_cli_rejects_a_2d_model(tmp_path, capsys):
    from pathlib import Path

    from app.cli import main
    shipped = Path(__file__).resolve().parents[1] / "slam" / "neural" / "weights" / "front_2d"
    assert main(["neural", "train-topview", str(shipped), "--steps", "1", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "is a 2d model" in err, err
    assert not (shipped / "topview.pt").exists()


@pytest.mark.slow  # ~30 s; the 3D ablation views are fingerprinted in the default run
def test_evaluate_3d_end_to_end_on_a_tiny_world(tmp_path, tiny_worlds, tiny_3d_model):
    """evaluate_3d on one simulated 40-frame test room with a tiny untrained model (+ its top-view decoder):
    localisation (neural and icp), images, ablations, baseline, top view and speed all come out finite and
    JSON-serialisable. The plumbing, not the accuracy (the shipped model's numbers are in the README)."""
    import json

    from slam.neural.evaluate3d import evaluate_3d
    from slam.neural.io import load_model
    model, cfg, _ = load_model(tiny_3d_model)
    ex: dict = {}
    res = evaluate_3d(model, cfg, tmp_path / "ev", tiny_3d_model, samples=2, progress=False, simulate=tiny_worlds[2],
                      examples=ex)
    json.dumps(res)
    from slam.neural.figures import write_figures
    assert sorted(write_figures(tmp_path / "ev", {"mode": "3d", **res}, ex)) == ["ate.png", "examples.png",
                                                                                "images.png"]
    assert len(ex["samples"]) == 2 and (tmp_path / "ev" / "ate.png").stat().st_size > 1000
    assert list(res["sequences"]) == ["test_000"]
    row = res["sequences"]["test_000"]
    assert row["neural"]["frames"] == row["icp"]["frames"] == row["neural_no_motion_prior"]["frames"] == 40
    assert "neural_no_motion_prior" in res["localisation"]
    assert row["icp"]["ate_m"]["rmse"] < 0.1                   # icp tracks a simulated room
    # the heading error beside a trajectory that never turns: for a camera of fixed pitch and roll, the rotation
    # angle between frame t and frame 0 is the yaw turned
    from data_tools.sequence import SequenceReader
    from slam.neural.geometry3d import planar_relative
    root = tiny_worlds[0]
    P = SequenceReader(root / "test_000").poses
    yaw = np.degrees([abs(planar_relative(P[0], T, 0.15)[2]) for T in P])
    assert yaw.max() > 5                                       # the planar path turns
    assert row["heading_fixed_baseline_deg"]["mean"] == pytest.approx(yaw.mean(), abs=1e-6)
    assert row["icp"]["ape_rotation_deg"]["mean"] < 2 < row["heading_fixed_baseline_deg"]["mean"]
    assert res["localisation"]["heading_fixed_baseline_deg_mean"] == row["heading_fixed_baseline_deg"]["mean"]
    assert res["localisation"]["neural"]["ape_rotation_deg_mean"] == row["neural"]["ape_rotation_deg"]["mean"]
    for key in ("anamnesis", "anamnesis_backend_registration", "hallucination", "baseline_tsdf_inpainting",
                "ablation_no_localisation_anamnesis", "ablation_no_culling_anamnesis",
                "ablation_no_culling_hallucination"):
        assert 0.0 <= res[key]["l1"] <= 1.0 and -1.0 <= res[key]["ssim_thesis"] <= 1.0, key
    top = res["topview"]
    assert 0.0 < top["l1"] <= 1.0 and 0.0 < top["l1_true_poses"] <= 1.0 and 0.0 < top["baseline_mean_colour_l1"] < 1
    assert res["speed_register5_recall5_hallucinate5_s"]["median"] > 0


def test_every_train_preset_exists_in_both_modes():
    """``neural train --preset`` offers cpu, cpu-long and gpu; each names a recipe in 2D and in 3D (cpu-long: the
    shipped weights' recipe of each mode)."""
    import argparse

    from app.commands.neural import register
    from slam.neural.config import TRAIN_PRESETS, TRAIN_PRESETS_3D
    p = argparse.ArgumentParser()
    register(p)
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction)).choices["train"]
    choices = set(next(a for a in sub._actions if a.dest == "preset").choices)
    assert choices == set(TRAIN_PRESETS) == set(TRAIN_PRESETS_3D) == {"cpu", "cpu-long", "gpu"}
    big, small = TRAIN_PRESETS["cpu-long"], TRAIN_PRESETS["cpu"]
    assert (big.model.features, big.model.width) == (16, 32) and big.iterations == small.iterations
    c = TRAIN_PRESETS_3D["cpu"]            # the <= 30 min schedule (see its docstring for the step costs)
    assert c.pretrain_steps < c.hallucination_from < c.iterations and c.topview_steps > 0


def test_2d_cpu_long_preset_is_the_shipped_front_2d_recipe():
    """The shipped front_2d weights were trained by the 2D ``cpu-long`` preset (its decoder refinement included):
    the configuration its neural.json records (version 1, converted on reading) is the preset's with the network's
    sizes the data gives, and the refinement recorded is the preset's."""
    import json
    from dataclasses import asdict, replace
    from pathlib import Path

    from slam.neural.config import TRAIN_PRESETS
    from slam.neural.io import read_config
    folder = Path(__file__).resolve().parents[1] / "slam" / "neural" / "weights" / "front_2d"
    cfg, info = read_config(folder)
    preset = TRAIN_PRESETS["cpu-long"]
    assert cfg == preset.resolved()
    ref = info["decoder_refinement"]["config"]
    assert asdict(replace(preset.refine, seed=preset.seed)) == ref
    assert json.loads((folder / "neural.json").read_text())["version"] == 1       # the shipped file is untouched


def test_3d_cpu_long_preset_is_the_shipped_planar_3d_recipe():
    """The shipped planar_3d weights record the configuration they were trained with; the ``cpu-long`` 3D preset
    must be that configuration: its memory phases (the occupancy mask trained afterwards by ``neural
    refine-hallucination``: ``affine``), and the decoder refinement, run afterwards by ``neural refine-decoder`` and
    recorded in ``info.decoder_refinement``, is the preset's ``refine``."""
    from dataclasses import replace
    from pathlib import Path

    from slam.neural.config import TRAIN_PRESETS_3D
    from slam.neural.io import read_config
    cfg, info = read_config(Path(__file__).resolve().parents[1] / "slam" / "neural" / "weights" / "planar_3d")
    preset = TRAIN_PRESETS_3D["cpu-long"]
    ref = info["decoder_refinement"]["config"]
    assert cfg.refine.steps == 0 and (preset.refine.steps, preset.refine.rooms, preset.refine.pool_batches) == \
        (ref["steps"], ref["rooms"], ref["pool_batches"])
    assert cfg == replace(preset, refine=cfg.refine, model=replace(preset.resolved().model, occupancy="affine"))
    assert cfg.world.view == 49 and cfg.world.max_range_m == 3.6
