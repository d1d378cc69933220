"""Training the descriptor network on simulated views (thesis sections 3.2.1 and 3.4.3).

Batches are built by pose-aware mining (:class:`TripletMiner`): an anchor view (object o, view v,
one of its noise draws), its positive = the view of o whose pose is nearest (one of the two
nearest, symmetry-aware, rotation in the patch's virtual camera), a negative = a view of another
object (probability ``1 - same_object_negatives``) or a view of o farther from the anchor than
the positive, and the pair partner = the anchor view under its other noise draw. The loss is
:mod:`recog.loss`. Every ``log_every`` iterations the log records the losses, the fraction of
*active* triplets (loss > 0; near 0 means the task is solved or too easy, near 1 that it is not
learning) and the descriptor spread (std of the batch's descriptors; a spread near 0 is a
collapse to one point, which the run reports as a warning).

Training is resumable: ``checkpoint.pt`` (network, optimiser, iteration, random states) is
written every ``checkpoint_every`` iterations; a re-run continues from it and reaches the same
weights as an uninterrupted run (the random states are restored, CPU kernels are deterministic).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Literal

import numpy as np

from data_tools.config import Range, check_fields
from data_tools.errors import ConfigError
from data_tools.training import TrainingState, run_steps, settings_of
from recog.data import TrainingData

__all__ = ["TrainConfig", "TRAIN_PRESETS", "TripletMiner", "train_network", "TrainLog", "colour_renderer",
           "render_colour_views", "database_seed"]


@dataclass
class TrainConfig:
    """How the network is trained (saved with the recogniser)."""

    network: str = "lenet"
    """Network name (:data:`recog.net.NETWORKS`: lenet, deeper)."""
    descriptor: Annotated[int, Range(1)] = 64
    """Descriptor dimension d."""
    iterations: Annotated[int, Range(1)] = 3000
    """Optimiser steps."""
    batch: Annotated[int, Range(1)] = 64
    """Triplets per step (each also gives one pair): 4 x batch patches go through the network."""
    lr: Annotated[float, Range(0, open_lo=True)] = 1e-3
    """Adam learning rate."""
    weight_decay: Annotated[float, Range(0)] = 1e-5
    """lambda of the loss (L2 on the weights, as the optimiser's weight decay)."""
    class_margin: Annotated[float, Range(math.pi, open_lo=True)] = 4.0
    """Margin for negatives of another object (> pi)."""
    same_object_negatives: Annotated[float, Range(0, 1)] = 0.5
    """Fraction of negatives taken from the anchor's own object (another pose)."""
    hard_negatives: Annotated[float, Range(0, 1)] = 0.5
    """Fraction of negatives mined by pose (see :class:`TripletMiner`); the rest are uniform."""
    pair_weight: Annotated[float, Range(0)] = 1.0
    """Weight of the pair loss."""
    checkpoint_every: Annotated[int, Range(1)] = 250
    """Write checkpoint.pt every this many steps."""
    log_every: Annotated[int, Range(1)] = 50
    """Record the losses every this many steps."""
    synda_augment: Annotated[float, Range(0, 1)] = 0.0
    """Fraction of the training patches put through SynDA's online augmentation A of the depth domain (thesis
    ch. 5's "A(synthetic)" baseline: procedural depth backgrounds, nearer polygon occluders, blur; the ranges
    of ``synda_preset('cpu', 'depth').augment``), each patch of each step drawn anew, on top of the variant's
    sensor model; 0 = off. Every patch augmented (1) made the LeNet descriptor collapse to one point within 50
    steps (chairs, physical variant: spread 0.012, loss 1.0), hence a fraction; with a fraction the pair term
    (two independently augmented draws of a view) still shrinks the descriptors, so an A-trained recogniser wants
    a low :attr:`pair_weight` (0.1: docs/synda.md). The database stays built from the unaugmented patches. Needs
    the object masks of this version's training chunks."""
    input: Literal["depth", "rgb"] = "depth"
    """What the network reads: ``depth``, the normalised depth patch (1 channel, every shipped recogniser), or
    ``rgb``, a colour patch in [-1, 1] (3 channels): SynDA's A-trained colour baseline (thesis ch. 5, Table 5.2's
    "A(synthetic)" row for colour). With ``rgb`` every training patch is rendered anew each step by SynDA's colour
    augmentation A (``synda_preset('cpu', 'rgb').augment``, the ranges the rgb generator is trained on: Blinn-Phong
    shading of the view's normals under a random light, procedural hue/saturation textures, image or noise
    backgrounds, polygon occluders, blur) from the normals of its depth patch and its object mask, so both draws of
    a view (the pair) are two renders; the database holds one A render per view and draw with a fixed seed
    (:func:`database_seed`), and evaluation reads the scan's colour image (``recog eval`` on a colour test set,
    ``realgap synda testset``). Train it on the ``clean`` variant (the normals of noisy depth are noise)."""
    seed: int = 0
    """Seed of the initial weights and of the mining."""
    device: str = "cpu"
    """torch device ('cpu', 'cuda')."""

    def validate(self) -> "TrainConfig":
        from recog.net import NETWORKS
        if self.network not in NETWORKS:
            raise ConfigError(f"unknown network {self.network!r}; choose one of {', '.join(NETWORKS)}")
        check_fields(self)
        if self.input == "rgb" and self.synda_augment > 0:
            raise ConfigError("--synda-augment is SynDA's depth augmentation; with --input rgb every patch is "
                              "already rendered by its colour augmentation (leave --synda-augment at 0)")
        return self


TRAIN_PRESETS = {
    "cpu": TrainConfig(),
    "gpu": TrainConfig(network="deeper", iterations=20000, batch=256, device="cuda"),
}
"""``cpu``: LeNet, 3000 steps of 64 triplets (about 5 minutes on 2 cores); ``gpu``: the deeper
network, 20000 steps of 256 triplets."""


@dataclass
class TrainLog:
    """What training recorded."""

    steps: list[dict] = field(default_factory=list)
    """Every ``log_every`` steps: step, loss, triplet, pair, active fraction, descriptor spread."""
    seconds: float = 0.0
    resumed_from: int = 0
    """Step the run continued from (0 = a fresh start)."""
    warnings: list[str] = field(default_factory=list)


class TripletMiner:
    """Draws (anchor, positive, negative, pair) index tuples from :class:`TrainingData` by pose.

    A fraction ``hard`` of the negatives are *hard*: of the anchor's own object, one of the
    ``HARD_K`` poses nearest to the anchor beyond the positive; of another object, one of its
    ``HARD_K`` views whose pose is nearest to the anchor's (look-alike objects seen the same way,
    the confusion that matters). The rest are drawn uniformly (same object: any pose farther
    than the positive)."""

    HARD_K = 8

    def __init__(self, data: TrainingData, symmetries: list[dict], hard: float = 0.5):
        self.hard = float(hard)
        from recog.symmetry import sym_angles
        self.data = data
        self.by_obj = [np.nonzero(data.obj == k)[0] for k in range(len(data.names))]
        if any(len(ix) < 3 for ix in self.by_obj):
            bad = [data.names[k] for k, ix in enumerate(self.by_obj) if len(ix) < 3]
            raise ConfigError(f"too few usable training views of {', '.join(bad)} (is the object visible?)")
        self.angles = []      # per object: (n, n) symmetry-aware angles between its views, radians
        self.nearest = []     # per object: (n, K) its other views, nearest pose first (local indices)
        for k, ix in enumerate(self.by_obj):
            A = sym_angles(data.R_local[ix], data.R_local[ix], symmetries[k]).astype(np.float32)
            np.fill_diagonal(A, np.inf)
            self.nearest.append(np.argsort(A, axis=1)[:, :self.HARD_K + 2])
            np.fill_diagonal(A, 0.0)
            self.angles.append(A)
        # per (object, other object): for each view of the first, the views of the second with the
        # nearest poses (plain geodesic angle): the hard negatives of look-alike objects
        self.cross = {}
        for k, ix in enumerate(self.by_obj):
            for j, jx in enumerate(self.by_obj):
                if j != k:
                    C = sym_angles(data.R_local[ix], data.R_local[jx], None)
                    self.cross[k, j] = np.argsort(C, axis=1)[:, :self.HARD_K]

    def sample(self, rng: np.random.Generator, batch: int, same_object_negatives: float):
        """Index arrays into the data (view rows) and draw columns:
        (anchor, a_draw, positive, p_draw, negative, n_draw, pair_draw, same_object, angle_rad)."""
        n_obj = len(self.by_obj)
        D = self.data.patches.shape[1]
        objs = rng.integers(0, n_obj, batch)
        a, p, ng = np.zeros(batch, np.int64), np.zeros(batch, np.int64), np.zeros(batch, np.int64)
        same, ang = np.zeros(batch, bool), np.zeros(batch, np.float32)
        for i, o in enumerate(objs):
            ix = self.by_obj[o]
            la = int(rng.integers(len(ix)))
            lp = int(self.nearest[o][la, rng.integers(2)])
            a[i], p[i] = ix[la], ix[lp]
            hard = rng.random() < self.hard
            if n_obj == 1 or rng.random() < same_object_negatives:
                if hard:     # one of the next-nearest poses beyond the positive
                    cand = [c for c in self.nearest[o][la] if self.angles[o][la, c] > self.angles[o][la, lp]]
                else:
                    cand = np.nonzero(self.angles[o][la] > self.angles[o][la, lp])[0]
                ln = int(rng.choice(cand)) if len(cand) else int(rng.integers(len(ix)))
                ng[i], same[i], ang[i] = ix[ln], True, self.angles[o][la, ln]
            else:
                o2 = int((o + rng.integers(1, n_obj)) % n_obj)
                if hard:     # another object seen from (nearly) the same pose
                    ng[i] = self.by_obj[o2][int(rng.choice(self.cross[o, o2][la]))]
                else:
                    ng[i] = self.by_obj[o2][rng.integers(len(self.by_obj[o2]))]
        a_draw = rng.integers(0, D, batch)
        pair_draw = (a_draw + rng.integers(1, D, batch)) % D
        return (a, a_draw, p, rng.integers(0, D, batch), ng, rng.integers(0, D, batch), pair_draw, same, ang)


def train_network(data: TrainingData, symmetries: list[dict], config: TrainConfig, size: int,
                  checkpoint: str | Path | None = None, progress: bool = True,
                  log: Callable[[str], None] | None = None):
    """Train the descriptor network; returns (network in eval mode, :class:`TrainLog`).
    ``checkpoint``: the resumable checkpoint file (continued from when it exists)."""
    import torch

    from recog.loss import dynamic_margin, pair_loss, triplet_loss
    from recog.net import INPUT_CHANNELS, make_network
    config.validate()
    device = torch.device(config.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' requested but no GPU is available here (use --preset cpu)")
    torch.manual_seed(config.seed)
    net = make_network(config.network, size, config.descriptor, INPUT_CHANNELS[config.input]).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    rng = np.random.default_rng(config.seed)
    miner = TripletMiner(data, symmetries, config.hard_negatives)
    patches = torch.from_numpy(np.ascontiguousarray(data.patches))       # (N, D, S, S) float16
    tlog = TrainLog()
    state = TrainingState(checkpoint, {"net": net, "opt": opt}, rng, "training checkpoint", map_location=device,
                          settings=settings_of(config))
    resumed = state.resume(log, config.iterations)
    if resumed is not None:
        tlog.resumed_from, tlog.steps = resumed

    augment = _synda_augmenter(data, size) if config.synda_augment > 0 else None
    render = colour_renderer(data, size) if config.input == "rgb" else None

    def step_fn(step: int) -> dict:
        a, ad, p, pd, n, nd, qd, same, ang = miner.sample(rng, config.batch, config.same_object_negatives)
        x = torch.cat([patches[a, ad], patches[p, pd], patches[n, nd], patches[a, qd]]).float().unsqueeze(1)
        if augment is not None:
            x = augment(x, np.concatenate([a, p, n, a]), int(rng.integers(0, 2 ** 62)), config.synda_augment)
        if render is not None:
            x = render(x, np.concatenate([a, p, n, a]), int(rng.integers(0, 2 ** 62)))
        f = net(x.to(device))
        B = config.batch
        fb, fp, fn, fq = f[:B], f[B:2 * B], f[2 * B:3 * B], f[3 * B:]
        m = dynamic_margin(torch.from_numpy(same).to(device), torch.from_numpy(ang).to(device), config.class_margin)
        lt = triplet_loss(fb, fp, fn, m)
        lp = pair_loss(fb, fq)
        loss = lt.mean() + config.pair_weight * lp.mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        with torch.no_grad():
            return {"loss": float(loss), "triplet": float(lt.mean()), "pair": float(lp.mean()),
                    "active": float((lt > 0).float().mean()), "spread": float(fb.std(0).mean())}

    net.train()
    tlog.seconds = run_steps(step_fn, config.iterations, start=tlog.resumed_from, history=tlog.steps,
                             log_every=config.log_every, state=state, checkpoint_every=config.checkpoint_every,
                             progress=progress, desc=f"training {config.network}",
                             postfix=lambda r: f"loss {r['loss']:.3f} active {r['active']:.2f} spread {r['spread']:.3f}")
    if tlog.steps and tlog.steps[-1]["spread"] < 1e-3:
        tlog.warnings.append(f"descriptor collapse: the descriptors' spread is {tlog.steps[-1]['spread']:.2g} "
                             f"(every input maps to nearly one point)")
    net.eval()
    return net, tlog


def _synda_augmenter(data: TrainingData, size: int):
    """``(x (4B, 1, S, S) patches, view rows (4B,), seed, fraction) -> x`` with a random ``fraction`` of its
    patches replaced by A(patch): SynDA's depth augmentation A with the views' object masks
    (``TrainConfig.synda_augment``); ConfigError when the chunks hold no masks."""
    import torch

    from recog.synda.augment import Augmenter, select_params
    from recog.synda.config import synda_preset
    if data.mask is None:
        raise ConfigError("--synda-augment needs the object masks of the training chunks, which chunks made by an "
                          "older version lack (delete the model's data folder to simulate them again)")
    aug = Augmenter(synda_preset("cpu", "depth").augment, "depth", size)
    masks = torch.from_numpy(data.mask)

    def run(x, rows, seed: int, fraction: float = 1.0):
        params = aug.draw(len(rows), seed)
        pick = torch.nonzero(torch.rand(len(rows), generator=torch.Generator().manual_seed(seed + 1)) < fraction)
        pick = pick.flatten()
        if len(pick) == 0:
            return x
        m = masks[torch.from_numpy(rows)[pick]].to(device=x.device, dtype=torch.float32)[:, None]
        y = x.clone()      # A acts on each sample alone: the picked ones come out as in a full-batch apply (to float rounding)
        y[pick.to(x.device)] = aug.apply({"depth": x[pick.to(x.device)], "mask": m}, select_params(params, pick))["input"]
        return y

    return run


def _view_masks(data: TrainingData, what: str):
    import torch
    if data.mask is None:
        raise ConfigError(f"{what} needs the object masks of the training chunks, which chunks made by an older "
                          f"version lack (delete the model's data folder to simulate them again)")
    return torch.from_numpy(data.mask)


def colour_renderer(data: TrainingData, size: int):
    """``(x (B, 1, S, S) normalised depth patches, view rows (B,), seed) -> (B, 3, S, S)`` colour patches in [-1, 1]:
    SynDA's colour augmentation A (``synda_preset('cpu', 'rgb').augment``) of each patch's normals
    (:func:`recog.synda.data.normals_from_depth`) with its view's object mask, its random parameters drawn from
    ``seed`` (the same seed gives the same images: training replays on resume). ``TrainConfig.input == 'rgb'``;
    ConfigError when the chunks hold no masks."""
    import torch

    from recog.synda.augment import Augmenter
    from recog.synda.config import synda_preset
    from recog.synda.data import normals_from_depth
    masks = _view_masks(data, "--input rgb")
    aug = Augmenter(synda_preset("cpu", "rgb").augment, "rgb", size)

    def run(x, rows, seed: int):
        m = masks[torch.from_numpy(np.asarray(rows))].to(device=x.device, dtype=torch.float32)[:, None]
        return aug.apply({"normals": normals_from_depth(x.float()), "mask": m}, aug.draw(len(rows), seed))["input"]

    return run


def database_seed(config: TrainConfig) -> int:
    """The seed of the A renders a colour recogniser's database is built from (fixed by ``config.seed``, apart from
    the training steps' draws)."""
    import zlib
    return zlib.crc32(f"recog-colour-database/{config.seed}".encode()) & 0x7FFFFFFF


def render_colour_views(data: TrainingData, size: int, seed: int, batch: int = 256) -> np.ndarray:
    """(N, D, 3, S, S) float32: one A render (:func:`colour_renderer`) of every view and draw of ``data``, in
    batches of ``batch`` patches, batch ``i`` drawn with ``seed + i`` (deterministic for a seed and batch)."""
    import torch
    N, D, S = data.patches.shape[0], data.patches.shape[1], data.patches.shape[-1]
    render = colour_renderer(data, size)
    flat = data.patches.reshape(N * D, S, S)
    rows = np.repeat(np.arange(N), D)
    out = np.zeros((N * D, 3, S, S), np.float32)
    for i, s in enumerate(range(0, N * D, batch)):
        x = torch.from_numpy(flat[s:s + batch].astype(np.float32))[:, None]
        with torch.no_grad():
            out[s:s + batch] = render(x, rows[s:s + batch], seed + i).numpy()
    return out.reshape(N, D, 3, S, S)
