"""The runs behind ``realgap recog ...``: train a recogniser (simulate the views, train the network,
index the database) into a folder, resumably.

Every step keeps its result on disk (the chunks of simulated views, the training checkpoint),
so a killed ``recog train`` continues where it stopped; the folder carries ``incomplete.json``
until the recogniser is saved.
"""
from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from data_tools.errors import ConfigError
from recog.data import DataConfig, generate_training_data, load_training_data
from recog.database import DescriptorDB
from recog.model import Recogniser
from recog.objects import load_objects
from recog.patches import PatchConfig
from recog.symmetry import detect_symmetry, parse_symmetry
from recog.train import TrainConfig, train_network

__all__ = ["train_recogniser", "TrainOutcome", "parse_symmetries"]


@dataclass
class TrainOutcome:
    model: Recogniser
    folder: Path
    chunks_made: int
    chunks_kept: int
    resumed_step: int
    seconds: dict
    self_check: dict


def parse_symmetries(items: list[str] | None) -> dict[str, dict]:
    """``["obj_05=z:2", "obj_01=z:inf"]`` -> {name: symmetry}."""
    out = {}
    for it in items or []:
        if "=" not in it:
            raise ConfigError(f"--symmetry: expected NAME=AXIS:ORDER (e.g. obj_05=z:2), got {it!r}")
        name, spec = it.split("=", 1)
        try:
            out[name.strip()] = parse_symmetry(spec)
        except ValueError as e:
            raise ConfigError(f"--symmetry: {e}") from None
    return out


def train_recogniser(objects_spec, out: str | os.PathLike, data: DataConfig, train: TrainConfig, *,
                     scale: float | None = None, symmetries: dict[str, dict] | None = None, workers: int = 1,
                     overwrite: bool = False, keep_data: bool = True, index: str = "auto", progress: bool = True,
                     log: Callable[[str], None] | None = None) -> TrainOutcome:
    """Train a recogniser of ``objects_spec`` (see :func:`recog.objects.load_objects`) into ``out``."""
    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    data.validate()
    train.validate()
    folder = check_output_dir(out, finished="recogniser.json", overwrite=overwrite)
    if overwrite and (folder / "recogniser.json").exists():
        import shutil
        for name in ("recogniser.json", "weights.pt", "database.npz", "checkpoint.pt"):
            (folder / name).unlink(missing_ok=True)
        shutil.rmtree(folder / "data", ignore_errors=True)
    objs = load_objects(objects_spec, scale)
    declared = symmetries or {}
    unknown = sorted(set(declared) - {o.name for o in objs})
    if unknown:
        raise ConfigError(f"--symmetry: no object named {unknown[0]!r} (objects: {', '.join(o.name for o in objs)})")
    t = {}
    t0 = time.perf_counter()
    for o in objs:
        o.symmetry = declared.get(o.name) or detect_symmetry(o.merged())
    t["symmetry_s"] = time.perf_counter() - t0
    patch = PatchConfig(crop_m=round(1.2 * max(o.diameter_m for o in objs), 4))
    folder.mkdir(parents=True, exist_ok=True)
    mark_incomplete(folder, "realgap recog train", 0, 3, unit="steps (views, training, database)")
    n_chunks = sum(1 for _ in (folder / "data" / data.variant).glob("*/chunk_*.npz")) \
        if (folder / "data" / data.variant).is_dir() else 0
    t0 = time.perf_counter()
    made = generate_training_data(objs, data, patch, folder / "data", workers=workers, progress=progress)
    t["views_s"] = time.perf_counter() - t0
    if n_chunks and log is not None:
        log(f"resumed: {n_chunks} chunks of simulated views already in {folder / 'data'} were kept")
    mark_incomplete(folder, "realgap recog train", 1, 3, unit="steps (views, training, database)")
    td = load_training_data(objs, data, folder / "data")
    t0 = time.perf_counter()
    net, tlog = train_network(td, [o.symmetry for o in objs], train, patch.size, folder / "checkpoint.pt",
                              progress=progress, log=log)
    t["train_s"] = time.perf_counter() - t0
    mark_incomplete(folder, "realgap recog train", 2, 3, unit="steps (views, training, database)")
    t0 = time.perf_counter()
    model = Recogniser([o.to_json() for o in objs], net, DescriptorDB(np.zeros((0, 1), np.float32), *([np.zeros(0)] * 4)),
                       patch, data, train, folder=folder)
    N, D = td.patches.shape[:2]
    if train.input == "rgb":     # a colour recogniser indexes A renders of the views (TrainConfig.input)
        from recog.train import database_seed, render_colour_views
        views = render_colour_views(td, patch.size, database_seed(train)).reshape(N * D, 3, patch.size, patch.size)
    else:
        views = td.patches.reshape(N * D, patch.size, patch.size).astype(np.float32)
    desc = model.describe(views).reshape(N, D, -1)
    check = _self_check(desc, td)
    db = DescriptorDB(desc.reshape(N * D, -1), np.repeat(td.obj, D), np.repeat(td.R_local, D, axis=0),
                      td.offset.reshape(N * D, 3), np.repeat(td.view, D), index)
    model.db = db
    t["database_s"] = time.perf_counter() - t0
    model.info = {"training_views": int(N), "draws": int(D), "database_entries": len(db),
                  "train_log": tlog.steps[-10:], "train_seconds": round(tlog.seconds, 1),
                  "warnings": tlog.warnings, "self_check": check, "timings_s": {k: round(v, 1) for k, v in t.items()},
                  "resumed_from_step": tlog.resumed_from}
    model.save(folder)
    (folder / "checkpoint.pt").unlink(missing_ok=True)
    if not keep_data:
        import shutil
        shutil.rmtree(folder / "data", ignore_errors=True)
    clear_incomplete(folder)
    for w in tlog.warnings:
        if log is not None:
            log(f"warning: {w}")
    return TrainOutcome(model, folder, made, n_chunks, tlog.resumed_from, t, check)


def _self_check(desc: np.ndarray, td) -> dict:
    """Each view's second draw queried against the first draws of all views: how often the nearest is
    the same object / the same view (noise invariance of the descriptor on the training data)."""
    from recog.database import ExactIndex
    idx = ExactIndex(desc[:, 0])
    _, nn = idx.search(desc[:, 1], 1)
    nn = nn[:, 0]
    return {"same_object": float(np.mean(td.obj[nn] == td.obj)),
            "same_view": float(np.mean(nn == np.arange(len(nn))))}


def describe_configs(data: DataConfig, train: TrainConfig) -> dict:
    return {"data": asdict(data), "train": asdict(train)}


def predict_file(model_dir, depth_png, bbox_text: str, camera_json=None, icp: bool = True):
    """``recog predict``: the :class:`~recog.model.Prediction` for a window of a depth PNG. The
    camera is ``camera_json`` or the camera.json next to the image or in its parent folder."""
    from data_tools.camera import read_camera_json
    from data_tools.errors import FormatError
    from data_tools.outputs import check_input_file
    from data_tools.sequence import read_depth_png
    png = check_input_file(depth_png, "depth image")
    if camera_json is None:
        for cand in (png.parent / "camera.json", png.parent.parent / "camera.json"):
            if cand.is_file():
                camera_json = cand
                break
        else:
            raise FormatError(png, "no camera.json next to the image or in its parent folder (give --camera)")
    cam = read_camera_json(check_input_file(camera_json, "camera file", "--camera"))
    try:
        bbox = [float(v) for v in str(bbox_text).split(",")]
    except ValueError:
        raise ConfigError(f"--bbox: expected x0,y0,x1,y1 in pixels, got {bbox_text!r}") from None
    if len(bbox) != 4:
        raise ConfigError(f"--bbox: expected x0,y0,x1,y1 in pixels, got {bbox_text!r}")
    depth = read_depth_png(png, cam.depth_scale)
    if depth.shape != (cam.intrinsics.height, cam.intrinsics.width):
        raise FormatError(png, f"image is {depth.shape[1]}x{depth.shape[0]}, the camera says "
                               f"{cam.intrinsics.width}x{cam.intrinsics.height}")
    from recog.patches import check_bbox
    try:     # a window mostly off the image would be recognised from a sliver, with full confidence
        check_bbox(bbox, cam.intrinsics.width, cam.intrinsics.height, "--bbox", min_inside=0.5)
    except Exception as e:
        raise ConfigError(str(e)) from None
    return Recogniser.load(model_dir).predict(depth, cam.intrinsics, bbox, icp=icp)
