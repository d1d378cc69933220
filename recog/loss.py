"""The triplet + pair loss of Wohlhart & Lepetit 2015 with the dynamic margin of Zakharov et al. 2017.

For descriptors f (network outputs) of an anchor x_b, a positive x_+ (same object, nearest
pose), a negative x_- and a pair partner x_b' (the same view under another noise draw):

    L_triplet = max(0, 1 - ||f(x_b) - f(x_-)||^2 / (||f(x_b) - f(x_+)||^2 + m))
    L_pair    = ||f(x_b) - f(x_b')||^2
    L         = mean(L_triplet) + w_pair mean(L_pair) + lambda ||theta||^2

(lambda is the optimiser's weight decay). The margin m is *dynamic*: for a negative of the
anchor's own object it is the (symmetry-aware) rotation angle between their poses in radians,
2 arccos(|q_b . q_-|); for a negative of another object a fixed ``class_margin`` > pi, larger
than any pose difference, so other objects are always pushed further away than other poses.

Deviation, on purpose: the thesis' Eq. 3.2 writes q_+ in the margin; we follow Zakharov et al.
2017 (anchor and *negative*, q_-). With q_+ the margin would be ~0 for every triplet (the
positive is the nearest pose), i.e. not dynamic at all.
"""
from __future__ import annotations

import math

import torch

__all__ = ["triplet_loss", "pair_loss", "dynamic_margin"]


def triplet_loss(f_b: torch.Tensor, f_pos: torch.Tensor, f_neg: torch.Tensor, margin: torch.Tensor) -> torch.Tensor:
    """(B,) per-triplet loss for (B, d) descriptors and (B,) margins (see the module docstring)."""
    d_pos = ((f_b - f_pos) ** 2).sum(1)
    d_neg = ((f_b - f_neg) ** 2).sum(1)
    return torch.clamp(1.0 - d_neg / (d_pos + margin), min=0.0)


def pair_loss(f_b: torch.Tensor, f_b2: torch.Tensor) -> torch.Tensor:
    """(B,) squared descriptor distance of the pairs."""
    return ((f_b - f_b2) ** 2).sum(1)


def dynamic_margin(same_object: torch.Tensor, angle_rad: torch.Tensor, class_margin: float = 4.0) -> torch.Tensor:
    """(B,) margins: the anchor-negative rotation angle (radians) within an object, ``class_margin``
    (must exceed pi) across objects."""
    if not class_margin > math.pi:
        raise ValueError(f"class_margin must exceed pi, got {class_margin}")
    return torch.where(same_object, angle_rad, torch.full_like(angle_rad, float(class_margin)))
