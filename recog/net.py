"""Descriptor networks: a depth patch (1, S, S) -> a descriptor (d,), in a registry by name.

``lenet`` is the network of the thesis (section 3.4.3, after Wohlhart & Lepetit 2015): two 5x5
convolutions, each followed by ReLU and 2x2 max-pooling, then two fully connected layers, the
last one giving the descriptor (d = 64). ``deeper`` adds a third conv block and batch norm
(measured against ``lenet`` by ``benchmarks/bench_recog.py``).
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["NETWORKS", "make_network", "LeNet", "Deeper"]


class LeNet(nn.Module):
    """conv5x5(16) - ReLU - pool2 - conv5x5(32) - ReLU - pool2 - fc(256) - ReLU - fc(d)."""

    def __init__(self, size: int = 64, descriptor: int = 64):
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(1, 16, 5), nn.ReLU(), nn.MaxPool2d(2),
            nn.Conv2d(16, 32, 5), nn.ReLU(), nn.MaxPool2d(2))
        n = ((size - 4) // 2 - 4) // 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(32 * n * n, 256), nn.ReLU(), nn.Linear(256, descriptor))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 1, S, S) float patches in [-1, 1] -> (B, d) descriptors."""
        return self.head(self.features(x))


class Deeper(nn.Module):
    """Three conv blocks (3x3, batch norm, ReLU, pool) - fc(256) - fc(d)."""

    def __init__(self, size: int = 64, descriptor: int = 64):
        super().__init__()
        layers, c = [], 1
        for k in (32, 64, 96):
            layers += [nn.Conv2d(c, k, 3, padding=1), nn.BatchNorm2d(k), nn.ReLU(),
                       nn.Conv2d(k, k, 3, padding=1), nn.BatchNorm2d(k), nn.ReLU(), nn.MaxPool2d(2)]
            c = k
        self.features = nn.Sequential(*layers)
        n = size // 8
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * n * n, 256), nn.ReLU(), nn.Linear(256, descriptor))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


NETWORKS = {"lenet": LeNet, "deeper": Deeper}


def make_network(name: str, size: int = 64, descriptor: int = 64) -> nn.Module:
    from data_tools.errors import ConfigError
    if name not in NETWORKS:
        raise ConfigError(f"unknown network {name!r}; choose one of {', '.join(NETWORKS)}")
    return NETWORKS[name](size, descriptor)
