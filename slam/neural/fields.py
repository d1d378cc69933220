"""Local pose fields of the neural memory (B, r, P, P): probability over r headings x P x P positions around an
allocentric ``centre`` (B, 2) (field index (P // 2, P // 2) = the centre). Their peak and its sub-cell refinement.
Poses are (row, col) in memory cells and the heading in steps of 2 pi / r."""
from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["peak_poses", "refine_pose", "refine_peak"]


def _peak_index(field: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(heading k, row i, column j) field indices (...,) of the maxima of fields (..., r, P, P)."""
    P = field.shape[-1]
    idx = field.flatten(-3).argmax(-1)
    rem = idx % (P * P)
    return idx // (P * P), rem // P, rem % P


def peak_poses(field: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """(..., 3) long allocentric (row, col, heading) of the maxima of local pose fields or logits (..., r, P, P)
    whose middle cell is the allocentric ``centre`` (..., 2)."""
    R = field.shape[-1] // 2
    k, i, j = _peak_index(field)
    return torch.stack([centre[..., 0] + i - R, centre[..., 1] + j - R, k], -1)


def refine_pose(field: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """(B, 3) float allocentric (row, col, heading in steps) of local pose fields (B, r, P, P) centred on ``centre``
    (B, 2): the maximum refined by the centroid of its 3 x 3 neighbours (position) and by the two neighbouring
    headings' mass (heading); the ``neural`` backend's estimates (``refine_peak``)."""
    B, r, P, _ = field.shape
    b = torch.arange(B, device=field.device)
    k, i, j = _peak_index(field)
    pad = F.pad(field, (1, 1, 1, 1))
    d = torch.arange(-1, 2, device=field.device)
    ii = i[:, None, None] + 1 + d[None, :, None]
    jj = j[:, None, None] + 1 + d[None, None, :]

    def window(kk):
        return pad[b[:, None, None], (kk % r)[:, None, None], ii, jj]          # (B, 3, 3)
    w0 = window(k)
    s0 = w0.sum((1, 2)).clamp(min=1e-12)
    di = (w0 * d[None, :, None]).sum((1, 2)) / s0
    dj = (w0 * d[None, None, :]).sum((1, 2)) / s0
    sm, sp = window(k - 1).sum((1, 2)), window(k + 1).sum((1, 2))
    dk = (sp - sm) / (sm + w0.sum((1, 2)) + sp).clamp(min=1e-12)
    R = P // 2
    return torch.stack([centre[:, 0].float() + i.float() + di - R, centre[:, 1].float() + j.float() + dj - R,
                        k.float() + dk], 1)


def refine_peak(field, centre, refine: bool = True) -> tuple[float, float, float, float]:
    """(row, col, heading index (fractional), peak probability) of one local pose field (r, P, P) array whose middle
    is the allocentric ``centre`` (2,): the maximum, refined (``refine``) by :func:`refine_pose` - the ``neural``
    registration backend's estimate of a memory step."""
    import numpy as np
    f = torch.from_numpy(np.asarray(field, np.float32))[None]
    c = torch.from_numpy(np.asarray(centre, np.int64))[None]
    pose = (refine_pose(f, c) if refine else peak_poses(f, c).float())[0].tolist()
    return float(pose[0]), float(pose[1]), float(pose[2]), float(f.max())
