"""Approximate Blinn-Phong shading of normal maps (thesis Algorithm 5.1).

    V(r, c) = unit vector from the surface towards the camera, from the pixel's ray
    H       = (V + L) / |V + L|          (half-way vector)
    D       = max(N . L, 0)              (diffuse)
    S       = max(N . H, 0) ** s^        (specular, hardness s^)
    Y       = clip(a + d D + s S, 0, 1)  (per RGB channel: a, d, s in R^3)

with the light at infinity (one direction L for every pixel). kornia has no shading function,
hence this module.

Deviations from Algorithm 5.1, on purpose:

* Frame: the project's camera frame (OpenCV, as :mod:`synth.render.ideal`): x right, y down, z
  forward; a surface facing the camera has a normal with negative z, and V(r, c) =
  -((c + 0.5 - W/2) / F, (r + 0.5 - H/2) / F, 1) normalised (the algorithm writes the same
  vectors in a frame whose z points to the viewer, with pixel corners instead of centres).
* H is normalised (the algorithm writes H = V + L; Blinn-Phong's half-way vector is unit: without
  the normalisation the specular term would reach 2 ** s^ for a surface facing both).
* D and N.H are clamped at 0 before use (a surface facing away from the light gets no light,
  instead of subtracting from the ambient term; a negative base with a fractional s^ is NaN).
"""
from __future__ import annotations

import torch

__all__ = ["view_vectors", "blinn_phong"]


def view_vectors(h: int, w: int, focal_px: float, device=None, dtype=torch.float32) -> torch.Tensor:
    """(3, H, W) unit vectors from the surface seen at each pixel towards the camera."""
    r = (torch.arange(h, device=device, dtype=dtype) + 0.5 - h / 2) / focal_px
    c = (torch.arange(w, device=device, dtype=dtype) + 0.5 - w / 2) / focal_px
    rr, cc = torch.meshgrid(r, c, indexing="ij")
    ray = torch.stack([cc, rr, torch.ones_like(rr)])
    return -ray / ray.norm(dim=0, keepdim=True)


def blinn_phong(normals: torch.Tensor, light: torch.Tensor, ambient: torch.Tensor, diffuse: torch.Tensor,
                specular: torch.Tensor, hardness: torch.Tensor, focal_px: float) -> torch.Tensor:
    """Shade (B, 3, H, W) unit normals (camera frame) with (B, 3) unit light directions (surface
    towards the light), (B, 3) RGB ambient / diffuse / specular coefficients and (B,) hardness;
    returns (B, 3, H, W) RGB in [0, 1] (see the module docstring)."""
    b, _, h, w = normals.shape
    v = view_vectors(h, w, focal_px, normals.device, normals.dtype)[None]        # (1, 3, H, W)
    lgt = light[:, :, None, None]
    half = v + lgt
    half = half / half.norm(dim=1, keepdim=True).clamp_min(1e-8)
    d = (normals * lgt).sum(1, keepdim=True).clamp_min(0.0)                       # (B, 1, H, W)
    s = (normals * half).sum(1, keepdim=True).clamp_min(0.0) ** hardness[:, None, None, None]
    y = ambient[:, :, None, None] + diffuse[:, :, None, None] * d + specular[:, :, None, None] * s
    return y.clamp(0.0, 1.0)
