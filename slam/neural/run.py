"""The runs behind ``realgap neural train|eval``: a model folder, resumable training, evaluation JSON."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from data_tools.errors import ConfigError

__all__ = ["train_to_folder", "train_topview_into", "add_topview", "refine_into", "refine_folder",
           "refine_hallucination_folder", "evaluate_folder"]

REFINE_CHECKPOINT = "refine_checkpoint.pt"
HALLU_CHECKPOINT = "hallucination_checkpoint.pt"


def train_to_folder(cfg, out: str | os.PathLike, overwrite: bool = False, progress: bool = True,
                    log: Callable[[str], None] | None = None, simulate=None):
    """Train into ``out`` (MODEL/weights.pt, neural.json; checkpoint.pt while training)."""
    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    from slam.neural.train import save_model, train_memory
    folder = check_output_dir(out, finished="neural.json", overwrite=overwrite)
    if overwrite:
        for name in ("neural.json", "weights.pt", "checkpoint.pt"):
            (folder / name).unlink(missing_ok=True)
    folder.mkdir(parents=True, exist_ok=True)
    total = cfg.iterations + cfg.refine_steps
    unit = "steps (memory training, then decoder refinement)" if cfg.refine_steps else "steps"

    def mark(done: int) -> None:
        mark_incomplete(folder, "realgap neural train", done, total, unit=unit)
    mark(0)
    model, _disc, tlog = train_memory(cfg, folder / "checkpoint.pt", progress=progress, log=log, simulate=simulate,
                                      on_checkpoint=mark)
    info = {}
    if cfg.refine_steps > 0:
        # the memory's final checkpoint is on disk: an interruption here restarts only this phase
        from slam.neural.refine import RefineConfig
        rcfg = RefineConfig(rooms=cfg.refine_rooms, steps=cfg.refine_steps, pool_batches=cfg.refine_pool_batches,
                            seed=cfg.seed)
        info["decoder_refinement"] = refine_into(folder, model, cfg, rcfg, progress=progress, log=log,
                                                 simulate=simulate, command=f"realgap neural train --mode {cfg.mode}",
                                                 on_checkpoint=lambda s: mark(cfg.iterations + s))
    if cfg.mode == "3d" and cfg.topview_steps > 0:
        # the memory's final checkpoint is on disk: an interruption here restarts only this phase
        train_topview_into(folder, model, cfg, cfg.topview_steps, progress=progress, log=log, simulate=simulate)
    save_model(folder, model, cfg, {"train_log": tlog.steps[-20:], "train_seconds": round(tlog.seconds, 1),
                                    "resumed_from_step": tlog.resumed_from, **info})
    (folder / "checkpoint.pt").unlink(missing_ok=True)
    (folder / REFINE_CHECKPOINT).unlink(missing_ok=True)
    clear_incomplete(folder)
    return model, tlog, folder


def train_topview_into(folder, model, cfg, steps: int, progress: bool = True, log=None, simulate=None,
                       command: str = "") -> dict:
    """Train the top-view decoder of a 3D ``model`` (frozen) on ``cfg``'s training rooms for ``steps`` steps and
    write MODEL/topview.pt (:mod:`slam.neural.topview`); returns its info (steps, seed, seconds, losses)."""
    from slam.neural.topview import save_topview, train_topview
    from slam.neural.train import worlds_3d
    bank = worlds_3d(cfg, simulate, progress, log)
    dec, hist, sec = train_topview(model, bank, steps, batch=cfg.batch, seq_steps=cfg.steps, lr=cfg.lr, seed=cfg.seed,
                                   progress=progress, log=log)
    info = {"steps": int(steps), "seed": int(cfg.seed), "seconds": round(sec, 1), "log": hist[-10:],
            "command": command or "realgap neural train --mode 3d"}
    save_topview(folder, dec, info)
    return info


def add_topview(model_dir, steps: int, overwrite: bool = False, worlds: str | None = None, progress: bool = True,
                log=None, simulate=None) -> dict:
    """``neural train-topview``: give an existing 3D model folder a trained top-view decoder (the memory's
    weights are not touched)."""
    import dataclasses

    from data_tools.errors import RealgapError
    from slam.neural.topview import TOPVIEW_FILE
    from slam.neural.train import load_model
    if steps < 1:
        raise ConfigError(f"--steps must be >= 1, got {steps}")
    model, cfg, _ = load_model(model_dir)
    if cfg.mode != "3d":
        raise ConfigError(f"{model_dir} is a {cfg.mode} model; the top-view decoder is for 3d models (a 2d memory "
                          "is a top view already)")
    if (Path(model_dir) / TOPVIEW_FILE).is_file() and not overwrite:
        raise RealgapError(f"{Path(model_dir) / TOPVIEW_FILE}: already holds a top-view decoder; pass --overwrite to "
                           "train a new one")
    if worlds:
        cfg = dataclasses.replace(cfg, worlds_dir=str(worlds))
    return train_topview_into(model_dir, model, cfg, steps, progress=progress, log=log, simulate=simulate,
                              command=f"realgap neural train-topview MODEL --steps {steps}")


def refine_into(folder, model, cfg, rcfg, progress: bool = True, log=None, simulate=None, command: str = "",
                on_checkpoint=None) -> dict:
    """Refine the recall decoder of ``model`` (:mod:`slam.neural.refine`) - 3D: on ``rcfg.rooms`` training rooms of
    ``cfg``'s world (simulated where missing); 2D: on training walks -, checkpointing to FOLDER/refine_checkpoint.pt
    (``on_checkpoint(step)`` after each); returns its info."""
    import dataclasses

    from slam.neural.refine import Walks2D, refine_decoder
    from slam.neural.train import worlds_3d
    if cfg.mode == "3d":
        wcfg = dataclasses.replace(cfg, world=dataclasses.replace(cfg.world, rooms=int(rcfg.rooms)))
        bank = worlds_3d(wcfg, simulate, progress, log)
    else:
        bank = Walks2D(cfg.agent, cfg.image)
    info = refine_decoder(model, bank, rcfg, cfg.steps, cfg.observe, Path(folder) / REFINE_CHECKPOINT,
                          progress=progress, log=log, on_checkpoint=on_checkpoint)
    info["command"] = command
    return info


def _model_copy_folder(model_dir, out, overwrite: bool, command: str, total: int):
    """(model, cfg, info, folder, mark) for the commands that write a retrained copy of the model ``model_dir`` into
    ``out``: the model loaded, ``out`` checked (not the model itself; a finished model there only with
    ``overwrite``) and marked incomplete until the copy is saved; ``mark(done)`` updates that marker to ``done`` of
    ``total`` steps."""
    from data_tools.outputs import check_output_dir, mark_incomplete
    from slam.neural.topview import TOPVIEW_FILE
    from slam.neural.train import load_model
    model, cfg, info = load_model(model_dir)
    if Path(out).resolve() == Path(model_dir).resolve():
        raise ConfigError(f"--out {out} is the model folder itself: the new model goes into a new folder")
    folder = check_output_dir(out, finished="neural.json", overwrite=overwrite)
    if overwrite:
        for name in ("neural.json", "weights.pt", TOPVIEW_FILE):
            (folder / name).unlink(missing_ok=True)
    folder.mkdir(parents=True, exist_ok=True)

    def mark(done: int) -> None:
        mark_incomplete(folder, command, done, total, unit="steps")
    mark(0)
    return model, cfg, info, folder, mark


def refine_folder(model_dir, out, rcfg, worlds: str | None = None, overwrite: bool = False, progress: bool = True,
                  log=None, simulate=None) -> dict:
    """``neural refine-decoder``: a copy of the model folder ``model_dir`` in ``out`` whose recall decoder is
    refined (:mod:`slam.neural.refine`; every other weight and the top-view decoder copied unchanged). Resumable:
    a re-run with the same ``out`` continues from its checkpoint. Returns the refinement's info."""
    import dataclasses
    import shutil

    from data_tools.outputs import clear_incomplete
    from slam.neural.topview import TOPVIEW_FILE
    from slam.neural.train import save_model
    rcfg.validate()
    model, cfg, info, folder, mark = _model_copy_folder(model_dir, out, overwrite, "realgap neural refine-decoder",
                                                        rcfg.steps)
    run_cfg = dataclasses.replace(cfg, worlds_dir=str(worlds)) if worlds else cfg    # saved: the model's own config
    rooms = f" --rooms {rcfg.rooms}" if cfg.mode == "3d" else ""
    rinfo = refine_into(folder, model, run_cfg, rcfg, progress=progress, log=log, simulate=simulate,
                        command=f"realgap neural refine-decoder MODEL --out OUT{rooms} --steps {rcfg.steps} "
                                f"--pool-batches {rcfg.pool_batches} --ssim-weight {rcfg.ssim_weight:g}",
                        on_checkpoint=mark)
    if (Path(model_dir) / TOPVIEW_FILE).is_file():
        shutil.copyfile(Path(model_dir) / TOPVIEW_FILE, folder / TOPVIEW_FILE)
    new_info = {**info, "decoder_refinement": rinfo}
    if info.get("decoder_refinement"):
        new_info["earlier_decoder_refinement"] = info["decoder_refinement"]
    save_model(folder, model, cfg, new_info)
    (folder / REFINE_CHECKPOINT).unlink(missing_ok=True)
    clear_incomplete(folder)
    return rinfo


def refine_hallucination_folder(model_dir, out, hcfg, topview_steps: int = 300, worlds: str | None = None,
                                overwrite: bool = False, progress: bool = True, log=None, simulate=None) -> dict:
    """``neural refine-hallucination``: a copy of the model folder ``model_dir`` in ``out`` with a trained
    occupancy mask and a retrained hallucination module (:mod:`slam.neural.refine_hallucination`; every other
    weight copied unchanged). The top-view decoder of a 3D model reads the occupancy: it is retrained for
    ``topview_steps`` steps on the same rooms (0 = none is written). Resumable: a re-run with the same ``out``
    continues from its checkpoint. Returns the stage's info."""
    import dataclasses

    from data_tools.outputs import clear_incomplete
    from slam.neural.refine import Walks2D
    from slam.neural.refine_hallucination import refine_hallucination
    from slam.neural.train import save_model, worlds_3d
    hcfg.validate()
    if topview_steps < 0:
        raise ConfigError(f"--topview-steps must be >= 0, got {topview_steps}")
    model, cfg, info, folder, mark = _model_copy_folder(model_dir, out, overwrite,
                                                        "realgap neural refine-hallucination",
                                                        hcfg.occ_steps + hcfg.steps)
    run_cfg = dataclasses.replace(cfg, worlds_dir=str(worlds)) if worlds else cfg    # saved: the model's own config
    bank = worlds_3d(run_cfg, simulate, progress, log) if cfg.mode == "3d" else Walks2D(cfg.agent, cfg.image)
    hinfo = refine_hallucination(model, bank, cfg, hcfg, folder / HALLU_CHECKPOINT, progress=progress, log=log,
                                 on_checkpoint=mark)
    hinfo["command"] = (f"realgap neural refine-hallucination MODEL --out OUT --occ-steps {hcfg.occ_steps} "
                        f"--steps {hcfg.steps} --topview-steps {topview_steps} --seed {hcfg.seed}")
    if cfg.mode == "3d" and topview_steps > 0:
        hinfo["topview"] = train_topview_into(folder, model, run_cfg, topview_steps, progress=progress, log=log,
                                              simulate=simulate, command=hinfo["command"])
    new_info = {**info, "hallucination_retraining": hinfo}
    save_model(folder, model, cfg, new_info)
    (folder / HALLU_CHECKPOINT).unlink(missing_ok=True)
    clear_incomplete(folder)
    return hinfo


def evaluate_folder(model_dir, out: str | os.PathLike | None, sequences: int | None = None, overwrite: bool = False,
                    progress: bool = True, mode: str | None = None, extra_sequences=(), log=None,
                    simulate=None) -> dict:
    """``neural eval``: the model's 2d or 3d evaluation (``sequences``: 2d test walks, default 64; 3d image
    samples, default 24), with ``mode`` (the model's) in the result; written to ``out``/neural_eval.json with
    the figures of :mod:`slam.neural.figures` beside it (their names in the result's ``figures``)."""
    from data_tools.outputs import check_output_dir
    from slam.neural.evaluate import evaluate_2d
    from slam.neural.train import load_model
    if sequences is not None and sequences < 1:
        raise ConfigError(f"--sequences must be >= 1, got {sequences}")
    folder = check_output_dir(out, finished="neural_eval.json", overwrite=overwrite) if out else None
    model, cfg, _info = load_model(model_dir)
    if mode is not None and mode != cfg.mode:
        raise ConfigError(f"--mode {mode}: {model_dir} is a {cfg.mode} model")
    if sequences is None:
        sequences = 24 if cfg.mode == "3d" else 64
    examples: dict = {}
    if cfg.mode == "3d":
        if folder is None:
            raise ConfigError("--mode 3d evaluation runs SLAM on the test rooms: give --out DIR for its runs")
        from slam.neural.evaluate3d import evaluate_3d
        res = evaluate_3d(model, cfg, folder, model_dir, extra_sequences, samples=sequences, progress=progress,
                          log=log, simulate=simulate, examples=examples)
    else:
        if extra_sequences:
            raise ConfigError("--planar sequences are for 3d models")
        res = evaluate_2d(model, cfg, sequences, progress=progress, examples=examples)
    res = {"mode": cfg.mode, **res}
    if folder is not None:
        from data_tools.results import make_header, write_result
        from slam.neural.figures import write_figures
        res["figures"] = write_figures(folder, res, examples)
        header = make_header("neural.eval", inputs={"model": Path(model_dir) / "neural.json"},
                             parameters={"mode": cfg.mode, "sequences": sequences}, metrics=eval_metrics(res))
        write_result(Path(folder) / "neural_eval.json", header, {"model": str(Path(model_dir).resolve()), **res})
    return res


def eval_metrics(res: dict) -> dict:
    """The flat numbers of a ``neural eval`` result that its header carries (what ``realgap show`` tabulates
    beside other results): 3D the ATE RMSE of the neural backend and of icp on the test rooms (metres), both modes
    recall (anamnesis) and hallucination L1 / thesis SSIM, 2D the APE median / mean (pixels)."""
    m = {}
    if res.get("mode") == "3d":
        loc = res["localisation"]
        m.update(ate_rmse_m_neural=loc["neural"]["ate_rmse_m_mean"], ate_rmse_m_icp=loc["icp"]["ate_rmse_m_mean"])
    else:
        m.update(ape_px_median=res["ape_px"]["median"], ape_px_mean=res["ape_px"]["mean"],
                 localised_within_1px=res["localised_within_1px"])
    for k in ("anamnesis", "hallucination"):
        m.update({f"{k}_l1": res[k]["l1"], f"{k}_ssim": res[k]["ssim_thesis"]})
    return m


def register_sequence(model, images, cells, wedge, memory: int, motion_prior=None, score: str = "sum") -> dict:
    """Run a 3D model over one sequence of memory steps: images (T, 4, H, W), cells (T, r, H * W), the view
    wedge (q, q) bool, a memory of side ``memory`` cells, ``motion_prior`` (sigma cells, sigma heading steps) or
    None, ``score`` sum | overlap (:meth:`slam.neural.model.NeuralMemory.forward`). Returns numpy arrays: fields
    (T, r, P, P) local pose fields, centres (T, 2) allocentric middle of each field, psi (n, U, U), occ (U, U) and
    seen (U, U) bool (the cells a registered view field covered)."""
    import numpy as np
    import torch
    vm = torch.from_numpy(np.asarray(wedge, np.float32))
    with torch.no_grad():
        out = model(torch.from_numpy(np.asarray(images, np.float32))[None], vm, None,
                    cells=torch.from_numpy(np.asarray(cells, np.int64))[None], memory=int(memory),
                    motion_prior=motion_prior, score=score)
    return {"fields": out["fields"][0].numpy(), "centres": out["centres"][0].numpy(),
            "psi": out["psi"][0].numpy(), "occ": out["occ"][0, 0].numpy(), "seen": out["seen"][0, 0].numpy() > 0}


def recall_view(run_dir: str | os.PathLike, pose_c2w, hallucinate: bool = False, size: tuple[int, int] | None = None):
    """The view a neural run's memory recalls at camera-to-world ``pose_c2w`` (4, 4): RUN/memory's
    features at the pose (a window culled at the pose rounded to the memory's cell and heading grid) decoded by the
    run's model; with ``hallucinate`` the hallucination module fills the memory's unobserved cells
    first. Returns (rgb (H, W, 3) uint8, depth (H, W) float32 metres, 0 = none): the decoder's
    image (40 x 30 for the shipped model), resized to ``size`` = (W, H) when given (bilinear)."""
    import json

    import cv2
    import numpy as np
    import torch

    from data_tools.errors import FormatError
    from slam.neural.geometry3d import planar_relative
    from slam.neural.train import load_model
    d = Path(run_dir) / "memory"
    meta_p = d / "memory.json"
    if not meta_p.is_file():
        raise FormatError(run_dir, "not a neural run (memory/memory.json missing; made by 'slam run --backend neural')")
    meta = json.loads(meta_p.read_text())
    model, tcfg, _ = load_model(meta["model"])
    try:
        psi = torch.from_numpy(np.load(d / "memory.npy"))[None]
        occ = torch.from_numpy(np.load(d / "occupancy.npy"))[None, None]
    except (OSError, ValueError) as e:
        raise FormatError(d, f"unreadable memory snapshot ({e})") from None
    if psi.shape[1] != model.cfg.features:
        raise FormatError(d / "memory.npy", f"{psi.shape[1]} features per cell, the model {meta['model']} has "
                                            f"{model.cfg.features}")
    cell, T0 = float(meta["cell_m"]), np.asarray(meta["T0"])
    row, col, yaw = planar_relative(T0, np.asarray(pose_c2w, float), cell)
    k = yaw / (2 * np.pi / model.cfg.rotations)          # heading in units of the memory's turns (real)
    U = psi.shape[-1]
    if max(abs(row), abs(col)) > U // 2:
        raise FormatError(meta_p, f"the pose is {max(abs(row), abs(col)) * cell:.1f} m from the first frame, "
                                  f"outside the memory ({U // 2 * cell:.1f} m)")
    w = tcfg.world
    from data_tools.camera import read_camera_json
    from slam.neural.data3d import view_geometry
    _, wedge = view_geometry(read_camera_json(Path(run_dir) / "camera.json").intrinsics, T0, w)
    vm = torch.from_numpy(wedge.astype(np.float32))
    with torch.no_grad():
        mem = model.hallucinate(psi, occ) if hallucinate else psi
        img = model.recall(mem, torch.tensor([[row, col, k]], dtype=torch.float32), vm)[0].numpy()
    rgb = np.clip((np.transpose(img[:3], (1, 2, 0)) + 1) / 2, 0, 1)
    depth = (img[3] + 1) / 2 * w.max_range_m
    depth = np.where(img[3] > -0.95, depth, 0.0).astype(np.float32)
    if size is not None:
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR)
        depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
    return (rgb * 255).round().astype(np.uint8), depth
