"""The runs behind the ``realgap neural`` commands: a model folder made or copied, resumable training and
refinement stages, the evaluation JSON with its result header. The inference the backend, ``slam render`` and
the viewer call is :mod:`slam.neural.inference`."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from data_tools.errors import ConfigError

__all__ = ["train_to_folder", "train_topview_into", "add_topview", "refine_into", "refine_folder",
           "refine_hallucination_folder", "evaluate_folder", "eval_metrics"]

REFINE_CHECKPOINT = "refine_checkpoint.pt"
HALLU_CHECKPOINT = "hallucination_checkpoint.pt"


def train_to_folder(cfg, out: str | os.PathLike, overwrite: bool = False, progress: bool = True,
                    log: Callable[[str], None] | None = None, simulate=None):
    """Train into ``out`` (MODEL/weights.pt, neural.json; checkpoint.pt while training)."""
    import dataclasses

    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    from slam.neural.io import save_model
    from slam.neural.train import train_memory
    folder = check_output_dir(out, finished="neural.json", overwrite=overwrite)
    if overwrite:
        for name in ("neural.json", "weights.pt", "checkpoint.pt"):
            (folder / name).unlink(missing_ok=True)
    folder.mkdir(parents=True, exist_ok=True)
    total = cfg.iterations + cfg.refine.steps
    unit = "steps (memory training, then decoder refinement)" if cfg.refine.steps else "steps"

    def mark(done: int) -> None:
        mark_incomplete(folder, "realgap neural train", done, total, unit=unit)
    mark(0)
    cfg = cfg.validate().resolved()
    model, _disc, tlog = train_memory(cfg, folder / "checkpoint.pt", progress=progress, log=log, simulate=simulate,
                                      on_checkpoint=mark)
    info = {}
    if cfg.refine.steps > 0:
        # the memory's final checkpoint is on disk: an interruption here restarts only this phase
        rcfg = dataclasses.replace(cfg.refine, seed=cfg.seed)
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
    from slam.neural.data import worlds_3d
    bank = worlds_3d(cfg, simulate, progress, log)
    dec, hist, sec = train_topview(model, bank, steps, batch=cfg.batch, seq_steps=cfg.steps, lr=cfg.lr, seed=cfg.seed,
                                   progress=progress, log=log)
    info = {"steps": int(steps), "seed": int(cfg.seed), "seconds": round(sec, 1), "log": hist[-10:],
            "command": command or "realgap neural train --mode 3d"}
    save_topview(folder, dec, info)
    return info


def add_topview(model_dir, tvcfg, overwrite: bool = False, worlds: str | None = None, progress: bool = True,
                log=None, simulate=None) -> dict:
    """``neural train-topview``: give an existing 3D model folder a trained top-view decoder for ``tvcfg``
    (:class:`slam.neural.config.TopviewConfig`) (the memory's weights are not touched)."""
    import dataclasses

    from data_tools.errors import RealgapError
    from slam.neural.io import load_model
    from slam.neural.topview import TOPVIEW_FILE
    tvcfg.validate()
    steps = tvcfg.steps
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

    from slam.neural.data import batch_source
    from slam.neural.refine import refine_decoder
    wcfg = dataclasses.replace(cfg, world=dataclasses.replace(cfg.world, rooms=int(rcfg.rooms)))
    bank = batch_source(wcfg, simulate, progress, log)
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
    from slam.neural.io import load_model
    from slam.neural.topview import TOPVIEW_FILE
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
    from slam.neural.io import save_model
    from slam.neural.topview import TOPVIEW_FILE
    rcfg.validate()
    if rcfg.steps < 1:
        raise ConfigError(f"steps must be >= 1, got {rcfg.steps}")
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


def refine_hallucination_folder(model_dir, out, hcfg, worlds: str | None = None,
                                overwrite: bool = False, progress: bool = True, log=None, simulate=None) -> dict:
    """``neural refine-hallucination``: a copy of the model folder ``model_dir`` in ``out`` with a trained
    occupancy mask and a retrained hallucination module (:mod:`slam.neural.refine_hallucination`; every other
    weight copied unchanged). The top-view decoder of a 3D model reads the occupancy: it is retrained for
    ``hcfg.topview_steps`` steps on the same rooms (0 = none is written). Resumable: a re-run with the same ``out``
    continues from its checkpoint. Returns the stage's info."""
    import dataclasses

    from data_tools.outputs import clear_incomplete
    from slam.neural.data import batch_source
    from slam.neural.io import save_model
    from slam.neural.refine_hallucination import refine_hallucination
    hcfg.validate()
    topview_steps = hcfg.topview_steps
    model, cfg, info, folder, mark = _model_copy_folder(model_dir, out, overwrite,
                                                        "realgap neural refine-hallucination",
                                                        hcfg.occ_steps + hcfg.steps)
    run_cfg = dataclasses.replace(cfg, worlds_dir=str(worlds)) if worlds else cfg    # saved: the model's own config
    bank = batch_source(run_cfg, simulate, progress, log)
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
    from slam.neural.io import load_model
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
