"""A stand-in for a measured sequence in lab unit tests: what ``synth.lab.guards`` and
``measured_samples`` read (measured depth, the ideal render's depth and hit mask, no masks), from
hand-made arrays."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np


class FakeMeasured:
    """``measured`` and ``ideal``: lists of (H, W) depth arrays in metres (0 = no measurement /
    no geometry), one per frame."""

    def __init__(self, measured, ideal):
        self._m, self._z = measured, ideal

    def __len__(self):
        return len(self._m)

    def measured_depth(self, k):
        return self._m[k]

    def render(self, k):
        z = self._z[k]
        return SimpleNamespace(depth=z.astype(np.float32), hit=z > 0)

    def mask(self, k):
        return None
