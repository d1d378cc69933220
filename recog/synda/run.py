"""SynDA end to end: objects -> training views -> trained generator file (``realgap synda train``), and
the generator in front of a recogniser (:func:`patch_mapper`, ``realgap recog eval --synda``).

    GEN            the generator (:mod:`recog.synda.io`); its ``info`` holds the objects, the patch
                   configuration (must match the recogniser's), the view configuration, the command,
                   seed, final losses and timings
    GEN.work/      (default; ``work``) data/<object>/chunk_NNN.npz (:mod:`recog.synda.data`) and
                   checkpoint.pt: a killed run continues when re-run; deleted at the end unless kept
"""
from __future__ import annotations

import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable

import numpy as np

from data_tools.errors import ConfigError, FormatError
from recog.data import DataConfig
from recog.objects import load_objects
from recog.patches import PatchConfig
from recog.synda.config import SyndaConfig

__all__ = ["train_synda", "patch_mapper", "use_synda", "check_patch_match"]


def train_synda(objects_spec, gen: str | os.PathLike, cfg: SyndaConfig, views: DataConfig, *,
                work: str | os.PathLike | None = None, scale: float | None = None, workers: int = 1,
                overwrite: bool = False, keep_work: bool = False, progress: bool = True, command: str = "",
                checkpoint_every: int = 100, log: Callable[[str], None] | None = None,
                init: str | os.PathLike | None = None) -> tuple[Path, dict]:
    """Train a generator of ``objects_spec`` into the file ``gen``; returns (path, info). ``init``: a generator
    file to start from (fine-tuning, e.g. with the descriptor loss)."""
    from recog.synda.augment import Augmenter
    from recog.synda.data import folder_chunks, generate_synda_data, load_synda_data
    from recog.synda.io import save_generator
    from recog.synda.train import check_start, default_work, evaluate_batch_loss, load_descriptor_net, train_generator
    cfg.validate()
    views.validate()
    check_start(cfg, init)
    gen = Path(gen)
    if gen.exists() and not overwrite:
        raise FormatError(gen, "a generator is already there (use --overwrite to replace it)")
    if gen.is_dir():
        raise FormatError(gen, "is a folder; the generator is one file")
    work = Path(work) if work else default_work(gen)
    objs = load_objects(objects_spec, scale)
    patch = PatchConfig(size=cfg.generator.size, crop_m=round(1.2 * max(o.diameter_m for o in objs), 4))
    dnet = None
    if cfg.train.descriptor_weight > 0:
        dnet = load_descriptor_net(cfg.train.descriptor_recogniser, patch.size, patch.crop_m, cfg.train.device)
    noisy = cfg.domain == "depth"
    had = folder_chunks(work / "data")
    if had and log is not None:
        log(f"resumed: {had} chunks of simulated views already in {work / 'data'} are kept")
    t = {}
    t0 = time.perf_counter()
    made = generate_synda_data(objs, views, patch, work / "data", noisy, workers=workers, progress=progress)
    t["views_s"] = round(time.perf_counter() - t0, 1)
    data = load_synda_data(objs, work / "data", noisy)
    aug = Augmenter(cfg.augment, cfg.domain, cfg.generator.size)
    net, tlog = train_generator(cfg, data, work / "checkpoint.pt", augmenter=aug, progress=progress, log=log,
                                checkpoint_every=checkpoint_every, descriptor_net=dnet, init=init)
    t["train_s"] = round(tlog.seconds, 1)
    held = evaluate_batch_loss(net, cfg, data, aug, seed=12345, descriptor_net=dnet)
    info = {"command": command, "seed": cfg.train.seed, "objects": [o.to_json() for o in objs],
            "object_names": [o.name for o in objs], "patch": asdict(patch), "views": asdict(views),
            "training_views": int(len(data)), "measured_draws": int(data.noisy.shape[1]),
            "final_losses": tlog.steps[-1] if tlog.steps else {}, "train_log": tlog.steps[-20:],
            "eval_mode_batch_loss": {k: round(v, 5) for k, v in held.items()},
            "resumed_from_step": tlog.resumed_from, "init": str(init) if init else None, "chunks_made": made, "timings_s": t}
    save_generator(gen, net, cfg, info)
    if not keep_work:
        shutil.rmtree(work, ignore_errors=True)
    return gen, info


def check_patch_match(gen_info: dict, patch: PatchConfig, gen_path) -> None:
    """One-line error unless the generator was trained on patches cut like the recogniser's."""
    p = gen_info.get("patch") or {}
    if int(p.get("size", -1)) != int(patch.size) or abs(float(p.get("crop_m", -1)) - float(patch.crop_m)) > 1e-6:
        raise FormatError(gen_path, f"the generator was trained on {p.get('size')} px patches of {p.get('crop_m')} m, "
                                    f"the recogniser cuts {patch.size} px of {patch.crop_m} m (train it on the "
                                    f"recogniser's objects)")


def use_synda(model, generator: str | os.PathLike) -> dict:
    """Put SynDA's generator file ``generator`` in front of the descriptor of ``model`` (a
    :class:`recog.model.Recogniser`: its ``patch_map``, source and input domain); returns the generator's info.
    A colour recogniser is a one-line ConfigError: a generator maps its input to depth."""
    if model.input == "rgb":
        raise ConfigError("--synda: a SynDA generator maps its input to depth, this recogniser reads colour "
                          "(trained with --input rgb); give a depth recogniser")
    model.patch_map, ginfo = patch_mapper(generator, model.patch, domain=None)
    model.patch_map_source, model.patch_map_domain = str(generator), ginfo["domain"]
    return ginfo


def patch_mapper(gen_path: str | os.PathLike, patch: PatchConfig | None = None, device: str = "cpu",
                 domain: str | None = "depth"):
    """(map, info): ``map`` takes (S, S) / (N, S, S) float32 normalised depth patches (a ``depth`` generator) or
    (3, S, S) / (N, 3, S, S) colour patches in [-1, 1] (an ``rgb`` one) and returns h_G's final output, (S, S) /
    (N, S, S) clean synthetic depth; ``info['domain']`` says which. ``domain``: the input domain the caller
    needs (None: either); the generator's final output must be depth (the recogniser's input) and, with
    ``patch`` given, it must have been trained on such patches."""
    import torch

    from recog.synda.io import load_generator
    net, cfg, info = load_generator(gen_path, domain, device)
    if cfg.generator.target != "depth":
        raise FormatError(gen_path, f"the generator's final output is {cfg.generator.target}, the recogniser reads "
                                    f"depth (train it with 'realgap synda train --target depth')")
    if patch is not None:
        check_patch_match(info, patch, gen_path)
    single = 3 if cfg.domain == "rgb" else 2

    def run(images: np.ndarray) -> np.ndarray:
        a = np.asarray(images, np.float32)
        one = a.ndim == single
        x = torch.from_numpy(np.ascontiguousarray(a[None] if one else a))
        if cfg.domain != "rgb":
            x = x[:, None]
        with torch.no_grad():
            y = net(x.to(device))["output"][:, 0].cpu().numpy()
        return y[0] if one else y

    return run, {**info, "domain": cfg.domain}


def modalities(gen_path: str | os.PathLike, images: np.ndarray, domain: str | None = None) -> tuple[dict, dict]:
    """({modality: (N, C, S, S) numpy}, info): every intermediate output of the generator (the mask as
    probabilities) for (N, C, S, S) inputs in [-1, 1]."""
    import torch

    from recog.synda.io import load_generator
    from recog.synda.model import check_input
    net, cfg, info = load_generator(gen_path, domain)
    x = torch.from_numpy(np.ascontiguousarray(images, np.float32))
    check_input(x, cfg.generator, cfg.domain, gen_path)
    with torch.no_grad():
        out = net(x)
    res = {}
    for k, v in out.items():
        if k == "code":
            continue
        if k == "mask":
            v = torch.sigmoid(v) if v.shape[1] == 1 else torch.softmax(v, 1)
        res[k] = v.numpy()
    if cfg.domain not in ("rgb", "depth"):
        raise ConfigError(f"unknown generator domain {cfg.domain}")
    return res, {"domain": cfg.domain, "target": cfg.generator.target, **info}
