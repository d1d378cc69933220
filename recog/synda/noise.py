"""Procedural noise fields for SynDA's augmentation: fractal Perlin noise (Perlin 1985), cellular /
Voronoi noise (Worley 1996) and white noise, as random draws (tensors) separate from their
deterministic evaluation at arbitrary coordinates.

Every field is periodic on the unit torus, so it can be evaluated at any (u, v): at pixel
coordinates for backgrounds, or at coordinates taken from the normals for the textures that
the thesis indexes by the normals (section 5.3.2). kornia has no Perlin / Voronoi / value noise
(its plasma fractal is not indexable by coordinates), hence this module.

Values are min-max normalised per sample and channel to [0, 1] over the evaluated map (the
ranges of raw Perlin / Worley values depend on the draw; the augmentation maps [0, 1] into the
configured ranges).
"""
from __future__ import annotations

import math

import torch

__all__ = ["NOISE_KINDS", "PERLIN_RES", "VORONOI_POINTS", "WHITE_RES", "draw_noise", "eval_noise", "select", "NOISE",
           "pixel_coords"]

NOISE_KINDS = ("perlin", "voronoi", "white")
PERLIN_RES = (2, 4, 8)
"""Lattice cells per unit of each Perlin octave (amplitudes 1, 1/2, 1/4)."""
VORONOI_POINTS = 12
"""Feature points per unit torus of the cellular noise."""
WHITE_RES = 16
"""Lattice cells per unit of the white noise (nearest lookup: blocky colour noise)."""


def draw_noise(kinds: torch.Tensor, channels: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
    """Random draws of B noise fields with ``channels`` channels each; ``kinds`` (B,) int64 holds
    each sample's index into :data:`NOISE_KINDS`. Every kind's tensors are drawn for every
    sample (fixed tensor shapes, so a sample's draw does not depend on the others' kinds)."""
    b = kinds.shape[0]
    p = {"kind": kinds.clone()}
    for r in PERLIN_RES:
        p[f"perlin{r}"] = torch.rand(b, channels, r, r, generator=gen) * (2 * math.pi)
    p["voronoi"] = torch.rand(b, channels, VORONOI_POINTS, 2, generator=gen)
    p["white"] = torch.rand(b, channels, WHITE_RES, WHITE_RES, generator=gen)
    return p


def select(p: dict[str, torch.Tensor], idx: torch.Tensor) -> dict[str, torch.Tensor]:
    """The draws of the samples ``idx``."""
    return {k: v[idx] for k, v in p.items()}


def _perlin(angles: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Periodic gradient noise. angles (B, C, R, R) gradient directions on an R x R lattice;
    coords (B, H, W, 2) in [0, 1) -> (B, C, H, W), values in about [-0.71, 0.71]."""
    b, c, r, _ = angles.shape
    xy = coords * r
    i0 = torch.floor(xy).long()
    f = xy - i0                                             # (B, H, W, 2)
    gx, gy = torch.cos(angles), torch.sin(angles)
    flat_x, flat_y = gx.flatten(2), gy.flatten(2)           # (B, C, R*R)
    h, w = coords.shape[1:3]

    def corner(dx: int, dy: int) -> torch.Tensor:
        ix = (i0[..., 0] + dx) % r
        iy = (i0[..., 1] + dy) % r
        k = (iy * r + ix).view(b, 1, h * w).expand(b, c, h * w)
        g_x = flat_x.gather(2, k).view(b, c, h, w)
        g_y = flat_y.gather(2, k).view(b, c, h, w)
        return g_x * (f[..., 0] - dx).unsqueeze(1) + g_y * (f[..., 1] - dy).unsqueeze(1)

    fade = f * f * f * (f * (f * 6 - 15) + 10)              # Perlin's quintic
    u, v = fade[..., 0].unsqueeze(1), fade[..., 1].unsqueeze(1)
    top = corner(0, 0) * (1 - u) + corner(1, 0) * u
    bottom = corner(0, 1) * (1 - u) + corner(1, 1) * u
    return top * (1 - v) + bottom * v


def _voronoi(points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Distance to the nearest feature point on the unit torus (Worley's F1). points (B, C, K, 2),
    coords (B, H, W, 2) -> (B, C, H, W)."""
    d = coords[:, None, :, :, None, :] - points[:, :, None, None, :, :]   # (B, C, H, W, K, 2)
    d = torch.remainder(d, 1.0)
    d = torch.minimum(d, 1.0 - d)
    return (d * d).sum(-1).min(-1).values.sqrt()


def _white(values: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Nearest lookup in a periodic (B, C, R, R) lattice of uniform values."""
    b, c, r, _ = values.shape
    h, w = coords.shape[1:3]
    i = (torch.floor(coords * r).long() % r)
    k = (i[..., 1] * r + i[..., 0]).view(b, 1, h * w).expand(b, c, h * w)
    return values.flatten(2).gather(2, k).view(b, c, h, w)


def _normalise(x: torch.Tensor) -> torch.Tensor:
    lo = x.flatten(2).min(-1).values[..., None, None]
    hi = x.flatten(2).max(-1).values[..., None, None]
    return (x - lo) / (hi - lo).clamp_min(1e-6)


def eval_noise(p: dict[str, torch.Tensor], coords: torch.Tensor) -> torch.Tensor:
    """Evaluate the fields ``p`` (from :func:`draw_noise`) at coords (B, H, W, 2) (any real values;
    the fields have period 1) -> (B, C, H, W) in [0, 1]. Pure: same inputs, same output."""
    coords = torch.remainder(coords, 1.0)
    c = p["white"].shape[1]
    b, h, w = coords.shape[:3]
    out = coords.new_zeros(b, c, h, w)
    for k, name in enumerate(NOISE_KINDS):  # NOISE_KINDS fixes the index of each kind in the draws
        idx = torch.nonzero(p["kind"] == k).flatten()
        if len(idx) == 0:
            continue
        out[idx] = _normalise(NOISE[name](select(p, idx), coords[idx]))
    return out


def _fractal_perlin(q: dict[str, torch.Tensor], xy: torch.Tensor) -> torch.Tensor:
    return sum(_perlin(q[f"perlin{r}"].to(xy), xy) * (PERLIN_RES[0] / r) for r in PERLIN_RES)


NOISE = {"perlin": _fractal_perlin,
         "voronoi": lambda q, xy: _voronoi(q["voronoi"].to(xy), xy),
         "white": lambda q, xy: _white(q["white"].to(xy), xy)}
"""Kind -> (draws of the samples, coords (B, H, W, 2)) -> raw (B, C, H, W) values."""


def pixel_coords(batch: int, h: int, w: int, device=None) -> torch.Tensor:
    """(B, H, W, 2) pixel-centre coordinates (x, y) / side, in [0, 1)."""
    y, x = torch.meshgrid((torch.arange(h, device=device) + 0.5) / h, (torch.arange(w, device=device) + 0.5) / w,
                          indexing="ij")
    return torch.stack([x, y], -1).expand(batch, h, w, 2)
