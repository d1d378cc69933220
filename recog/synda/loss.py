"""SynDA losses (thesis section 5.3.1): a generative loss per decoded modality and on the
distilled output, plus the optional triplet loss at the bottleneck.

    L = sum_m L_g(h_D^m(x), y_m) + L_g(h_R(x), y_target) + w_t L_t(h_E)

L_g is the L1 distance for real-valued maps (normals, depth, lightness, the output) and the
cross-entropy for the mask (binary cross-entropy on logits for one channel; cross-entropy over
classes for ``mask_classes`` >= 2, the target then holding class indices). No per-task weights:
the thesis leaves the weighting to the distillation module. L_t is the recogniser's triplet loss
(:func:`recog.loss.triplet_loss`, thesis Eq. 5.1) on the flattened codes.

Deviation, optional (off by default; :class:`recog.synda.config.SyndaTrainConfig`): a descriptor-space
(feature-matching) term ``w_d ||f(h_R(x)) - f(y)||`` with ``f`` a frozen clean-trained recogniser's network
(:func:`descriptor_loss`), and an object-weighted L1 of the output (:func:`object_l1`). The output L1 is
dominated by the ~90 % background pixels and a smoothed chair passes it while the recogniser reads it as another
chair (docs/synda.md, "Why the target is missed"); these terms ask for what the recogniser needs instead.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from data_tools.errors import ConfigError
from recog.loss import triplet_loss

__all__ = ["modality_loss", "generator_loss", "bottleneck_triplet_loss", "descriptor_loss", "object_l1"]


def modality_loss(modality: str, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Scalar L_g of one modality: L1 for real maps (B, C, S, S) in [-1, 1]; for ``mask``,
    BCE-with-logits against a (B, 1, S, S) {0, 1} target (one channel) or cross-entropy against a
    (B, 1, S, S) or (B, S, S) class-index target (C >= 2 channels)."""
    if modality != "mask":
        return F.l1_loss(pred, target)
    if pred.shape[1] == 1:
        return F.binary_cross_entropy_with_logits(pred, target.to(pred.dtype))
    idx = target[:, 0] if target.dim() == 4 else target
    return F.cross_entropy(pred, idx.long())


def generator_loss(out: dict[str, torch.Tensor], targets: dict[str, torch.Tensor],
                   target_modality: str) -> tuple[torch.Tensor, dict[str, float]]:
    """(total, parts) of the generative losses: one per decoded modality in ``out`` and one on
    ``out['output']`` against ``targets[target_modality]``. ``parts`` holds each term as a float
    (``output`` for the final one)."""
    missing = [m for m in list(out) + [target_modality] if m not in ("output", "code") and m not in targets]
    if missing:
        raise ConfigError(f"synda loss: no ground truth for {', '.join(sorted(set(missing)))}")
    parts: dict[str, float] = {}
    total = out["output"].new_zeros(())
    for m, pred in out.items():
        if m in ("output", "code"):
            continue
        term = modality_loss(m, pred, targets[m])
        parts[m] = float(term.detach())
        total = total + term
    if "output" in out and out["output"] is not out.get(target_modality):
        term = modality_loss(target_modality, out["output"], targets[target_modality])
        parts["output"] = float(term.detach())
        total = total + term
    return total, parts


def bottleneck_triplet_loss(code_anchor: torch.Tensor, code_pos: torch.Tensor, code_neg: torch.Tensor,
                            margin: torch.Tensor) -> torch.Tensor:
    """Scalar mean triplet loss (Eq. 5.1) of (B, D) bottleneck codes with (B,) margins (see
    :func:`recog.loss.dynamic_margin`)."""
    return triplet_loss(code_anchor, code_pos, code_neg, margin).mean()


def descriptor_loss(net: torch.nn.Module, pred: torch.Tensor, target: torch.Tensor, distance: str = "l2") -> torch.Tensor:
    """Scalar mean over the batch of the distance between ``net``'s descriptors of ``pred`` and of ``target``
    ((B, 1, S, S) depth patches in the recogniser's normalisation, which h_G's tanh output already is:
    :mod:`recog.patches`, fed to the network as :meth:`recog.model.Recogniser.describe` does). ``l2``: squared
    Euclidean; ``l1``: sum of absolute differences. The target's descriptor carries no gradient; ``net`` should
    be frozen (its parameters not in the optimiser, ``requires_grad`` off) so that only h_G learns."""
    with torch.no_grad():
        t = net(target)
    d = net(pred) - t
    if distance == "l1":
        return d.abs().sum(1).mean()
    if distance != "l2":
        raise ConfigError(f"synda descriptor distance {distance!r}: choose l2 or l1")
    return (d * d).sum(1).mean()


def object_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Scalar L1 of ``pred`` against ``target`` ((B, C, S, S)) on the pixels where ``mask`` (B, 1, S, S) is set,
    mean over those pixels of the batch (0 when none is)."""
    m = mask.to(pred.dtype)
    return ((pred - target).abs() * m).sum() / (m.sum() * pred.shape[1]).clamp(min=1)
