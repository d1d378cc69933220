"""Descriptor networks: a patch (C, S, S) -> a descriptor (d,), in a registry by name.

``lenet`` is the network of the thesis (section 3.4.3, after Wohlhart & Lepetit 2015): two 5x5
convolutions, each followed by ReLU and 2x2 max-pooling, then two fully connected layers, the
last one giving the descriptor (d = 64). ``deeper`` adds a third conv block and batch norm
(measured against ``lenet`` by ``benchmarks/bench_recog.py``).

``channels`` is the input's channel count C: 1 for a normalised depth patch (the default, every
shipped recogniser), 3 for a colour patch in [-1, 1] (``recog train --input rgb``, SynDA's A-trained
colour baseline). Only the first convolution's weight shape depends on it, so a 1-channel network is
built (and its random initialisation drawn) exactly as before the option existed. :func:`check_input`
is the one-line error for a patch batch of another channel count than the network's.
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["NETWORKS", "make_network", "LeNet", "Deeper", "INPUT_CHANNELS", "check_input"]

INPUT_CHANNELS = {"depth": 1, "rgb": 3}
"""Input kind (``TrainConfig.input``) -> channels of its patches."""


class LeNet(nn.Module):
    """conv5x5(16) - ReLU - pool2 - conv5x5(32) - ReLU - pool2 - fc(256) - ReLU - fc(d)."""

    def __init__(self, size: int = 64, descriptor: int = 64, channels: int = 1):
        super().__init__()
        self.channels = int(channels)
        self.features = nn.Sequential(
            nn.Conv2d(self.channels, 16, 5), nn.ReLU(), nn.MaxPool2d(2),
            nn.Conv2d(16, 32, 5), nn.ReLU(), nn.MaxPool2d(2))
        n = ((size - 4) // 2 - 4) // 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(32 * n * n, 256), nn.ReLU(), nn.Linear(256, descriptor))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, S, S) float patches in [-1, 1] -> (B, d) descriptors."""
        return self.head(self.features(x))


class Deeper(nn.Module):
    """Three conv blocks (3x3, batch norm, ReLU, pool) - fc(256) - fc(d)."""

    def __init__(self, size: int = 64, descriptor: int = 64, channels: int = 1):
        super().__init__()
        self.channels = int(channels)
        layers, c = [], self.channels
        for k in (32, 64, 96):
            layers += [nn.Conv2d(c, k, 3, padding=1), nn.BatchNorm2d(k), nn.ReLU(),
                       nn.Conv2d(k, k, 3, padding=1), nn.BatchNorm2d(k), nn.ReLU(), nn.MaxPool2d(2)]
            c = k
        self.features = nn.Sequential(*layers)
        n = size // 8
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * n * n, 256), nn.ReLU(), nn.Linear(256, descriptor))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, S, S) float patches in [-1, 1] -> (B, d) descriptors."""
        return self.head(self.features(x))


NETWORKS = {"lenet": LeNet, "deeper": Deeper}


def make_network(name: str, size: int = 64, descriptor: int = 64, channels: int = 1) -> nn.Module:
    """The network ``name`` for ``size`` px patches of ``channels`` channels giving ``descriptor``-d descriptors."""
    from data_tools.errors import ConfigError
    if name not in NETWORKS:
        raise ConfigError(f"unknown network {name!r}; choose one of {', '.join(NETWORKS)}")
    if int(channels) not in INPUT_CHANNELS.values():
        raise ConfigError(f"a descriptor network reads 1 (depth) or 3 (colour) channels, got {channels}")
    return NETWORKS[name](size, descriptor, int(channels))


def _kind(c: int) -> str:
    return {1: "1-channel depth", 3: "3-channel colour"}.get(int(c), f"{c}-channel")


def check_input(net: nn.Module, x: torch.Tensor, where: str = "the recogniser") -> None:
    """One-line :class:`~data_tools.errors.ConfigError` unless ``x`` is a (B, C, S, S) batch with the
    network's channel count C (a depth patch given to a colour recogniser, or the reverse)."""
    from data_tools.errors import ConfigError
    want = int(getattr(net, "channels", 1))
    if x.dim() != 4 or x.shape[1] != want:
        got = _kind(x.shape[1]) + " patches" if x.dim() == 4 else f"an array of shape {tuple(x.shape)}"
        raise ConfigError(f"{where} reads {_kind(want)} patches (B, {want}, S, S), got {got}"
                          + (" (a colour recogniser needs the scan's colour image)" if want == 3 else ""))
