"""Training the neural memory (thesis 4.3-4.4.1), in three phases, resumable.

1. ``pretrain`` (``pretrain_steps``): encoder and decoder as an auto-encoder of single views.
2. ``memory``: encoder, LSTMs, decoder on whole sequences: L_loc (binary cross-entropy between the
   pose field and the one-hot true pose, thesis Eq. 4.6) + L_anam (L1 of the recalled views at
   the true poses). Registration uses the predicted field; during the first ``teacher_steps`` it
   uses the true pose with a probability falling linearly from 1 to 0 (teacher forcing: without
   it the memory is noise while localisation is still random, and neither learns - a deviation
   from the thesis, which does not describe how it starts).
3. ``hallucination`` (after ``hallucination_from``): the hallucination AE on the final memory,
   L_hallu (L1 of views at the poses the agent visits *after* the first ``observe`` steps,
   decoded from the hole-filled memory of those first steps) + L_corrupt (masked by occupancy) +
   the non-saturating GAN loss against the patch discriminator (trained on culled windows of the
   full memory as real, of the hole-filled partial memory at unvisited poses as fake).

Adam (beta1 = 0.5, lr 2e-4), weights N(0, 0.02), as in the thesis. ``checkpoint.pt`` every ``checkpoint_every``
steps (models, optimisers, step, random states; :class:`data_tools.training.TrainingState`): a re-run continues
there. The loop is :func:`data_tools.training.run_steps`, shared with every other trainer.
"""
from __future__ import annotations

import io
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from data_tools.errors import ConfigError, FormatError
from data_tools.training import TrainingState, linear_ramp, run_steps, set_lr
from slam.neural.data3d import World3DConfig

__all__ = ["NeuralTrainConfig", "TRAIN_PRESETS", "TRAIN_PRESETS_3D", "train_memory", "CKPT_FORMAT", "CKPT_VERSION", "save_model",
           "load_model"]

CKPT_FORMAT = "realgap-neural-memory"
CKPT_VERSION = 1
IMAGE_CHANNELS = {"2d": 3, "3d": 4}
"""Channels C of a mode's observations: 2D RGB views, 3D RGB-D images."""


@dataclass
class NeuralTrainConfig:
    """How the memory is trained (saved with the weights)."""

    mode: str = "2d"
    """2d (agents on images) or 3d (RGB-D sequences)."""
    agent: str = "front"
    """2D agent: square (360 deg view, translates) or front (180 deg view, turns by 90 deg)."""
    image: int = 43
    """Side of the 2D environments, pixels."""
    steps: int = 10
    """Observations per training sequence."""
    observe: int = 5
    """Hallucination: the first ``observe`` steps are memorised, the rest are to be predicted."""
    batch: int = 8
    """Sequences per step."""
    iterations: int = 2200
    """Optimiser steps in all (pretraining included)."""
    pretrain_steps: int = 300
    """Steps of the single-view auto-encoder pre-training (thesis phase 1)."""
    teacher_steps: int = 600
    """Steps (after pretraining) over which teacher-forced registration fades out."""
    hallucination_from: int = 1500
    """Step at which the hallucination module joins."""
    lr: float = 2e-4
    """Base learning rate (thesis: "initialized at 2e-4")."""
    lr_decay_from: int = 0
    """From this step on the learning rate falls linearly to ``lr_final`` x ``lr`` at the last step (all three
    optimisers); 0 = constant."""
    lr_final: float = 0.1
    """The learning rate at the last step over ``lr`` (with ``lr_decay_from``)."""
    loc_weight: float = 1.0
    """Weight of L_loc against L_anam (weight 1) in the memory phases. L_loc's gradient on the shared encoder
    dwarfs L_anam's, so at 1 the encoder serves localisation alone; the 2D ``cpu-long`` preset uses 0.01
    (docs/not_kept.md has the sweep)."""
    loc_weight_final: float = 1.0
    """L_loc's weight at the last step over ``loc_weight``: from ``lr_decay_from`` on it falls linearly with the
    learning rate (:func:`loc_factor`); 1 = constant. Lets localisation be learnt at ``loc_weight`` first and recall
        take the encoder over at the end; in no preset (docs/not_kept.md)."""
    occ_weight: float = 0.0
    """Weight of L_occ (BCE of the occupancy mask b against the observed cells ``seen``, memory phases) and, if > 0,
    the model's occupancy mask is ``affine`` (:attr:`slam.neural.model.MemoryConfig.occupancy`). 0: no loss reaches
    the occupancy LSTM (front_2d; planar_3d's mask was trained afterwards by ``neural refine-hallucination``).
    1 in the 2D ``gpu`` preset; 0 in the others, which reproduce the shipped models."""
    lstm_forget_bias: float = 0.0
    """If not 0: the forget-gate slice of both memory LSTMs' input biases is set to this value (their other
    weights keep PyTorch's LSTM init, uniform +-1/sqrt(n): the thesis' N(0, 0.02) is for the convolutions).
    Every memory cell is updated at every step, most with a zero input (out of view): with a forget bias near 0
    a cell keeps about half of itself per step until the gate learns otherwise; 1 (Jozefowicz et al. 2015's
    advice for LSTMs) starts at about 73 %. 0 = untouched."""
    checkpoint_every: int = 200
    log_every: int = 50
    seed: int = 0
    device: str = "cpu"
    features: int = 8
    """Feature size n of the memory (the thesis uses 16-32; 8 keeps a CPU step under a second)."""
    width: int = 16
    """Channels of the encoder/decoder ResNets."""
    topview_steps: int = 300
    """3D mode: steps of the top-view decoder trained after the memory, the memory frozen
    (:mod:`slam.neural.topview`; the ``slam run --backend neural`` snapshot's topview.png); 0 = none."""
    refine_steps: int = 0
    """Steps of the decoder refinement after the memory phases (:mod:`slam.neural.refine`: the recall decoder
    retrained with an SSIM term, the memory frozen; 3D on ``refine_rooms`` rooms); 0 = none."""
    refine_rooms: int = 48
    """3D mode: training rooms the refinement recalls (seeds 0 .. refine_rooms - 1, simulated on first use)."""
    refine_pool_batches: int = 450
    """Batches of 8 samples the refinement memorises once (:attr:`slam.neural.refine.RefineConfig.pool_batches`)."""
    world: World3DConfig = field(default_factory=World3DConfig)
    """3D mode: grid, images and simulated rooms (:class:`slam.neural.data3d.World3DConfig`)."""
    worlds_dir: str = ""
    """3D mode: folder of the simulated room sequences (made on first use; default ~/.cache/realgap/neural_worlds)."""

    def validate(self) -> "NeuralTrainConfig":
        if self.mode not in ("2d", "3d"):
            raise ConfigError(f"--mode must be 2d or 3d, got {self.mode!r}")
        from slam.neural.data2d import AGENTS
        if self.agent not in AGENTS:
            raise ConfigError(f"unknown agent {self.agent!r}; choose {', '.join(AGENTS)}")
        for k in ("steps", "batch", "iterations", "checkpoint_every", "log_every", "features", "width"):
            if int(getattr(self, k)) < 1:
                raise ConfigError(f"{k} must be >= 1, got {getattr(self, k)}")
        for k in ("topview_steps", "refine_steps"):
            if int(getattr(self, k)) < 0:
                raise ConfigError(f"{k} must be >= 0, got {getattr(self, k)}")
        for k in ("refine_rooms", "refine_pool_batches"):
            if int(getattr(self, k)) < 1:
                raise ConfigError(f"{k} must be >= 1, got {getattr(self, k)}")
        if not (self.occ_weight >= 0 and np.isfinite(self.occ_weight)):
            raise ConfigError(f"occ_weight must be >= 0, got {self.occ_weight}")
        if not (self.loc_weight > 0 and np.isfinite(self.loc_weight)):
            raise ConfigError(f"loc_weight must be > 0, got {self.loc_weight}")
        if not (self.loc_weight_final >= 0 and np.isfinite(self.loc_weight_final)):
            raise ConfigError(f"loc_weight_final must be >= 0, got {self.loc_weight_final}")
        if not 0.0 < self.lr_final <= 1.0:
            raise ConfigError(f"lr_final must be in (0, 1], got {self.lr_final}")
        if not 1 <= self.observe < self.steps:
            raise ConfigError(f"observe must be in 1..steps-1, got {self.observe}")
        return self


_CPU_2D = NeuralTrainConfig(lr_decay_from=1500, lstm_forget_bias=1.0, refine_steps=5000, refine_pool_batches=900)
TRAIN_PRESETS = {
    "cpu": _CPU_2D,
    "cpu-long": replace(_CPU_2D, features=16, width=32, loc_weight=0.01),
    "gpu": NeuralTrainConfig(batch=32, iterations=30000, pretrain_steps=2000, teacher_steps=5000,
                             hallucination_from=15000, features=32, width=64, device="cuda", lr_decay_from=20000,
                             lstm_forget_bias=1.0, refine_steps=10000, refine_pool_batches=2000, loc_weight=0.01,
                             occ_weight=1.0),
}
"""2D presets. ``cpu``: the 30-minute CPU recipe (with decoder refinement); ``cpu-long``: the shipped front_2d
recipe (features 16, width 32, L_loc weighted 0.01); ``gpu``: a larger configuration, never run. Times, and what
each choice measured: docs/neural.md, "Training presets"."""


_CPU_3D = NeuralTrainConfig(mode="3d", batch=8, iterations=1100, pretrain_steps=150, teacher_steps=350,
                            hallucination_from=700, features=16, width=16, topview_steps=150)
TRAIN_PRESETS_3D = {
    "cpu": _CPU_3D,
    "cpu-long": replace(_CPU_3D, lr_decay_from=700, refine_steps=1500, refine_rooms=48,
                        world=World3DConfig(view=49, max_range_m=3.6)),
    "gpu": NeuralTrainConfig(mode="3d", batch=32, iterations=20000, pretrain_steps=2000, teacher_steps=4000,
                             hallucination_from=10000, features=32, width=64, device="cuda", topview_steps=2000,
                             refine_steps=3000, refine_rooms=128,
                             world=World3DConfig(rooms=64, test_rooms=8, frames=300)),
}
"""3D (``--mode 3d``) presets. ``cpu``: <= 30 min on 2 cores after the 12 training rooms are simulated once;
``cpu-long``: the memory of the shipped planar_3d (a 49-cell grid to 3.6 m, decoder refined on 48 rooms; its mask
trained afterwards by ``neural refine-hallucination``); ``gpu``: a larger configuration. Times and measurements:
docs/neural.md, "Training presets"."""


def memory_config(cfg: NeuralTrainConfig):
    """The model's sizes for a training configuration."""
    from slam.neural.data2d import AGENTS
    from slam.neural.model import MemoryConfig
    if cfg.mode == "3d":
        w = cfg.world
        reach = int(np.ceil(0.45 * w.stride_max / 30.0 * (cfg.steps - 1) / w.cell_m)) + 4
        return MemoryConfig(channels=IMAGE_CHANNELS["3d"], features=cfg.features, view=w.view,
                            memory=w.view + 2 * reach, width=cfg.width, rotations=w.rotations, search=4, input="image",
                            image_size=(w.image_h, w.image_w), occupancy=_occupancy(cfg))
    q = AGENTS[cfg.agent].view
    reach = cfg.image - q                  # the largest offset from the start the agent can reach
    U = 2 * reach + q
    return MemoryConfig(channels=IMAGE_CHANNELS["2d"], features=cfg.features, view=q, memory=U, width=cfg.width,
                        search=min(3 * q // 4 + 5, (U - q) // 2), occupancy=_occupancy(cfg))


def _occupancy(cfg: NeuralTrainConfig) -> str:
    return "affine" if cfg.occ_weight > 0 else "sigmoid"


@dataclass
class TrainLog:
    steps: list = field(default_factory=list)
    seconds: float = 0.0
    resumed_from: int = 0


def lr_factor(cfg: NeuralTrainConfig, step: int) -> float:
    """The learning rate of ``step`` over the base one: 1 until ``lr_decay_from``, then linear to ``lr_final`` at
    the last step (:func:`data_tools.training.linear_ramp`)."""
    return linear_ramp(step, cfg.lr_decay_from, cfg.iterations, cfg.lr_final)


def loc_factor(cfg: NeuralTrainConfig, step: int) -> float:
    """L_loc's weight at ``step`` over ``loc_weight``: the learning rate's schedule (:func:`lr_factor`) falling to
    ``loc_weight_final``."""
    return linear_ramp(step, cfg.lr_decay_from, cfg.iterations, cfg.loc_weight_final)


OCC_LR = 5e-2
"""Learning rate of the occupancy LSTM (with ``occ_weight``; constant): its 16 weights must move far - forget gate
open, input gate saturated - which the memory's 2e-4 does not do in a CPU budget (tiny 2D model, 400 memory steps:
L_occ 0.86 -> 0.20 at 1e-2, -> 0.004-0.04 at 5e-2)."""


def loc_loss(logits, truth_field):
    """Thesis Eq. 4.6 per step: -[p log p~ + (1 - p) log(1 - p~)] summed over the field, averaged over t >= 1."""
    import torch
    B, T = logits.shape[:2]
    lg = logits[:, 1:].flatten(2)
    logp = torch.log_softmax(lg, -1)
    p = truth_field[:, 1:].flatten(2)
    inside = p.sum(-1) > 0                  # the true pose lies in the searched window
    pos = -(p * logp).sum(-1)
    neg = -((1 - p) * torch.log1p(-logp.exp().clamp(max=1 - 1e-6))).sum(-1)
    return ((pos + neg) * inside).sum() / inside.sum().clamp(min=1)


def train_memory(cfg: NeuralTrainConfig, checkpoint: str | Path | None = None, progress: bool = True,
                 log: Callable[[str], None] | None = None, simulate=None,
                 on_checkpoint: Callable[[int], None] | None = None):
    """Train; returns (model, discriminator, TrainLog). 3D: ``simulate`` makes missing training rooms
    (:data:`slam.neural.data3d.Simulator`). ``on_checkpoint(step)`` is called after each checkpoint is written
    (and with the resumed step on a resume): the command's progress marker follows it."""
    import torch
    import torch.nn.functional as F

    from slam.neural.data2d import AGENTS, make_batch, view_mask
    from slam.neural.model import NeuralMemory, PatchDiscriminator, init_weights, memory_index
    cfg.validate()
    dev = torch.device(cfg.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' requested but no GPU is available here (use --preset cpu)")
    torch.manual_seed(cfg.seed)
    if cfg.mode == "3d":
        bank = worlds_3d(cfg, simulate, progress, log)
    mcfg = memory_config(cfg)
    model = NeuralMemory(mcfg).to(dev)
    if cfg.lstm_forget_bias:
        with torch.no_grad():
            for cell in (model.lstm, model.occ_lstm):
                hs = cell.hidden_size
                cell.bias_ih[hs:2 * hs].fill_(float(cfg.lstm_forget_bias))    # gate order: input, forget, cell, output
    disc = PatchDiscriminator(mcfg).to(dev)
    init_weights(disc)
    occ_own = _occupancy(cfg) == "affine"       # a trained mask: its LSTM learns on its own optimiser, at OCC_LR
    main_params = [p for n, p in model.named_parameters()
                   if not n.startswith("hallucinator") and not (occ_own and n.startswith("occ_lstm"))]
    opt = torch.optim.Adam(main_params, lr=cfg.lr, betas=(0.5, 0.999))
    opt_occ = torch.optim.Adam(model.occ_lstm.parameters(), lr=OCC_LR, betas=(0.5, 0.999)) if occ_own else None
    opt_h = torch.optim.Adam(model.hallucinator.parameters(), lr=cfg.lr, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.lr, betas=(0.5, 0.999))
    rng = np.random.default_rng(cfg.seed)
    if cfg.mode == "3d":
        vm = torch.from_numpy(bank.wedge.astype(np.float32)).to(dev)

        def batch():
            return bank_batch(bank, rng, cfg.batch, cfg.steps, dev)
    else:
        agent = AGENTS[cfg.agent]
        vm = torch.from_numpy(view_mask(agent).astype(np.float32)).to(dev)

        def batch():
            _, obs, _, allo = make_batch(rng, cfg.batch, agent, cfg.steps, cfg.image)
            a = torch.from_numpy(allo).to(dev)
            return torch.from_numpy(obs).to(dev), None, a, a
    tlog = TrainLog()
    parts = {"model": model, "disc": disc, "opt": opt, "opt_h": opt_h, "opt_d": opt_d}
    if occ_own:
        parts["opt_occ"] = opt_occ
    state = TrainingState(checkpoint, parts, rng, "training checkpoint", map_location=dev, on_save=on_checkpoint)
    resumed = state.resume()
    if resumed is not None:
        tlog.resumed_from, tlog.steps = resumed
        if log is not None:
            log(f"resuming training at step {tlog.resumed_from} of {cfg.iterations} from {checkpoint}")
    img_mask = 1.0 if cfg.mode == "3d" else vm         # 3D recalls whole images, 2D the view field

    def step_fn(step: int) -> dict:
        obs_t, cells_t, allo_t, exact_t = batch()      # exact: 3D recall poses, not rounded to the grid
        T = obs_t.shape[1]
        losses = {}
        if step < cfg.pretrain_steps:
            x = obs_t.flatten(0, 1)
            f = model.encode(obs_t, cells_t).flatten(0, 1)
            # each view's own grid as a memory (U = q), recalled at its centre: the auto-encoder of single views
            rec = model.recall(f, f.new_zeros(len(x), 3), vm)
            loss = (torch.abs(rec - x) * img_mask).mean()
            losses["anam"] = float(loss.detach())
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            return losses
        s = step - cfg.pretrain_steps
        p_teacher = max(0.0, 1.0 - s / max(cfg.teacher_steps, 1))
        teacher = allo_t if rng.random() < p_teacher else None
        out = model(obs_t, vm, teacher, cells=cells_t)
        Wp = out["logits"].shape[-1]
        truth = torch.stack([model.local_one_hot(allo_t[:, t], out["centres"][:, t], Wp)
                             for t in range(cfg.steps)], 1)
        l_loc = loc_loss(out["logits"], truth)
        rec = model.recall(out["psi"], exact_t.flatten(0, 1), vm, memory_index(out["psi"], T))
        l_anam = (torch.abs(rec - obs_t.flatten(0, 1)) * img_mask).mean()
        loss = cfg.loc_weight * loc_factor(cfg, step) * l_loc + l_anam
        losses.update(loc=float(l_loc.detach()), anam=float(l_anam.detach()))
        if occ_own:       # its gradient reaches the occupancy LSTM only (its input is detached)
            l_occ = F.binary_cross_entropy(out["occ"].clamp(1e-6, 1 - 1e-6), out["seen"])
            loss = loss + cfg.occ_weight * l_occ
            losses["occ"] = float(l_occ.detach())
            opt_occ.zero_grad(set_to_none=True)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if occ_own:
            opt_occ.step()
        if step >= cfg.hallucination_from:
            losses.update(hallucination_step(model, disc, opt_h, opt_d, obs_t, allo_t, vm, cfg, cells_t, img_mask,
                                              exact_t))
        return losses

    model.train()
    tlog.seconds = run_steps(step_fn, cfg.iterations, start=tlog.resumed_from, history=tlog.steps,
                             log_every=cfg.log_every, state=state, checkpoint_every=cfg.checkpoint_every,
                             lr=lambda step: set_lr((opt, opt_h, opt_d), cfg.lr * lr_factor(cfg, step)),
                             progress=progress, desc="training neural memory")
    model.eval()
    return model, disc, tlog


def bank_batch(bank, rng: np.random.Generator, batch: int, steps: int, dev):
    """One training batch of ``bank`` (:class:`slam.neural.data3d.WorldBank` or :class:`slam.neural.refine.Walks2D`)
    as tensors on ``dev``: (images (B, T, C, H, W) float32, cells (B, T, r, H*W) int64 or None, allocentric poses
    (B, T, 3) int64, exact poses (B, T, 3) float32 - row, col in cells, heading in units of 2 pi / r)."""
    import torch
    imgs, cells, allo, poses = bank.sample(rng, batch, steps)
    exact = np.stack([bank.exact(p) for p in poses]).astype(np.float32)
    return (torch.from_numpy(np.asarray(imgs, np.float32)).to(dev),
            None if cells is None else torch.from_numpy(cells).to(dev),
            torch.from_numpy(np.asarray(allo)).to(dev), torch.from_numpy(exact).to(dev))


def hallucination_step(model, disc, opt_h, opt_d, obs_t, allo_t, vm, cfg, cells_t=None, img_mask=None,
                        exact_t=None) -> dict:
    """One hallucination update: memorise the first ``observe`` steps (no gradient into the memory
    path), fill the holes, predict the later views (recalled at ``exact_t``, default ``allo_t``);
    discriminator on culled windows."""
    import torch
    import torch.nn.functional as F

    from slam.neural.model import memory_index
    B, T = obs_t.shape[:2]
    k = cfg.observe
    img_mask = vm if img_mask is None else img_mask
    with torch.no_grad():
        part = model(obs_t[:, :k], vm, allo_t[:, :k], cells=None if cells_t is None else cells_t[:, :k])
        full = model(obs_t, vm, allo_t, cells=cells_t)
    filled = model.hallucinate(part["psi"], part["occ"])
    later = allo_t[:, k:].flatten(0, 1)
    later_exact = (allo_t if exact_t is None else exact_t)[:, k:].flatten(0, 1)
    rec = model.recall(filled, later_exact, vm, memory_index(filled, T - k))
    l_hallu = (torch.abs(rec - obs_t[:, k:].flatten(0, 1)) * img_mask).mean()
    l_corrupt = (torch.abs(filled - part["psi"]) * part["occ"]).mean()
    fake = model.cull(filled, later, vm, memory_index(filled, T - k))[:, :-1]
    real = model.cull(full["psi"], later, vm, memory_index(full["psi"], T - k))[:, :-1]
    l_gan = F.softplus(-disc(fake)).mean()
    loss = l_hallu + l_corrupt + 0.05 * l_gan
    opt_h.zero_grad(set_to_none=True)
    loss.backward()
    opt_h.step()
    d_loss = F.softplus(-disc(real.detach())).mean() + F.softplus(disc(fake.detach())).mean()
    opt_d.zero_grad(set_to_none=True)
    d_loss.backward()
    opt_d.step()
    return {"hallu": float(l_hallu.detach()), "corrupt": float(l_corrupt.detach()), "disc": float(d_loss.detach())}


def worlds_3d(cfg: NeuralTrainConfig, simulate, progress: bool, log, split: str = "train"):
    """The prepared 3D worlds of ``split`` (:class:`slam.neural.data3d.WorldBank`): simulated on first use
    into ``cfg.worlds_dir`` (default :func:`slam.neural.data3d.default_worlds_dir`), cached as .npz."""
    from slam.neural.data3d import WorldBank, build_worlds, cache_name, default_worlds_dir, load_sequence_arrays
    root = Path(cfg.worlds_dir) if cfg.worlds_dir else default_worlds_dir(cfg.world)
    seqs = build_worlds(root, cfg.world, split, simulate=simulate, log=log)
    arrays = [load_sequence_arrays(s, cfg.world, s / cache_name(cfg.world), progress=progress) for s in seqs]
    return WorldBank(arrays, cfg.world, seqs)


def save_model(folder: str | Path, model, cfg: NeuralTrainConfig, info: dict | None = None) -> Path:
    """MODEL/weights.pt (state dict) + MODEL/neural.json (format, version, configs, info)."""
    import torch

    from data_tools.results import atomic_write_bytes, atomic_write_json
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    atomic_write_bytes(folder / "weights.pt", buf.getvalue())
    atomic_write_json(folder / "neural.json", {"format": CKPT_FORMAT, "version": CKPT_VERSION, "train": asdict(cfg),
                                               "memory": asdict(model.cfg), "info": info or {}})
    return folder


def without_removed_options(block, where) -> dict:
    """A copy of a neural.json ``train`` or ``memory`` block without the options earlier code had and no shipped
    model used (:data:`slam.neural.model.REMOVED_OPTIONS`): recorded at the value the code implements they are
    dropped, another value is a :class:`FormatError` naming ``where``; the ``rays`` decoder's camera fields are
    dropped."""
    from slam.neural.model import RAY_FIELDS, REMOVED_OPTIONS
    out = dict(block) if isinstance(block, dict) else block
    if not isinstance(out, dict):
        return out                      # config_from_dict names the problem
    for k, kept in REMOVED_OPTIONS.items():
        if k in out and (v := out.pop(k)) != kept:
            raise FormatError(where, f"trained with {k} = {v!r}, an option this realgap no longer has "
                                     "(docs/neural_not_kept.md)")
    for k in RAY_FIELDS:
        out.pop(k, None)
    return out


def load_model(folder: str | Path):
    """(NeuralMemory in eval mode, NeuralTrainConfig, info) of a saved model; one-line errors."""
    import json

    import torch

    from data_tools.config import config_from_dict
    from slam.neural.model import MemoryConfig, NeuralMemory
    folder = Path(folder)
    meta_p = folder / "neural.json"
    if folder.is_file() or not meta_p.is_file():
        raise FormatError(folder, "not a neural-memory model folder (neural.json missing; made by 'realgap neural train')")
    try:
        meta = json.loads(meta_p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(meta_p, f"not valid JSON ({e})") from None
    if meta.get("format") != CKPT_FORMAT:
        raise FormatError(meta_p, f"not a {CKPT_FORMAT} file")
    if meta.get("version") != CKPT_VERSION:
        raise FormatError(meta_p, f"model format version {meta.get('version')!r}, this realgap reads {CKPT_VERSION}")
    cfg = config_from_dict(NeuralTrainConfig, without_removed_options(meta.get("train"), meta_p), str(meta_p))
    mcfg = config_from_dict(MemoryConfig, without_removed_options(meta.get("memory"), meta_p), str(meta_p))
    model = NeuralMemory(mcfg)
    try:
        model.load_state_dict(torch.load(folder / "weights.pt", map_location="cpu", weights_only=True))
    except FileNotFoundError:
        raise FormatError(folder / "weights.pt", "file not found") from None
    except Exception as e:
        raise FormatError(folder / "weights.pt", f"weights do not fit the model ({type(e).__name__}: "
                                                 f"{str(e).splitlines()[0][:80]})") from None
    model.eval()
    return model, cfg, meta.get("info", {})
