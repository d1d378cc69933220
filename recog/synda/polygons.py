"""Random occluding polygons (thesis Algorithm 5.2, after Ounsworth's random polygon generator)
and their rasterisation.

For a polygon of n vertices around centre C with mean radius r_mu, irregularity epsilon and
spikeyness sigma:

    dtheta_i ~ U((1 - epsilon) 2 pi / n, (1 + epsilon) 2 pi / n),   i = 1..n
    dtheta_i <- 2 pi dtheta_i / sum_j dtheta_j                       (the steps close the loop)
    theta_1 ~ U(0, 2 pi);  theta_{i+1} = theta_i + dtheta_i
    r_i ~ N(r_mu, sigma r_mu) clipped to [0, 2 r_mu]
    p_i = C + r_i (cos theta_i, sin theta_i)

Deviations from the algorithm as printed, on purpose (both as in Ounsworth's code it adapts):
epsilon and sigma are fractions (of 2 pi / n and of r_mu), so that the configured U(0, 0.5)
ranges mean the same for every n and radius; the steps are normalised by their sum (the printed
||dtheta||_2 would not make them close the polygon); radii are clipped to [0, 2 r_mu].

Polygons can be concave or self-intersecting (spiky), so kornia's ``draw_convex_polygon`` does
not apply: :func:`polygon_masks` rasterises with the even-odd rule at pixel centres.
"""
from __future__ import annotations

import math

import torch

__all__ = ["random_polygons", "polygon_masks"]


def random_polygons(n: torch.Tensor, centre: torch.Tensor, r_mu: torch.Tensor, irregularity: torch.Tensor,
                    spikeyness: torch.Tensor, gen: torch.Generator, v_max: int
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """P polygons at once: n (P,) vertex counts (3..v_max), centre (P, 2) pixels (x, y), r_mu,
    irregularity, spikeyness (P,). Returns vertices (P, v_max, 2) (slots beyond n repeat the
    last vertex, which adds only zero-length edges), the normalised angular steps (P, v_max)
    (0 beyond n) and the radii (P, v_max) (those beyond n repeat the last)."""
    p = n.shape[0]
    slot = torch.arange(v_max)[None, :]
    valid = slot < n[:, None]
    base = (2 * math.pi / n.to(torch.float32))[:, None]
    u = torch.rand(p, v_max, generator=gen)
    steps = base * (1 - irregularity[:, None] + 2 * irregularity[:, None] * u)
    steps = torch.where(valid, steps, torch.zeros_like(steps))
    steps = steps * (2 * math.pi) / steps.sum(1, keepdim=True)
    theta0 = torch.rand(p, 1, generator=gen) * (2 * math.pi)
    theta = theta0 + torch.cumsum(steps, 1) - steps                 # theta_1 = theta0
    radii = r_mu[:, None] + spikeyness[:, None] * r_mu[:, None] * torch.randn(p, v_max, generator=gen)
    radii = torch.minimum(radii.clamp_min(0.0), 2 * r_mu[:, None])
    last = (n - 1).clamp_min(0)[:, None]
    radii = torch.where(valid, radii, radii.gather(1, last))
    theta = torch.where(valid, theta, theta.gather(1, last))
    verts = centre[:, None, :] + radii[..., None] * torch.stack([torch.cos(theta), torch.sin(theta)], -1)
    return verts, steps, radii


def polygon_masks(verts: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(..., V, 2) polygons in pixels (x, y) -> (..., H, W) float {0, 1} masks: a pixel is inside
    when a ray from its centre crosses the closed outline an odd number of times."""
    y, x = torch.meshgrid(torch.arange(h, dtype=verts.dtype, device=verts.device) + 0.5,
                          torch.arange(w, dtype=verts.dtype, device=verts.device) + 0.5, indexing="ij")
    a = verts[..., :, None, None, :]                                  # (..., V, 1, 1, 2)
    b = torch.roll(verts, -1, dims=-2)[..., :, None, None, :]
    ax, ay, bx, by = a[..., 0], a[..., 1], b[..., 0], b[..., 1]
    straddles = (ay > y) != (by > y)
    denom = torch.where(straddles, by - ay, torch.ones_like(by))
    x_cross = ax + (y - ay) * (bx - ax) / denom
    crossings = (straddles & (x < x_cross)).sum(-3)
    return (crossings % 2).to(verts.dtype)
