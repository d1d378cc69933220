"""The training data of the neural memory behind one batch-source interface: 2D walks on images
(:class:`Walks2D`, over :mod:`slam.neural.data2d`) and 3D worlds of simulated rooms
(:class:`slam.neural.data3d.WorldBank`). A source has ``wedge`` (q, q) bool, the view field of an observation,
``sample(rng, batch, steps)`` -> (images (B, T, C, ...) float32, cells (B, T, r, H * W) int64 or None,
allocentric poses (B, T, 3) int64, poses in the source's own form) and ``exact(poses)`` -> (T, 3) exact
allocentric poses (row, col in cells, heading in units of 2 pi / r); :func:`batch_tensors` turns a sample into
tensors, :func:`batch_source` makes the source of a training configuration.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["Walks2D", "batch_source", "batch_tensors", "worlds_3d"]


class Walks2D:
    """2D batch source: ``sample`` draws training walks of ``agent`` on environments of side ``size``
    (:func:`slam.neural.data2d.make_batch`, split ``train``); poses are integers, their own exact poses."""

    def __init__(self, agent: str, size: int):
        from slam.neural.data2d import AGENTS, view_mask
        self.agent, self.size = AGENTS[agent], int(size)
        self.wedge = view_mask(self.agent).astype(bool)

    def sample(self, rng: np.random.Generator, batch: int, steps: int):
        from slam.neural.data2d import make_batch
        _, obs, _, allo = make_batch(rng, batch, self.agent, steps, self.size)
        return obs.astype(np.float32), None, allo, allo

    def exact(self, poses: np.ndarray) -> np.ndarray:
        return np.asarray(poses, np.float64)


def batch_tensors(source, rng: np.random.Generator, batch: int, steps: int, dev):
    """One batch of ``source`` as tensors on ``dev``: (images (B, T, C, H, W) float32, cells (B, T, r, H*W) int64 or
    None, allocentric poses (B, T, 3) int64, exact poses (B, T, 3) float32)."""
    import torch
    imgs, cells, allo, poses = source.sample(rng, batch, steps)
    exact = np.stack([source.exact(p) for p in poses]).astype(np.float32)
    return (torch.from_numpy(np.asarray(imgs, np.float32)).to(dev),
            None if cells is None else torch.from_numpy(cells).to(dev),
            torch.from_numpy(np.asarray(allo)).to(dev), torch.from_numpy(exact).to(dev))


def worlds_3d(cfg, simulate=None, progress: bool = True, log=None, split: str = "train"):
    """The prepared 3D worlds of ``split`` (:class:`slam.neural.data3d.WorldBank`) of a training configuration:
    simulated on first use into ``cfg.worlds_dir`` (default :func:`slam.neural.data3d.default_worlds_dir`),
    cached as .npz."""
    from slam.neural.data3d import WorldBank, build_worlds, cache_name, default_worlds_dir, load_sequence_arrays
    root = Path(cfg.worlds_dir) if cfg.worlds_dir else default_worlds_dir(cfg.world)
    seqs = build_worlds(root, cfg.world, split, simulate=simulate, log=log)
    arrays = [load_sequence_arrays(s, cfg.world, s / cache_name(cfg.world), progress=progress) for s in seqs]
    return WorldBank(arrays, cfg.world, seqs)


def batch_source(cfg, simulate=None, progress: bool = True, log=None):
    """The training batch source of a :class:`slam.neural.config.NeuralTrainConfig`: 3D its world's training rooms
    (:func:`worlds_3d`), 2D walks of its agent on ``image``-pixel environments."""
    if cfg.mode == "3d":
        return worlds_3d(cfg, simulate, progress, log)
    return Walks2D(cfg.agent, cfg.image)
