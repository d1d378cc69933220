"""The runs behind ``realgap neural train|eval``: a model folder, resumable training, evaluation JSON."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from data_tools.errors import ConfigError

__all__ = ["train_to_folder", "evaluate_folder"]


def train_to_folder(cfg, out: str | os.PathLike, overwrite: bool = False, progress: bool = True,
                    log: Callable[[str], None] | None = None):
    """Train into ``out`` (MODEL/weights.pt, neural.json; checkpoint.pt while training)."""
    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    from slam.neural.train import save_model, train_memory
    folder = check_output_dir(out, finished="neural.json", overwrite=overwrite)
    if overwrite:
        for name in ("neural.json", "weights.pt", "checkpoint.pt"):
            (folder / name).unlink(missing_ok=True)
    folder.mkdir(parents=True, exist_ok=True)
    mark_incomplete(folder, "realgap neural train", 0, cfg.iterations, unit="steps")
    model, _disc, tlog = train_memory(cfg, folder / "checkpoint.pt", progress=progress, log=log)
    save_model(folder, model, cfg, {"train_log": tlog.steps[-20:], "train_seconds": round(tlog.seconds, 1),
                                    "resumed_from_step": tlog.resumed_from})
    (folder / "checkpoint.pt").unlink(missing_ok=True)
    clear_incomplete(folder)
    return model, tlog, folder


def evaluate_folder(model_dir, out: str | os.PathLike | None, sequences: int = 64, overwrite: bool = False,
                    progress: bool = True) -> dict:
    from data_tools.outputs import check_output_dir
    from slam.neural.evaluate import evaluate_2d
    from slam.neural.train import load_model
    if sequences < 1:
        raise ConfigError(f"--sequences must be >= 1, got {sequences}")
    folder = check_output_dir(out, finished="neural_eval.json", overwrite=overwrite) if out else None
    model, cfg, _info = load_model(model_dir)
    if cfg.mode != "2d":
        raise ConfigError("only 2d models can be evaluated so far")
    res = evaluate_2d(model, cfg, sequences, progress=progress)
    if folder is not None:
        from data_tools.results import atomic_write_json
        atomic_write_json(Path(folder) / "neural_eval.json", {"model": str(Path(model_dir).resolve()), **res})
    return res
