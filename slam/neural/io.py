"""Saving and loading a neural-memory model folder: MODEL/weights.pt (the network's state dict) and
MODEL/neural.json (format, version, the training configuration with the network's as its ``model``, info).

Version 1 files (written before the configuration tree; both shipped models) held the network's configuration
in a separate ``memory`` block, the training's ``features`` / ``width`` / ``refine_*`` fields flat, and the options
of experiments no shipped model kept: :func:`upgrade_v1` turns them into version 2 on reading (the files on disk are
not touched).
"""
from __future__ import annotations

import io
import json
from pathlib import Path

from data_tools.errors import FormatError

__all__ = ["CKPT_FORMAT", "CKPT_VERSION", "save_model", "load_model", "read_config", "upgrade_v1",
           "REMOVED_OPTIONS"]

CKPT_FORMAT = "realgap-neural-memory"
CKPT_VERSION = 2

REMOVED_OPTIONS = {"decoder": "learned", "correlation": "dot", "equivariance": "none", "subcell": False,
                   "colour_skip": False, "decoder_skip": False, "loc_weight_final": 1.0}
"""Options of earlier code that no shipped model used, with the one value the code implements now
(docs/neural_not_kept.md): a saved model that records them with that value loads, any other value is refused. The
``rays`` decoder's camera fields (:data:`RAY_FIELDS`) only mattered with ``decoder = "rays"`` and are dropped."""
RAY_FIELDS = ("camera", "level_rotation", "camera_height_m", "cell_m", "max_range_m", "ray_samples")
_MOVED_TO_REFINE = {"refine_steps": "steps", "refine_rooms": "rooms", "refine_pool_batches": "pool_batches"}


def _without_removed_options(block: dict, where) -> dict:
    out = dict(block)
    for k, kept in REMOVED_OPTIONS.items():
        if k in out and (v := out.pop(k)) != kept:
            raise FormatError(where, f"trained with {k} = {v!r}, an option this realgap no longer has "
                                     "(docs/neural_not_kept.md)")
    for k in RAY_FIELDS:
        out.pop(k, None)
    return out


def upgrade_v1(meta: dict, where) -> dict:
    """A version 1 neural.json (``train`` and ``memory`` blocks) as version 2: the memory block becomes
    ``train.model`` (the training's ``features`` / ``width`` must agree with it), ``refine_steps`` /
    ``refine_rooms`` / ``refine_pool_batches`` become ``train.refine``, removed options recorded at the value the
    code implements are dropped (another value is a :class:`FormatError` naming ``where``)."""
    train, memory = meta.get("train"), meta.get("memory")
    if not isinstance(train, dict) or not isinstance(memory, dict):
        raise FormatError(where, "version 1 model without 'train' and 'memory' objects")
    train, memory = _without_removed_options(train, where), _without_removed_options(memory, where)
    for k in ("features", "width"):
        if k in train and train.pop(k) != memory.get(k):
            raise FormatError(where, f"train.{k} and memory.{k} differ")
    refine = {new: train.pop(old) for old, new in _MOVED_TO_REFINE.items() if old in train}
    return {**meta, "version": CKPT_VERSION, "train": {**train, "model": memory, "refine": refine}}


def save_model(folder: str | Path, model, cfg, info: dict | None = None) -> Path:
    """MODEL/weights.pt (state dict) + MODEL/neural.json (format, version, ``cfg`` with ``model.cfg`` as its
    ``model``, info)."""
    import dataclasses

    import torch

    from data_tools.config import config_to_dict
    from data_tools.results import atomic_write_bytes, atomic_write_json
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    atomic_write_bytes(folder / "weights.pt", buf.getvalue())
    train = config_to_dict(dataclasses.replace(cfg, model=model.cfg))
    atomic_write_json(folder / "neural.json", {"format": CKPT_FORMAT, "version": CKPT_VERSION, "train": train,
                                               "info": info or {}})
    return folder


def read_config(folder: str | Path):
    """(:class:`slam.neural.config.NeuralTrainConfig` with the network's configuration as ``model``, info) of a
    model folder, without torch; one-line errors naming the file."""
    from data_tools.config import config_from_dict
    from slam.neural.config import NeuralTrainConfig
    folder = Path(folder)
    meta_p = folder / "neural.json"
    if folder.is_file() or not meta_p.is_file():
        raise FormatError(folder, "not a neural-memory model folder (neural.json missing; made by 'realgap neural train')")
    try:
        meta = json.loads(meta_p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(meta_p, f"not valid JSON ({e})") from None
    if not isinstance(meta, dict) or meta.get("format") != CKPT_FORMAT:
        raise FormatError(meta_p, f"not a {CKPT_FORMAT} file")
    if meta.get("version") == 1:
        meta = upgrade_v1(meta, meta_p)
    if meta.get("version") != CKPT_VERSION:
        raise FormatError(meta_p, f"model format version {meta.get('version')!r}, this realgap reads 1 and "
                                  f"{CKPT_VERSION}")
    cfg = config_from_dict(NeuralTrainConfig, meta.get("train"), f"{meta_p}: train", strict=True)   # a file: JSON types
    return cfg, meta.get("info", {})


def load_model(folder: str | Path):
    """(NeuralMemory in eval mode, NeuralTrainConfig, info) of a saved model; one-line errors."""
    import torch

    from slam.neural.memory import NeuralMemory
    folder = Path(folder)
    cfg, info = read_config(folder)
    model = NeuralMemory(cfg.model)
    try:
        model.load_state_dict(torch.load(folder / "weights.pt", map_location="cpu", weights_only=True))
    except FileNotFoundError:
        raise FormatError(folder / "weights.pt", "file not found") from None
    except Exception as e:
        raise FormatError(folder / "weights.pt", f"weights do not fit the model ({type(e).__name__}: "
                                                 f"{str(e).splitlines()[0][:80]})") from None
    model.eval()
    return model, cfg, info
