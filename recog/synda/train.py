"""Training SynDA's generator h_G (thesis section 5.3) with the project's one training loop
(:func:`data_tools.training.run_steps`: resume, checkpoint, progress; constant learning rate as in
the thesis).

Every step draws a batch of views (numpy Generator of the resumable state) and A's parameters
(a seed from the same Generator: :meth:`Augmenter.draw`), builds the input with
:meth:`Augmenter.apply` and the targets (:func:`make_batch`), and takes one Adam step on
:func:`recog.synda.loss.generator_loss` (+ the optional bottleneck triplet loss).

Domains:

* ``depth``: targets are the clean view (depth in the recogniser's patch normalisation, its normals
  by :func:`recog.synda.data.normals_from_depth`, the object mask); the input is one of the view's
  physical-pipeline draws (randomised sensor effects) put through A (background kept or replaced by
  a procedural one - the target then carries the same clean background -, nearer occluders, blur).
* ``rgb``: the thesis' setting: A renders the clean normals of the view with a random Blinn-Phong
  light, procedural hue/saturation textures, backgrounds, occluders and blur; targets are the
  normals and depth on the object (0 normals / far depth +1 elsewhere), the mask and the lightness.

Optional terms (off by default; a deviation from the thesis, see :mod:`recog.synda.loss`): the descriptor loss
through a frozen recogniser's network (:func:`load_descriptor_net`) and the object-weighted output L1, weighted by
``SyndaTrainConfig.descriptor_weight`` / ``object_weight``. ``init``: training may start from a generator file's
weights (same architecture and domain) instead of the seed's random ones, to fine-tune with these terms.

Deviation, on purpose: the optional triplet loss at the bottleneck (thesis Eq. 5.1, with poses)
uses, without poses at hand, the view under a second augmentation as the positive and another
sample of the batch as the negative, with a constant margin :data:`TRIPLET_MARGIN`; it doubles the
batch's cost.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from data_tools.errors import ConfigError, FormatError
from data_tools.training import TrainingState, run_steps, settings_of
from recog.synda.augment import Augmenter
from recog.synda.config import SyndaConfig
from recog.synda.data import SyndaData, normals_from_depth
from recog.synda.loss import bottleneck_triplet_loss, descriptor_loss, generator_loss, object_l1
from recog.synda.model import Generator

__all__ = ["SyndaTrainLog", "make_batch", "train_generator", "TRIPLET_MARGIN", "pick_threads", "load_descriptor_net",
           "extra_losses"]

TRIPLET_MARGIN = 1.0
"""Margin of the bottleneck triplet loss (see the module docstring)."""


@dataclass
class SyndaTrainLog:
    """What training recorded."""

    steps: list[dict] = field(default_factory=list)
    """Every ``log_every`` steps: step, loss (total), one term per modality, ``output``, ``triplet``."""
    seconds: float = 0.0
    """Wall time of the steps run now."""
    resumed_from: int = 0
    """Step the run continued from (0 = a fresh start)."""


def pick_threads(threads: int | None) -> int:
    """torch threads for training: ``threads`` or 1 (measured best on the shared 2-core machine: two threads
    wait for each other, see docs/synda.md); sets them and returns the number."""
    n = 1 if threads is None else int(threads)
    if n < 1:
        raise ConfigError(f"--threads must be >= 1, got {n}")
    torch.set_num_threads(n)
    return n


def make_batch(data: SyndaData, idx: np.ndarray, draw: np.ndarray, augmenter: Augmenter,
               params: dict[str, torch.Tensor], device: str | torch.device = "cpu") -> tuple[torch.Tensor, dict]:
    """(input (B, C, S, S), targets {modality: (B, C_m, S, S)}) of the views ``idx`` (their measured draws
    ``draw`` for the depth domain) under A's ``params`` (see the module docstring)."""
    clean = torch.from_numpy(data.clean[idx].astype(np.float32))[:, None].to(device)
    mask = torch.from_numpy(data.mask[idx])[:, None].to(device=device, dtype=torch.float32)
    if augmenter.domain == "depth":
        if data.noisy.shape[1] == 0:
            raise ConfigError("the depth domain needs measured draws of the views (data made for rgb?)")
        measured = torch.from_numpy(data.noisy[idx, draw].astype(np.float32))[:, None].to(device)
        out = augmenter.apply({"depth": clean, "mask": mask, "measured": measured}, params)
        target = out["target"]
        return out["input"], {"depth": target, "normals": normals_from_depth(target), "mask": mask}
    normals = normals_from_depth(clean)
    out = augmenter.apply({"normals": normals, "mask": mask}, params)
    return out["input"], {"normals": normals * mask, "depth": torch.where(mask > 0.5, clean, torch.ones_like(clean)),
                          "mask": mask, "lightness": out["lightness"]}


def load_descriptor_net(path: str | os.PathLike, size: int, crop_m: float | None = None,
                        device: str | torch.device = "cpu") -> torch.nn.Module:
    """The frozen network (eval mode, no gradients to its weights) of the recogniser folder ``path``, for the
    descriptor loss. One-line :class:`FormatError` unless it reads ``size`` px patches (of ``crop_m`` metres when
    given): only then is h_G's output, in the patch normalisation of :mod:`recog.patches`, what it was trained on."""
    from recog.model import Recogniser
    model = Recogniser.load(path)
    if int(model.patch.size) != int(size) or (crop_m is not None and abs(float(model.patch.crop_m) - crop_m) > 1e-6):
        raise FormatError(path, f"the recogniser reads {model.patch.size} px patches of {model.patch.crop_m} m, the "
                                f"generator's are {size} px of {crop_m if crop_m is not None else '?'} m (another "
                                f"normalisation): use a recogniser of the same objects and patch size")
    net = model.net.to(device).eval()
    for p in net.parameters():
        p.requires_grad_(False)
    return net


def extra_losses(cfg: SyndaConfig, out: dict, tgt: dict, descriptor_net: torch.nn.Module | None) -> tuple[torch.Tensor, dict]:
    """(weighted sum, parts) of the optional descriptor and object terms (see the module docstring); zero and
    no parts when both weights are 0."""
    tc = cfg.train
    total, parts = out["output"].new_zeros(()), {}
    y = tgt[cfg.generator.target]
    if tc.descriptor_weight > 0:
        if descriptor_net is None:
            raise ConfigError("synda descriptor loss: no recogniser network given")
        ld = descriptor_loss(descriptor_net, out["output"], y, tc.descriptor_distance)
        total, parts["descriptor"] = total + tc.descriptor_weight * ld, float(ld.detach())
    if tc.object_weight > 0:
        lo = object_l1(out["output"], y, tgt["mask"])
        total, parts["object"] = total + tc.object_weight * lo, float(lo.detach())
    return total, parts


def check_start(cfg: SyndaConfig, init: str | os.PathLike | None = None) -> None:
    """What would stop training, checked before anything is simulated: a cuda device without a GPU, and an
    ``init`` generator of another version, domain or architecture (ConfigError / FormatError)."""
    if torch.device(cfg.train.device).type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' requested but no GPU is available here (use --preset cpu)")
    if init is not None:
        _init_generator(cfg, init)


def _init_generator(cfg: SyndaConfig, init: str | os.PathLike) -> Generator:
    """The generator in the file ``init``, checked to have ``cfg``'s domain and architecture (building it draws
    from torch's random generator)."""
    from recog.synda.io import load_generator
    from data_tools.config import config_to_dict
    other, ocfg, _ = load_generator(init, cfg.domain)
    if config_to_dict(ocfg.generator) != config_to_dict(cfg.generator):
        raise FormatError(init, "its architecture differs from the one being trained (another preset or --target?)")
    return other


def train_generator(cfg: SyndaConfig, data: SyndaData, checkpoint: str | os.PathLike | None = None, *,
                    augmenter: Augmenter | None = None, progress: bool = True, checkpoint_every: int = 100,
                    log_every: int = 25, log: Callable[[str], None] | None = None,
                    descriptor_net: torch.nn.Module | None = None,
                    init: str | os.PathLike | None = None) -> tuple[Generator, SyndaTrainLog]:
    """Train h_G on ``data``; returns (generator in eval mode, :class:`SyndaTrainLog`). ``checkpoint``: the
    resumable state file (continued from when it exists; a resumed run reaches the same weights as an
    uninterrupted one: the random states are restored and CPU kernels are deterministic). ``descriptor_net``:
    the frozen network of the descriptor loss (default: loaded from ``cfg.train.descriptor_recogniser`` when its
    weight is > 0, checking the patch size only); ``init``: a generator file to start from."""
    cfg.validate()
    tc = cfg.train
    device = torch.device(tc.device)
    check_start(cfg)
    if len(data) < 2:
        raise ConfigError(f"SynDA training needs at least 2 usable views, got {len(data)}")
    if data.clean.shape[-1] != cfg.generator.size:
        raise ConfigError(f"training patches are {data.clean.shape[-1]} px, the generator takes {cfg.generator.size}")
    if tc.descriptor_weight > 0 and descriptor_net is None:     # before seeding: building its network draws
        descriptor_net = load_descriptor_net(tc.descriptor_recogniser, cfg.generator.size, device=device)
    torch.manual_seed(tc.seed)
    net = Generator(cfg.generator, cfg.domain)
    if init is not None:
        net.load_state_dict(_init_generator(cfg, init).state_dict())
    net = net.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=tc.lr, betas=(tc.beta1, 0.999))
    rng = np.random.default_rng(tc.seed)
    aug = augmenter or Augmenter(cfg.augment, cfg.domain, cfg.generator.size)
    K = max(data.noisy.shape[1], 1)
    tlog = SyndaTrainLog()
    state = TrainingState(checkpoint, {"net": net, "opt": opt}, rng, "SynDA training checkpoint", map_location=device,
                          settings=settings_of(cfg))
    resumed = state.resume(log, tc.iterations)
    if resumed is not None:
        tlog.resumed_from, tlog.steps = resumed
    triplet = cfg.generator.triplet

    def step_fn(step: int) -> dict:
        B = tc.batch
        idx = rng.integers(0, len(data), B)
        draw = rng.integers(0, K, B)
        seeds = rng.integers(0, 2 ** 62, 2)
        x, tgt = make_batch(data, idx, draw, aug, aug.draw(B, int(seeds[0])), device)
        if triplet:
            x2, tgt2 = make_batch(data, idx, draw, aug, aug.draw(B, int(seeds[1])), device)
            x = torch.cat([x, x2])
            tgt = {k: torch.cat([v, tgt2[k]]) for k, v in tgt.items()}
        out = net(x)
        loss, parts = generator_loss(out, tgt, cfg.generator.target)
        extra, more = extra_losses(cfg, out, tgt, descriptor_net)
        loss, parts = loss + extra, {**parts, **more}
        if triplet:
            c1, c2 = out["code"][:B], out["code"][B:]
            lt = bottleneck_triplet_loss(c1, c2, c1.roll(1, 0), torch.full((B,), TRIPLET_MARGIN, device=device))
            loss = loss + tc.triplet_weight * lt
            parts["triplet"] = float(lt.detach())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": float(loss.detach()), **parts}

    net.train()
    tlog.seconds = run_steps(step_fn, tc.iterations, start=tlog.resumed_from, history=tlog.steps, log_every=log_every,
                             state=state, checkpoint_every=checkpoint_every, progress=progress,
                             desc=f"training SynDA {cfg.domain}",
                             postfix=lambda r: " ".join(f"{k} {v:.3f}" for k, v in r.items() if k != "step"))
    net.eval()
    return net, tlog


def evaluate_batch_loss(net: Generator, cfg: SyndaConfig, data: SyndaData, augmenter: Augmenter, seed: int,
                        batch: int = 32, descriptor_net: torch.nn.Module | None = None) -> dict:
    """Losses of ``net`` (eval mode) on one fixed batch (views and A drawn from ``seed``): a held-constant
    yardstick to compare generators or steps (with ``cfg``'s optional terms; the descriptor term needs
    ``descriptor_net``)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(data), batch)
    draw = rng.integers(0, max(data.noisy.shape[1], 1), batch)
    x, tgt = make_batch(data, idx, draw, augmenter, augmenter.draw(batch, seed))
    with torch.no_grad():
        out = net(x)
        loss, parts = generator_loss(out, tgt, cfg.generator.target)
        if cfg.train.descriptor_weight == 0 or descriptor_net is not None:
            extra, more = extra_losses(cfg, out, tgt, descriptor_net)
            loss, parts = loss + extra, {**parts, **more}
    return {"loss": float(loss), **parts}


def timed(fn, *a, **kw):
    """(result, seconds) of ``fn(*a, **kw)``."""
    t0 = time.perf_counter()
    r = fn(*a, **kw)
    return r, time.perf_counter() - t0


def default_work(gen: str | os.PathLike) -> Path:
    """The work folder of a generator file (training data and checkpoint): ``GEN.work`` beside it."""
    g = Path(gen)
    return g.with_name(g.name + ".work")
