"""The configuration tree of the neural memory, free of torch (the ``neural`` backend and the CLI read it without
loading a network): the model's sizes (:class:`MemoryConfig`), the 3D data (:class:`World3DConfig`), the training
(:class:`NeuralTrainConfig`, which holds the other two and the decoder refinement's :class:`RefineConfig`), the
later stages (:class:`HallucinationConfig`, :class:`TopviewConfig`) and the named presets.

Each dataclass has one ``validate()``: the ranges and choices written in the field annotations
(``Annotated[int, Range(1)]``, ``Literal[...]``, checked by :func:`data_tools.config.check_fields`, which the
command-line flags generated from these classes read too) and the checks between fields.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Annotated, Literal

import numpy as np

from data_tools.config import Range, check_fields
from data_tools.errors import ConfigError

__all__ = ["MemoryConfig", "World3DConfig", "RefineConfig", "HallucinationConfig", "TopviewConfig",
           "NeuralTrainConfig", "TRAIN_PRESETS", "TRAIN_PRESETS_3D", "PRESETS", "IMAGE_CHANNELS", "POSE_SCORES",
           "derived_model", "DERIVED_MODEL_FIELDS", "OCC_LR"]

Positive = Annotated[int, Range(1)]
NonNegative = Annotated[int, Range(0)]
Rate = Annotated[float, Range(0, open_lo=True)]

POSE_SCORES = ("overlap", "sum")
"""How the localisation scores a pose against the memory (:meth:`slam.neural.memory.NeuralMemory.forward`'s
``score``); checked by the ``neural`` backend's configuration before a model is loaded."""
IMAGE_CHANNELS = {"2d": 3, "3d": 4}
"""Channels C of a mode's observations: 2D RGB views, 3D RGB-D images."""
OCC_LR = 5e-2
"""Learning rate of the occupancy LSTM (with ``occ_weight``; constant): its 16 weights must move far - forget gate
open, input gate saturated - which the memory's 2e-4 does not do in a CPU budget (tiny 2D model, 400 memory steps:
L_occ 0.86 -> 0.20 at 1e-2, -> 0.004-0.04 at 5e-2)."""


@dataclass
class MemoryConfig:
    """Sizes of the model (saved with the weights, as the training configuration's ``model``)."""

    channels: Positive = 3
    """Image channels C (3 RGB, 4 RGB-D)."""
    features: Positive = 16
    """Feature size n of the memory cells."""
    view: Positive = 15
    """Side q of the egocentric grid (odd)."""
    memory: Positive = 71
    """Side U of the allocentric memory (odd): must hold every position the agent reaches from its start."""
    width: Positive = 32
    """Channels inside the encoder/decoder ResNets."""
    rotations: Positive = 4
    """Headings r (quarter turns)."""
    search: Positive = 16
    """Localisation searches positions within +-search cells of the previous estimate."""
    input: Literal["grid", "image"] = "grid"
    """``grid``: observations are egocentric grids already (2D, B x T x C x q x q); ``image``: they are
    images (3D, B x T x C x H x W) whose per-pixel encoder features are ground-projected into the grid
    by the pixels' cell indices (:func:`slam.neural.geometry3d.project_max`)."""
    image_size: tuple = (0, 0)
    """3D: (H, W) of the decoded images, pixels (the decoder back-projects the culled window)."""
    occupancy: Literal["sigmoid", "affine"] = "sigmoid"
    """How the occupancy LSTM's hidden state h in (-1, 1) becomes the mask b: ``sigmoid`` (b = sigmoid(h), in
    (0.27, 0.73): models trained with ``occ_weight`` 0, whose occupancy LSTM gets no gradient) or ``affine``
    (b = (h + 1) / 2, in (0, 1): trained to the observed cells ``seen`` by L_occ,
    :attr:`NeuralTrainConfig.occ_weight`)."""

    def validate(self) -> "MemoryConfig":
        """Raises ConfigError naming the first field out of range (the model's sizes and choices, checked once)."""
        check_fields(self)
        if self.view % 2 == 0 or self.memory % 2 == 0:
            raise ConfigError(f"view and memory must be odd, got {self.view}, {self.memory}")
        if self.input == "image" and (len(self.image_size) != 2 or min(self.image_size) < 1):
            raise ConfigError(f"an image-input memory needs image_size (H, W), got {self.image_size}")
        return self


@dataclass
class World3DConfig:
    """Grid, image and data settings of the 3D memory (saved with the weights)."""

    cell_m: Rate = 0.15
    """Side of a memory cell, metres."""
    view: Annotated[int, Range(5)] = 33
    """Side q of the egocentric grid, cells (odd): the view reaches (q // 2) x cell_m ahead."""
    max_range_m: Rate = 2.4
    """Depth beyond this is not projected (and the depth channel saturates), metres."""
    image_h: Positive = 30
    """Height of the network's images, pixels."""
    image_w: Positive = 40
    """Width of the network's images, pixels."""
    rotations: Positive = 12
    """Headings r (360 / r degrees apart)."""
    rooms: Positive = 12
    """Training rooms (sequences), seeds 0 .. rooms - 1."""
    test_rooms: Positive = 3
    """Test rooms, seeds TEST_SEED0 ..."""
    frames: Positive = 200
    """Frames per room sequence (30 fps)."""
    stride_min: Positive = 5
    """Fewest frames between two steps of a training sample."""
    stride_max: Positive = 15
    """Most frames between two steps of a training sample."""

    def validate(self) -> "World3DConfig":
        check_fields(self)
        if self.view % 2 == 0:
            raise ConfigError(f"view must be odd, got {self.view}")
        if not self.stride_min <= self.stride_max:
            raise ConfigError(f"need stride_min <= stride_max, got {self.stride_min} > {self.stride_max}")
        return self


@dataclass
class RefineConfig:
    """How the recall decoder is refined (:mod:`slam.neural.refine`; saved in the model's neural.json ``info``)."""

    rooms: Positive = 48
    """3D: training rooms whose views form the pool (seeds 0 .. rooms - 1; the memory trained on the first 12)."""
    pool_batches: Positive = 450
    """Batches of ``batch`` samples memorised once for the pool (3600 samples of 10 views by default)."""
    steps: NonNegative = 1500
    """Optimiser steps (3D, in an experiment with this pool size: the test rooms' SSIM was flat from 500 to 1500
    steps); 0 = no refinement (``neural train``'s default)."""
    batch: Positive = 32
    """(memory, pose) pairs per step."""
    lr: Rate = 2e-4
    """Initial learning rate, falling linearly to a tenth over the last 40 % of the steps."""
    ssim_weight: Annotated[float, Range(0)] = 1.0
    """Weight of the (1 - SSIM) / 2 term (kornia's ``ssim_loss``) beside the L1; 0 = the thesis' L1 alone."""
    seed: int = 0
    """Seeds the pool and the pairs drawn from it (``neural train``: the training's seed)."""
    checkpoint_every: Positive = 250
    """Steps between two checkpoints."""

    def validate(self) -> "RefineConfig":
        check_fields(self)
        return self


@dataclass
class HallucinationConfig:
    """How the occupancy mask and the hallucination module are retrained (:mod:`slam.neural.refine_hallucination`;
    saved in the model's neural.json)."""

    occ_steps: NonNegative = 400
    """Steps of stage 1 (L_occ; measured on planar_3d, batch 8: L_occ 0.385 after 25 steps, 0.009 after 250)."""
    steps: Positive = 600
    """Steps of stage 2 (the hallucination GAN; the 3D ``cpu-long`` memory training gives it 400)."""
    lr: Rate = 2e-4
    """Stage 2's initial learning rate (thesis: 2e-4), falling linearly to a tenth."""
    seed: int = 0
    """Seeds the batches and the re-initialised weights."""
    checkpoint_every: Positive = 100
    """Steps between two checkpoints."""
    topview_steps: NonNegative = 300
    """3D: steps of the top-view decoder's retraining afterwards (it reads the occupancy); 0 = none."""

    def validate(self) -> "HallucinationConfig":
        check_fields(self)
        return self


@dataclass
class TopviewConfig:
    """How ``neural train-topview`` trains a 3D model's top-view decoder (:mod:`slam.neural.topview`; batch,
    sample length, learning rate and seed are the model's training's)."""

    steps: Positive = 300
    """Optimiser steps."""

    def validate(self) -> "TopviewConfig":
        check_fields(self)
        return self


@dataclass
class NeuralTrainConfig:
    """How the memory is trained (saved with the weights; ``model`` is the trained network's configuration)."""

    mode: Literal["2d", "3d"] = "2d"
    """2d (agents on images) or 3d (RGB-D sequences)."""
    agent: Literal["square", "front"] = "front"
    """2D agent: square (360 deg view, translates) or front (180 deg view, turns by 90 deg)."""
    image: Positive = 43
    """Side of the 2D environments, pixels."""
    steps: Annotated[int, Range(2)] = 10
    """Observations per training sequence."""
    observe: Positive = 5
    """Hallucination: the first ``observe`` steps are memorised, the rest are to be predicted."""
    batch: Positive = 8
    """Sequences per step."""
    iterations: Positive = 2200
    """Optimiser steps in all (pretraining included)."""
    pretrain_steps: NonNegative = 300
    """Steps of the single-view auto-encoder pre-training (thesis phase 1)."""
    teacher_steps: NonNegative = 600
    """Steps (after pretraining) over which teacher-forced registration fades out."""
    hallucination_from: NonNegative = 1500
    """Step at which the hallucination module joins."""
    lr: Rate = 2e-4
    """Base learning rate (thesis: "initialized at 2e-4")."""
    lr_decay_from: NonNegative = 0
    """From this step on the learning rate falls linearly to ``lr_final`` x ``lr`` at the last step (all three
    optimisers); 0 = constant."""
    lr_final: Annotated[float, Range(0, 1, open_lo=True)] = 0.1
    """The learning rate at the last step over ``lr`` (with ``lr_decay_from``)."""
    loc_weight: Rate = 1.0
    """Weight of L_loc against L_anam (weight 1) in the memory phases. L_loc's gradient on the shared encoder
    dwarfs L_anam's, so at 1 the encoder serves localisation alone; the 2D ``cpu-long`` preset uses 0.01
    (docs/not_kept.md has the sweep)."""
    occ_weight: Annotated[float, Range(0)] = 0.0
    """Weight of L_occ (BCE of the occupancy mask b against the observed cells ``seen``, memory phases); > 0 makes
    the model's occupancy mask ``affine`` (:attr:`MemoryConfig.occupancy`). 0: no loss reaches the occupancy LSTM
    (front_2d; planar_3d's mask was trained afterwards by ``neural refine-hallucination``). 1 in the 2D ``gpu``
    preset; 0 in the others, which reproduce the shipped models."""
    lstm_forget_bias: float = 0.0
    """If not 0: the forget-gate slice of both memory LSTMs' input biases is set to this value (their other
    weights keep PyTorch's LSTM init, uniform +-1/sqrt(n): the thesis' N(0, 0.02) is for the convolutions).
    Every memory cell is updated at every step, most with a zero input (out of view): with a forget bias near 0
    a cell keeps about half of itself per step until the gate learns otherwise; 1 (Jozefowicz et al. 2015's
    advice for LSTMs) starts at about 73 %. 0 = untouched."""
    checkpoint_every: Positive = 200
    """Steps between two checkpoints (MODEL/checkpoint.pt)."""
    log_every: Positive = 50
    """Steps between two records of the loss log (running means)."""
    seed: int = 0
    """Seeds the batches, the weights and the refinement."""
    device: str = "cpu"
    """Torch device (cpu, cuda)."""
    topview_steps: NonNegative = 300
    """3D mode: steps of the top-view decoder trained after the memory, the memory frozen
    (:mod:`slam.neural.topview`; the ``slam run --backend neural`` snapshot's topview.png); 0 = none."""
    model: MemoryConfig = field(default_factory=lambda: MemoryConfig(features=8, width=16))
    """The network: ``features`` (the memory's n; the thesis uses 16-32, 8 keeps a CPU step under a second),
    ``width`` (channels of the encoder/decoder ResNets) and ``occupancy`` are chosen; the other sizes follow from
    the data (mode, agent, image, world, steps: :func:`derived_model`) and may be left at their defaults."""
    refine: RefineConfig = field(default_factory=lambda: RefineConfig(steps=0))
    """The decoder refinement after the memory phases (:mod:`slam.neural.refine`: the recall decoder retrained with
    an SSIM term, the memory frozen; 3D on ``refine.rooms`` rooms, simulated on first use); ``steps`` 0 = none. Its
    seed is the training's."""
    world: World3DConfig = field(default_factory=World3DConfig)
    """3D mode: grid, images and simulated rooms."""
    worlds_dir: str = ""
    """3D mode: folder of the simulated room sequences (made on first use; default ~/.cache/realgap/neural_worlds)."""

    def validate(self) -> "NeuralTrainConfig":
        """The fields' ranges and choices, the nested configurations, ``observe`` < ``steps`` and a ``model`` whose
        data-given sizes are either left at their defaults or those of the data (:func:`derived_model`)."""
        check_fields(self)
        if not self.observe < self.steps:
            raise ConfigError(f"observe must be in 1..steps-1, got {self.observe}")
        self.world.validate()
        self.refine.validate()
        self.model.validate()
        derived, unset = derived_model(self), MemoryConfig()
        for k in DERIVED_MODEL_FIELDS:
            v = getattr(self.model, k)
            if tuple(np.atleast_1d(v)) not in (tuple(np.atleast_1d(getattr(derived, k))),
                                               tuple(np.atleast_1d(getattr(unset, k)))):
                raise ConfigError(f"model.{k} = {v!r} does not fit the data ({self.mode}: "
                                  f"{getattr(derived, k)!r}); leave it out")
        return self

    def resolved(self) -> "NeuralTrainConfig":
        """A copy whose ``model`` has every size the data gives (:func:`derived_model`): what is trained and saved."""
        return replace(self, model=derived_model(self))


DERIVED_MODEL_FIELDS = ("channels", "view", "memory", "search", "rotations", "input", "image_size")
"""The :class:`MemoryConfig` fields the training data fixes."""


def derived_model(cfg: NeuralTrainConfig) -> MemoryConfig:
    """``cfg.model`` with the sizes the data fixes: 3D the image channels, the world's grid and headings, a memory
    that holds the farthest a sample of ``steps`` frames reaches at the largest stride (0.45 m/s at 30 fps) and a
    search of 4 cells; 2D the agent's view and a memory holding every position of an ``image``-pixel environment
    from any start. An ``occ_weight`` > 0 makes the mask ``affine``."""
    from slam.neural.data2d import AGENTS
    occ = "affine" if cfg.occ_weight > 0 else cfg.model.occupancy
    if cfg.mode == "3d":
        w = cfg.world
        reach = int(np.ceil(0.45 * w.stride_max / 30.0 * (cfg.steps - 1) / w.cell_m)) + 4
        return replace(cfg.model, channels=IMAGE_CHANNELS["3d"], view=w.view, memory=w.view + 2 * reach,
                       rotations=w.rotations, search=4, input="image", image_size=(w.image_h, w.image_w),
                       occupancy=occ)
    q = AGENTS[cfg.agent].view
    reach = cfg.image - q                  # the largest offset from the start the agent can reach
    U = 2 * reach + q
    return replace(cfg.model, channels=IMAGE_CHANNELS["2d"], view=q, memory=U, rotations=4,
                   search=min(3 * q // 4 + 5, (U - q) // 2), input="grid", image_size=(0, 0), occupancy=occ)


_CPU_2D = NeuralTrainConfig(lr_decay_from=1500, lstm_forget_bias=1.0, refine=RefineConfig(steps=5000, pool_batches=900))
TRAIN_PRESETS = {
    "cpu": _CPU_2D,
    "cpu-long": replace(_CPU_2D, model=MemoryConfig(features=16, width=32), loc_weight=0.01),
    "gpu": NeuralTrainConfig(batch=32, iterations=30000, pretrain_steps=2000, teacher_steps=5000,
                             hallucination_from=15000, model=MemoryConfig(features=32, width=64), device="cuda",
                             lr_decay_from=20000, lstm_forget_bias=1.0,
                             refine=RefineConfig(steps=10000, pool_batches=2000), loc_weight=0.01, occ_weight=1.0),
}
"""2D presets. ``cpu``: the 30-minute CPU recipe (with decoder refinement); ``cpu-long``: the shipped front_2d
recipe (features 16, width 32, L_loc weighted 0.01); ``gpu``: a larger configuration, never run. Times, and what
each choice measured: docs/neural.md, "Training presets"."""

_CPU_3D = NeuralTrainConfig(mode="3d", batch=8, iterations=1100, pretrain_steps=150, teacher_steps=350,
                            hallucination_from=700, model=MemoryConfig(features=16, width=16), topview_steps=150)
TRAIN_PRESETS_3D = {
    "cpu": _CPU_3D,
    "cpu-long": replace(_CPU_3D, lr_decay_from=700, refine=RefineConfig(steps=1500, rooms=48),
                        world=World3DConfig(view=49, max_range_m=3.6)),
    "gpu": NeuralTrainConfig(mode="3d", batch=32, iterations=20000, pretrain_steps=2000, teacher_steps=4000,
                             hallucination_from=10000, model=MemoryConfig(features=32, width=64), device="cuda",
                             topview_steps=2000, refine=RefineConfig(steps=3000, rooms=128),
                             world=World3DConfig(rooms=64, test_rooms=8, frames=300)),
}
"""3D (``--mode 3d``) presets. ``cpu``: <= 30 min on 2 cores after the 12 training rooms are simulated once;
``cpu-long``: the memory of the shipped planar_3d (a 49-cell grid to 3.6 m, decoder refined on 48 rooms; its mask
trained afterwards by ``neural refine-hallucination``); ``gpu``: a larger configuration. Times and measurements:
docs/neural.md, "Training presets"."""

PRESETS = {"2d": TRAIN_PRESETS, "3d": TRAIN_PRESETS_3D}
"""The presets by mode (``neural train --mode M --preset NAME``)."""
