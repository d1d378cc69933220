"""The neural allocentric spatial memory of thesis chapter 4 (after MapNet, Henriques & Vedaldi 2018).

For a sequence of observations x_t (C x q x q, the agent's view, heading up) and nothing else:

* **encode**: a shallow ResNet (4 residual blocks, instance norm, LeakyReLU 0.2) maps x_t to an
  egocentric feature grid o_t (n x q x q). In 2D the view *is* the ground projection (thesis:
  crop + resize, here already q x q); 3D ground projection is :func:`ground_project`.
* **localise**: the bank of the r = 4 rotations of o_t (``torch.rot90``: exact quarter turns) is
  cross-correlated with the memory psi_{t-1} (n x U x U) - one grouped ``conv2d`` for the batch -
  and a softmax (with a learned inverse temperature) turns the responses into the pose field
  p_t (r x U x U): rotation and position of the view's centre in the first observation's frame.
  The first observation is registered at the centre without rotation.
* **register**: the registered features ô_t = p_t * o'_t (the transposed convolution with the same
  bank: a soft, differentiable placement; uncertainty blurs ô_t), and the registered view mask.
* **memorise**: psi_t = LSTM(psi_{t-1}, ô_t) with one LSTM cell shared by every memory cell (each cell
  updated independently, as MapNet); a second shared LSTM cell updates the occupancy b_t from the
  registered view mask (its input detached: the mask's loss trains that LSTM only). ``seen`` is the
  registered view masks binarised and accumulated - what was observed -, which the backend's snapshot pictures
  use. The thesis trains b_t implicitly; here, with :attr:`MemoryConfig.occupancy` ``affine``, b_t = (h_t + 1) / 2
  is trained to ``seen`` (BCE, L_occ - a deviation). Models trained without it (``occupancy = sigmoid``: the
  shipped front_2d) have an untrained occupancy LSTM whose mask sigmoid(h_t) lies in (0.27, 0.73): no loss reads
  ``occ`` with a gradient (see its model card); planar_3d's mask was trained afterwards (``neural
  refine-hallucination``).
* **anamnesis (recall)**: for a requested pose, the q x q window of psi at that position, turned back by
  its heading (geometric culling), masked by the view field (-1 outside, thesis Eq. 4.7), goes
  through the decoder (a shallow ResNet) to an image.
* **hallucination**: an auto-encoder on the memory (spectral norm, one SAGAN self-attention layer)
  fills unobserved cells; it is trained to predict views not yet observed (L_hallu) while leaving
  observed cells unchanged (L_corrupt, masked by the occupancy), against a spectral-normalised
  patch discriminator on culled windows (L_disc).

Deviations from the thesis, on purpose: in 2D quarter-turn rotations only (exact on the grid; the
thesis' +-45 deg agent needs resampling); the hallucination AE has one self-attention layer instead of
two (CPU budget); memory cells are image pixels (bin = 1 px) in 2D. At inference the ``neural`` registration
backend may multiply the pose field by a Gaussian motion prior around the previous estimate
(``forward(..., motion_prior=...)``; the thesis has none): without it one wrong registration corrupts the memory
and the next steps follow it (docs/neural.md); it
may also score a pose on the observed memory cells only (``forward(..., score="overlap")``,
:meth:`NeuralMemory._overlap_score`; the thesis sums over the whole view, which in 3D keeps the heading at the
first frame's).
The shipped 3D model's recall decoder is refined after the memory's training, the memory frozen, on 48 rooms
instead of 12 and with an SSIM term beside the thesis' L1 (:mod:`slam.neural.refine`).
Optionally (2D, :attr:`MemoryConfig.equivariance`) the encoder is made exactly equivariant to quarter turns
(averaged over C4, or its regular representation), so that a place seen from several headings is written with the
same features - the thesis' encoder is a plain ResNet.

3D (``input = "image"``, thesis 4.4.3): the encoder runs on the RGB-D image (4 x 30 x 40) and its
per-pixel features are ground-projected (max-pool per cell, :func:`slam.neural.geometry3d.project_max`)
into the egocentric grid (15 cm cells; 33 x 33 in the 3D `cpu` preset, 49 x 49 in the shipped planar_3d; the
camera at the centre looking up the grid). The
rotation bank of r = 12 headings (30 deg, the thesis' Doom turn) is made by projecting the pixels into
each turned grid (points turned, then binned): exact, unlike resampling a grid - a deviation that also
keeps the bank cheap. Recall (``decoder = "rays"``, ``neural train --decoder rays``): a
:class:`RayDecoder` samples the memory along every pixel's ray at the exact requested pose (real row,
column and heading: no rounding to the 15 cm / 30 deg grid) and a small per-pixel network turns the
samples into the 4 x 30 x 40 RGB-D image - the geometric culling of thesis Fig. 4.5 done per ray.
``decoder = "learned"`` (the default, and the shipped 3D weights): the memory window at the rounded pose is culled
(turned by ``kornia.geometry.transform.rotate`` for headings that are not quarter turns) and an
:class:`ImageDecoder` learns the back-projection. Poses are estimated on the 15 cm / 30 deg grid; the ``neural`` registration
backend refines the field's maximum to sub-cell precision.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["NeuralMemory", "MemoryConfig", "Encoder", "Decoder", "ImageDecoder", "RayDecoder", "Hallucinator",
           "PatchDiscriminator", "rotation_bank", "rotate_grid", "turn_features", "memory_index", "peak_poses",
           "init_weights", "correlate", "register", "refine_pose", "splat_field"]

from dataclasses import dataclass

from slam.neural import POSE_SCORES
from slam.neural.fields import peak_poses, refine_pose, splat_field


@dataclass
class MemoryConfig:
    """Sizes of the model (saved with the weights)."""

    channels: int = 3
    """Image channels C (3 RGB, 4 RGB-D)."""
    features: int = 16
    """Feature size n of the memory cells."""
    view: int = 15
    """Side q of the egocentric grid (odd)."""
    memory: int = 71
    """Side U of the allocentric memory (odd): must hold every position the agent reaches from its start."""
    width: int = 32
    """Channels inside the encoder/decoder ResNets."""
    rotations: int = 4
    """Headings r (quarter turns)."""
    search: int = 16
    """Localisation searches positions within +-search cells of the previous estimate."""
    input: str = "grid"
    """``grid``: observations are egocentric grids already (2D, B x T x C x q x q); ``image``: they are
    images (3D, B x T x C x H x W) whose per-pixel encoder features are ground-projected into the grid
    by the pixels' cell indices (:func:`slam.neural.geometry3d.project_max`)."""
    image_size: tuple = (0, 0)
    """3D: (H, W) of the decoded images, pixels (the decoder back-projects the culled window)."""
    decoder: str = "learned"
    """3D recall: ``learned`` (:class:`ImageDecoder`: the culled window at the pose rounded to the grid, a learned
    top-view-to-image map) or ``rays`` (:class:`RayDecoder`: the memory sampled along every pixel's ray at the
    exact pose, then a per-pixel network - a geometric back-projection)."""
    camera: tuple = ()
    """``rays``: (fx, fy, cx, cy) of the decoded H x W image, pixels."""
    level_rotation: tuple = ()
    """``rays``: R_c_L of the camera (9 numbers, row-major; :func:`slam.neural.geometry3d.level_rotation`): its
    pitch and roll."""
    camera_height_m: float = 0.0
    """``rays``: height of the camera above the floor, metres."""
    cell_m: float = 0.0
    """``rays``: side of a memory cell, metres."""
    max_range_m: float = 0.0
    """``rays``: the last depth sampled along a ray, metres (the ground projection's range)."""
    ray_samples: int = 12
    """``rays``: depths sampled per ray, evenly spaced in (0, max_range_m]."""
    correlation: str = "dot"
    """Localisation score: ``dot`` (MapNet's plain cross-correlation of features and memory) or ``cosine``
    (each cell's feature vector and memory vector unit-normalised first, the sum divided by the view's cell
    count: a score in [-1, 1] whatever the scale of the LSTM's output, times a learned inverse temperature
    starting at 20 - a deviation that lets localisation learn from the first memory steps)."""
    equivariance: str = "none"
    """2D (``grid`` input) only: make the encoder exactly equivariant to quarter turns, so that a place seen from
    different headings gives the same registered features (up to the context the view mask leaves) and the memory
    LSTM does not have to merge heading-dependent codes - a deviation from the thesis' (and MapNet's) plain ResNet,
    at 4 x the encoder's cost. ``none``: the plain encoder. ``invariant``: averaged over the group C4,
    E'(x) = 1/4 sum_k rot90^-k(E(rot90^k(x))), so E'(rot90(x)) = rot90(E'(x)): every channel is a
    rotation-invariant field (it cannot tell a horizontal edge from a vertical one). ``regular``: the regular
    representation of C4 - the ResNet gives n / 4 channels and E'(x) stacks the 4 groups rot90^-k(E(rot90^k(x))),
    k = 0..3, so E'(rot90^j(x)) = rot90^j(roll(E'(x), -j groups)) (:func:`turn_features`): orientation is kept in
    which group responds. The rotation bank and the culling turn features by that same action; ``features`` must
    be a multiple of 4."""
    subcell: bool = False
    """3D: register views below the grid's resolution - a pose field is turned into the trilinear splat of one
    real pose (row, col, heading) over its 2 x 2 x 2 neighbouring cells and headings, so a move or turn smaller than
    a cell or a heading step is written where it happened instead of rounded away. Training (``teacher`` poses real)
    registers at the exact poses and L_loc's target is the splat of the exact pose; inference registers at the
    field's peak refined by its 3 x 3 centroid and the neighbouring headings (:func:`refine_pose`), and the motion
    prior is centred there. A deviation from the thesis (MapNet registers with the soft field on the grid): a view
    moved 0.1 m and turned 15 deg from the last lies in the same 15 cm / 30 deg bin, so a memory registered on the
    grid learns "no move" and never turns (docs/neural.md)."""
    colour_skip: bool = False
    """The last ``channels`` of the ``features`` are the observation itself (RGB(-D) in [-1, 1], ground-projected
    like the rest). A deviation: the thesis' encoder (N(0, 0.02) weights, instance norm in every residual branch)
    keeps no absolute colour - a linear probe finds no chroma in its features, recalled floor plans come back grey
    (docs/not_kept.md). False: the thesis' encoder (the shipped models)."""
    decoder_skip: bool = False
    """2D: a 1 x 1 convolution of the culled window added before the decoder's tanh, beside its ResNet (a linear
    path no instance norm rescales). A deviation from the thesis' decoder; False: the shipped models."""
    occupancy: str = "sigmoid"
    """How the occupancy LSTM's hidden state h in (-1, 1) becomes the mask b: ``sigmoid`` (b = sigmoid(h), in
    (0.27, 0.73): models trained with ``occ_weight`` 0, whose occupancy LSTM gets no gradient) or ``affine``
    (b = (h + 1) / 2, in (0, 1): trained to the observed cells ``seen`` by L_occ,
    :attr:`slam.neural.train.NeuralTrainConfig.occ_weight`)."""


class ResBlock(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(c, c, 3, padding=1), nn.InstanceNorm2d(c, affine=True),
                                  nn.LeakyReLU(0.2), nn.Conv2d(c, c, 3, padding=1), nn.InstanceNorm2d(c, affine=True))

    def forward(self, x):
        return F.leaky_relu(x + self.body(x), 0.2)


class Encoder(nn.Module):
    """x (B, C, q, q) in [-1, 1] (3D: (B, C, H, W)) -> o (B, n, q, q); made equivariant to quarter turns by
    :attr:`MemoryConfig.equivariance` (square inputs only); :attr:`MemoryConfig.colour_skip`: o[:, -C:] = x."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        w = cfg.width
        self.equivariance = cfg.equivariance
        self.colour_skip = bool(cfg.colour_skip)
        n = cfg.features - (cfg.channels if self.colour_skip else 0)
        out = n // 4 if cfg.equivariance == "regular" else n
        self.net = nn.Sequential(nn.Conv2d(cfg.channels, w, 3, padding=1), nn.LeakyReLU(0.2),
                                 *[ResBlock(w) for _ in range(4)], nn.Conv2d(w, out, 1))

    def forward(self, x):
        if self.equivariance == "none":
            f = self.net(x)
        else:
            B = x.shape[0]
            f = self.net(torch.cat([torch.rot90(x, k, (-2, -1)) for k in range(4)], 0))
            turned = [torch.rot90(f[k * B:(k + 1) * B], -k, (-2, -1)) for k in range(4)]
            f = sum(turned) / 4.0 if self.equivariance == "invariant" else torch.cat(turned, 1)
        return torch.cat([f, x], 1) if self.colour_skip else f


class Decoder(nn.Module):
    """culled window (B, n + 1, q, q) (features + view-field channel) -> image (B, C, q, q) in [-1, 1]."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        w = cfg.width
        self.net = nn.Sequential(nn.Conv2d(cfg.features + 1, w, 3, padding=1), nn.LeakyReLU(0.2),
                                 *[ResBlock(w) for _ in range(4)], nn.Conv2d(w, cfg.channels, 3, padding=1), nn.Tanh())
        self.skip = nn.Conv2d(cfg.features + 1, cfg.channels, 1) if cfg.decoder_skip else None

    def forward(self, x):     # decoder_skip: a 1 x 1 convolution of the window added before the tanh
        return self.net(x) if self.skip is None else torch.tanh(self.net[:-1](x) + self.skip(x))


class ImageDecoder(nn.Module):
    """3D: culled window (B, n + 1, q, q) -> image (B, C, H, W) in [-1, 1]. Two strided convolutions and a
    learned linear map take the top view to a coarse (H / 5, W / 5) image-plane grid (the back-projection
    is learned, not geometric: a deviation that keeps the decoder small), then a ResNet refines it."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        w = cfg.width
        H, W = cfg.image_size
        self.coarse = (max(H // 5, 1), max(W // 5, 1))
        s1 = (cfg.view + 1) // 2
        s2 = (s1 + 1) // 2
        self.top = nn.Sequential(nn.Conv2d(cfg.features + 1, w, 3, padding=1), nn.LeakyReLU(0.2), ResBlock(w),
                                 nn.Conv2d(w, w, 3, 2, 1), nn.LeakyReLU(0.2), nn.Conv2d(w, w, 3, 2, 1),
                                 nn.LeakyReLU(0.2), nn.Conv2d(w, 8, 1))
        self.fc = nn.Linear(8 * s2 * s2, w * self.coarse[0] * self.coarse[1])
        self.img = nn.Sequential(ResBlock(w), ResBlock(w), nn.Conv2d(w, cfg.channels, 3, padding=1), nn.Tanh())
        self.size = (H, W)
        self.w = w

    def forward(self, x):
        B = x.shape[0]
        y = F.leaky_relu(self.fc(self.top(x).flatten(1)), 0.2).view(B, self.w, *self.coarse)
        return self.img(F.interpolate(y, size=self.size, mode="bilinear", align_corners=False))


class RayDecoder(nn.Module):
    """3D recall by geometric back-projection: for every pixel of the H x W image the memory is sampled
    (bilinear, ``grid_sample``) at ``ray_samples`` points of the pixel's ray (camera depths evenly spaced up to
    ``max_range_m``), placed by the *exact* requested pose (row, col in cells, heading in units of 2 pi / r,
    all real: no rounding to the grid); the n x D samples of a pixel, plus where each sample lies under the
    floor and the depth at which the ray meets the floor (known: camera height and pitch), go through a
    1 x 1 convolution (a per-pixel network along the ray) and a ResNet to RGB-D. This is the thesis' culling
    (rotation, translation, clipping to the view frustum) done per ray instead of on a top-view window -
    a deviation: the memory is 2.5D (cells on the floor plan), so the decoder still has to learn which
    sample along a ray is the first surface (the encoder max-pools a cell's column)."""

    def __init__(self, cfg: "MemoryConfig"):
        super().__init__()
        if len(cfg.camera) != 4 or len(cfg.level_rotation) != 9 or cfg.cell_m <= 0 or cfg.max_range_m <= 0:
            raise ValueError("a ray decoder needs camera (fx, fy, cx, cy), level_rotation (9), cell_m and max_range_m")
        H, W = cfg.image_size
        D, n, w = cfg.ray_samples, cfg.features, cfg.width
        fx, fy, cx, cy = (float(v) for v in cfg.camera)
        R = torch.tensor([float(v) for v in cfg.level_rotation], dtype=torch.float64).view(3, 3)
        v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
        d_c = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1).reshape(-1, 3)
        d_L = d_c @ R                                  # level-frame directions per unit camera depth (x, down, fwd)
        z = cfg.max_range_m * torch.arange(1, D + 1, dtype=torch.float64) / D
        pts = z[:, None, None] * d_L[None]             # (D, H*W, 3) metres
        self.register_buffer("fwd", (pts[..., 2] / cfg.cell_m).float(), persistent=False)      # (D, H*W) cells
        self.register_buffer("right", (pts[..., 0] / cfg.cell_m).float(), persistent=False)
        under = (pts[..., 1] > cfg.camera_height_m).float().view(D, H, W) * 2 - 1
        down = d_L[:, 1]
        zf = torch.where(down > 1e-6, cfg.camera_height_m / down.clamp(min=1e-6), torch.full_like(down, 1e9))
        floor = (zf / cfg.max_range_m).clamp(0, 1).view(1, H, W) * 2 - 1
        self.register_buffer("prior", torch.cat([under, floor], 0).float(), persistent=False)   # (D + 1, H, W)
        self.size, self.D, self.n = (H, W), D, n
        self.rotations = cfg.rotations
        self.net = nn.Sequential(nn.Conv2d(n * D + D + 1, w, 1), nn.LeakyReLU(0.2), nn.Conv2d(w, w, 3, padding=1),
                                 nn.LeakyReLU(0.2), ResBlock(w), ResBlock(w), nn.Conv2d(w, cfg.channels, 3, padding=1),
                                 nn.Tanh())

    def ray_cells(self, poses: torch.Tensor, U: int) -> torch.Tensor:
        """(N, D, H*W, 2) memory (row, col) of every ray sample, cells (real), for (N, 3) poses (row, col, heading
        in units of 2 pi / r) in a U x U memory."""
        p = poses.to(self.fwd.dtype)
        a = p[:, 2] * (2 * torch.pi / self.rotations)
        ca, sa = torch.cos(a)[:, None, None], torch.sin(a)[:, None, None]
        x = self.right[None] * ca - self.fwd[None] * sa
        f = self.right[None] * sa + self.fwd[None] * ca
        c = U // 2
        return torch.stack([c + p[:, 0, None, None] - f, c + p[:, 1, None, None] + x], -1)

    def forward(self, psi: torch.Tensor, poses: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) images of the memories ``psi[index]`` (B, n, U, U) at ``poses`` (N, 3)."""
        U = psi.shape[-1]
        rc = self.ray_cells(poses, U)
        grid = torch.stack([rc[..., 1], rc[..., 0]], -1) * (2.0 / (U - 1)) - 1.0      # x = col, y = row
        smp = F.grid_sample(psi[index], grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        N = poses.shape[0]
        x = torch.cat([smp.reshape(N, self.n * self.D, *self.size), self.prior.expand(N, -1, -1, -1)], 1)
        return self.net(x)


class SelfAttention(nn.Module):
    """SAGAN self-attention: o + gamma * (W_h o) softmax((W_f o)^T (W_g o))."""

    def __init__(self, c: int):
        super().__init__()
        k = max(c // 8, 1)
        sn = nn.utils.spectral_norm
        self.f, self.g, self.h = sn(nn.Conv2d(c, k, 1)), sn(nn.Conv2d(c, k, 1)), sn(nn.Conv2d(c, c, 1))
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x):
        B, C, H, W = x.shape
        f, g, h = self.f(x).flatten(2), self.g(x).flatten(2), self.h(x).flatten(2)
        att = torch.softmax(f.transpose(1, 2) @ g, dim=-1)          # (B, HW, HW)
        return x + self.gamma * (h @ att.transpose(1, 2)).view(B, C, H, W)


class Hallucinator(nn.Module):
    """Memory (B, n + 1, U, U) (features + occupancy) -> hole-filled features (B, n, U, U)."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        sn = nn.utils.spectral_norm
        w, n = cfg.width, cfg.features
        self.down = nn.Sequential(sn(nn.Conv2d(n + 1, w, 4, 2, 1)), nn.LeakyReLU(0.2),
                                  sn(nn.Conv2d(w, w, 4, 2, 1)), nn.LeakyReLU(0.2))
        self.att = SelfAttention(w)
        self.up = nn.Sequential(nn.ConvTranspose2d(w, w, 4, 2, 1), nn.LeakyReLU(0.2),
                                nn.ConvTranspose2d(w, w, 4, 2, 1), nn.LeakyReLU(0.2))
        self.out = nn.Conv2d(w + n + 1, n, 3, padding=1)

    def forward(self, psi, occ):
        x = torch.cat([psi, occ], 1)
        U = x.shape[-1]
        y = self.up(self.att(self.down(x)))
        y = F.interpolate(y, size=(U, U), mode="bilinear", align_corners=False) if y.shape[-1] != U else y
        filled = self.out(torch.cat([y, x], 1))
        return occ * psi + (1 - occ) * filled    # observed cells pass through (L_corrupt checks the rest)


class PatchDiscriminator(nn.Module):
    """Culled windows (B, n, q, q) -> realism logits (B, 1, q', q')."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        sn = nn.utils.spectral_norm
        w = cfg.width
        self.net = nn.Sequential(sn(nn.Conv2d(cfg.features, w, 3, 1, 1)), nn.LeakyReLU(0.2),
                                 sn(nn.Conv2d(w, w, 4, 2, 1)), nn.LeakyReLU(0.2), SelfAttention(w),
                                 sn(nn.Conv2d(w, 1, 3, 1, 1)))

    def forward(self, x):
        return self.net(x)


def init_weights(m: nn.Module) -> None:
    """Weights ~ N(0, 0.02) (thesis 4.4.1)."""
    for mod in m.modules():
        if isinstance(mod, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
            wt = getattr(mod, "weight_orig", mod.weight)
            nn.init.normal_(wt, 0.0, 0.02)
            if mod.bias is not None:
                nn.init.zeros_(mod.bias)


def rotate_grid(x: torch.Tensor, k: int, r: int) -> torch.Tensor:
    """(B, c, q, q) turned counter-clockwise (seen from above) by k / r of a full turn: exact
    ``torch.rot90`` for multiples of 90 deg, else bilinear resampling about the centre cell
    (``kornia.geometry.transform.rotate``)."""
    if (4 * k) % r == 0:
        return torch.rot90(x, (4 * k) // r, dims=(-2, -1))
    from kornia.geometry.transform import rotate
    ang = torch.full((x.shape[0],), 360.0 * k / r, dtype=x.dtype, device=x.device)
    return rotate(x, ang, mode="bilinear", padding_mode="zeros", align_corners=True)


def turn_features(x: torch.Tensor, k: int, r: int, regular: bool = False) -> torch.Tensor:
    """Feature grids (B, n, q, q) turned by k / r of a full turn (:func:`rotate_grid`); ``regular``: features of the
    regular representation of C4 (:attr:`MemoryConfig.equivariance`, r = 4) - turned and their 4 channel groups rolled
    by -k, the action under which the encoder is equivariant."""
    if regular:
        B, n = x.shape[:2]
        x = torch.roll(x.reshape(B, 4, n // 4, *x.shape[2:]), -k, 1).reshape(x.shape)
    return rotate_grid(x, k, r)


def memory_index(psi: torch.Tensor, n: int) -> torch.Tensor:
    """(B * n,) memory index of n consecutive poses per memory (0 x n, 1 x n, ...): the ``index`` of
    :meth:`NeuralMemory.cull` / :meth:`NeuralMemory.recall` when every memory is read at n poses."""
    return torch.arange(psi.shape[0], device=psi.device).repeat_interleave(n)


def rotation_bank(o: torch.Tensor, r: int = 4, regular: bool = False) -> torch.Tensor:
    """(B, n, q, q) -> (B, r, n, q, q): o turned counter-clockwise by k / r of a full turn, k = 0..r-1
    (quarter turns exact; see :func:`rotate_grid`; ``regular``: :func:`turn_features`)."""
    return torch.stack([turn_features(o, k, r, regular) for k in range(r)], 1)


def correlate(window: torch.Tensor, bank: torch.Tensor) -> torch.Tensor:
    """Cross-correlation of a memory window (B, n, W, W) with a rotation bank (B, r, n, q, q): (B, r, P, P)
    responses, P = W - q + 1, response (k, i, j) = sum of window[:, i:i+q, j:j+q] * bank[k] (one grouped
    convolution for the batch)."""
    B, r, n, q, _ = bank.shape
    W = window.shape[-1]
    return F.conv2d(window.reshape(1, B * n, W, W), bank.reshape(B * r, n, q, q), groups=B).view(B, r, W - q + 1,
                                                                                                  W - q + 1)


def register(field: torch.Tensor, bank: torch.Tensor) -> torch.Tensor:
    """The adjoint of :func:`correlate`: a pose field (B, r, P, P) placing the bank (B, r, c, q, q) ->
    (B, c, P + q - 1, P + q - 1); a one-hot field pastes bank[k] at (i, j)."""
    B, r, c, q, _ = bank.shape
    P = field.shape[-1]
    return F.conv_transpose2d(field.reshape(1, B * r, P, P), bank.reshape(B * r, c, q, q), groups=B).view(
        B, c, P + q - 1, P + q - 1)


class NeuralMemory(nn.Module):
    """Encoder, localisation, registration, LSTM memory, culling, decoder, hallucination."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        self.cfg = cfg
        if cfg.equivariance not in ("none", "invariant", "regular"):
            raise ValueError(f"equivariance must be none, invariant or regular, got {cfg.equivariance!r}")
        if cfg.equivariance != "none" and (cfg.input != "grid" or cfg.rotations != 4):
            raise ValueError("an equivariant encoder needs square grid inputs and 4 headings (2D)")
        if cfg.equivariance == "regular" and cfg.features % 4:
            raise ValueError(f"equivariance regular needs features divisible by 4, got {cfg.features}")
        if cfg.occupancy not in ("sigmoid", "affine"):
            raise ValueError(f"occupancy must be sigmoid or affine, got {cfg.occupancy!r}")
        if cfg.decoder_skip and cfg.input != "grid":
            raise ValueError("decoder_skip is for the 2D (grid input) decoder")
        if cfg.colour_skip and (cfg.features <= cfg.channels or cfg.equivariance == "regular"):
            raise ValueError(f"colour_skip needs features > {cfg.channels} channels and no regular equivariance")
        self.encoder = Encoder(cfg)
        if cfg.input == "image":
            self.decoder = RayDecoder(cfg) if cfg.decoder == "rays" else ImageDecoder(cfg)
        else:
            self.decoder = Decoder(cfg)
        self.lstm = nn.LSTMCell(cfg.features, cfg.features)
        self.occ_lstm = nn.LSTMCell(1, 1)
        self.hallucinator = Hallucinator(cfg)
        self.log_beta = nn.Parameter(torch.tensor(0.0))
        init_weights(self)

    def set_headings(self, r: int) -> "NeuralMemory":
        """Search (and recall at) ``r`` headings, 2 pi / r apart, instead of the trained ``cfg.rotations`` (3D image
        input only): no weight depends on r - the rotation bank is the pixels projected into each turned grid, given
        as ``cells`` (B, T, r, H * W) for the new r. Poses are then in units of 2 pi / r. Returns the model."""
        import dataclasses
        if self.cfg.input != "image":
            raise ValueError("only a 3D (image input) memory can change its headings: a 2D one turns by quarter turns")
        if int(r) < 1:
            raise ValueError(f"headings must be >= 1, got {r}")
        self.cfg = dataclasses.replace(self.cfg, rotations=int(r))
        if isinstance(self.decoder, RayDecoder):
            self.decoder.rotations = int(r)
        return self

    def one_hot(self, poses: torch.Tensor) -> torch.Tensor:
        """(B, 3) allocentric poses (row offset, col offset, heading) -> (B, r, U, U) one-hot fields."""
        B = poses.shape[0]
        U, c = self.cfg.memory, self.cfg.memory // 2
        f = torch.zeros(B, self.cfg.rotations, U, U, device=poses.device)
        f[torch.arange(B), poses[:, 2] % self.cfg.rotations, poses[:, 0] + c, poses[:, 1] + c] = 1.0
        return f

    # ------------------------------------------------------------------ a sequence
    def encode(self, obs: torch.Tensor, cells: torch.Tensor | None = None) -> torch.Tensor:
        """Egocentric feature grids (B, T, n, q, q) of observations (B, T, C, q, q) (``input`` grid) or of
        images (B, T, C, H, W) with the flat egocentric cell of every pixel ``cells`` (B, T, H * W)."""
        B, T = obs.shape[:2]
        n, q = self.cfg.features, self.cfg.view
        f = self.encoder(obs.flatten(0, 1))
        if self.cfg.input == "image":
            if cells is None:
                raise ValueError("an image-input memory needs the pixels' egocentric cells")
            from slam.neural.geometry3d import project_max
            c = cells[:, :, 0] if cells.dim() == 4 else cells         # the unturned grid
            f = project_max(f, c.flatten(0, 1), q)
        return f.view(B, T, n, q, q)

    def _image_bank(self, f_img: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
        """3D rotation bank (B, r, n, q, q): per-pixel features (B, n, H, W) ground-projected into the r turned
        grids by their cells (B, r, H * W) - exact, no resampling."""
        from slam.neural.geometry3d import project_max
        B, n, H, W = f_img.shape
        r, q = self.cfg.rotations, self.cfg.view
        f = f_img[:, None].expand(B, r, n, H, W).reshape(B * r, n, H, W)
        return project_max(f, cells.reshape(B * r, H * W), q).view(B, r, n, q, q)

    def forward(self, obs: torch.Tensor, view_mask: torch.Tensor, teacher: torch.Tensor | None = None,
                cells: torch.Tensor | None = None, memory: int | None = None,
                motion_prior: tuple[float, float] | None = None, score: str = "sum"):
        """Register a sequence.

        obs (B, T, C, q, q) in [-1, 1] (3D: images (B, T, C, H, W) with ``cells`` (B, T, H * W), see
        :meth:`encode`); view_mask (q, q) float (1 = seen); teacher (B, T, 3): register at these
        allocentric poses instead of the predicted field (training warm-up), or None - integers (a one-hot
        field) or reals (:func:`splat_field`: below the grid, :attr:`MemoryConfig.subcell`); ``memory``: side
        U of the memory for this call (default the configuration's; the model is the same for any U);
        ``motion_prior`` = (sigma_cells, sigma_headings): add the log of a Gaussian on the move from the previous
        estimate (cells, heading steps) to the localisation logits before the softmax - the field (and the
        estimates and the registration) become p(pose | view, memory, previous pose), see
        :meth:`_log_motion_prior`; the returned ``logits`` stay the content scores; None = the thesis' field.
        ``score``: ``sum`` (the thesis: the correlation summed over the whole view) or ``overlap`` (summed over the
        view cells that fall on observed memory cells only, over their number, times the view's cell count:
        :meth:`_overlap_score`).

        Localisation searches a window of (2 R + 1)^2 positions (R = :attr:`MemoryConfig.search`) around the
        previous estimate (the agent moves at most 3/4 of its view per step): a grouped convolution of
        that memory window with the rotation bank. This local search is a deviation from the thesis'
        whole-map correlation, for speed on a CPU (the whole 71x71 map has 5x the window's positions); the
        LSTMs then update every memory cell, as MapNet does (cells outside the registered view get a zero
        input).

        Returns dict: psi (B, n, U, U), occ (B, 1, U, U), seen (B, 1, U, U) 1 on the cells some step's
        registered view field covered (more than half: the occupancy LSTM's input, binarised, accumulated),
        logits (B, T, r, P, P) local logits (t = 0 zeros),
        fields (B, T, r, P, P), centres (B, T, 2) allocentric centre of each window, estimates (B, T, 3)."""
        B, T = obs.shape[:2]
        cfg = self.cfg
        U, n, q, r, R = memory or cfg.memory, cfg.features, cfg.view, cfg.rotations, cfg.search
        h2 = q // 2
        Wp = 2 * R + 1                 # positions per axis
        Wc = Wp + 2 * h2               # memory cells per axis touched by the window
        if Wc > U:
            raise ValueError(f"search window {Wc} cells is larger than the memory {U}")
        if score not in POSE_SCORES:
            raise ValueError(f"score must be one of {POSE_SCORES}, got {score!r}")
        Up = U
        image = cfg.input == "image"
        if image:
            if cells is None or cells.dim() != 4 or cells.shape[2] != r:
                raise ValueError(f"an image-input memory needs cells (B, T, {r}, H*W) for its {r} headings")
            f_img = self.encoder(obs.flatten(0, 1)).view(B, T, n, *obs.shape[-2:])
            from slam.neural.geometry3d import project_max
            feats = project_max(f_img.flatten(0, 1), cells[:, :, 0].flatten(0, 1), q).view(B, T, n, q, q)
        else:
            feats = self.encode(obs, cells)
        m = view_mask.to(obs.dtype)[None, None].expand(B, 1, q, q)
        mbank = rotation_bank(m, r)                                             # (B, r, 1, q, q)
        h = obs.new_zeros(B * Up * Up, n)
        c = obs.new_zeros(B * Up * Up, n)
        oh = obs.new_zeros(B * Up * Up, 1)
        oc = obs.new_zeros(B * Up * Up, 1)
        seen = obs.new_zeros(B * Up * Up, 1)
        est = torch.zeros(B, 3, dtype=torch.long, device=obs.device)            # (row, col, heading)
        bi = torch.arange(B, device=obs.device)[:, None, None]
        off = torch.arange(Wc, device=obs.device)
        logits, fields, centres, ests = [], [], [], []
        cont = est.float()             # the real pose the motion prior is centred on (subcell: the refined peak)
        for t in range(T):
            if image:
                bank = self._image_bank(f_img[:, t], cells[:, t]) * mbank         # (B, r, n, q, q)
            else:
                bank = rotation_bank(feats[:, t] * m, r, cfg.equivariance == "regular")  # (B, r, n, q, q)
            if teacher is None or t == 0:
                want = est[:, :2].clone()
            else:
                want = teacher[:, t - 1, :2]
                want = torch.round(want).long() if want.is_floating_point() else want.clone()
            # the window starts R + q//2 cells before the wanted centre, moved inside the memory at its borders;
            # ``centre`` is the allocentric position of the window's middle (field index R, R)
            start = (want + U // 2 - R - h2).clamp(0, U - Wc)
            centre = start + R + h2 - U // 2
            ri = start[:, 0][:, None, None] + off[None, :, None]                # (B, Wc, 1)
            ci = start[:, 1][:, None, None] + off[None, None, :]                # (B, 1, Wc)
            if t == 0:       # the first view: at the origin, unrotated
                field = self._local_one_hot(torch.zeros(B, 3, dtype=torch.long, device=obs.device), centre, Wp)
                lg = obs.new_zeros(B, r, Wp, Wp)
            else:
                hw = h.view(B, Up, Up, n)[bi, ri, ci].permute(0, 3, 1, 2)       # (B, n, Wc, Wc): the window
                if score == "overlap":
                    sw = seen.view(B, Up, Up, 1)[bi, ri, ci].permute(0, 3, 1, 2)  # (B, 1, Wc, Wc) observed cells
                    lg = self._overlap_score(hw, sw, bank, mbank, m)
                else:
                    lg = self._score(hw, bank, m)
                post = lg if motion_prior is None else lg + self._log_motion_prior(cont, centre, Wp, motion_prior)
                field = torch.softmax(post.flatten(1), 1).view_as(lg)
                if teacher is not None and teacher.is_floating_point():
                    field = splat_field(teacher[:, t], centre, Wp, r)
                elif teacher is not None:
                    field = self._local_one_hot(teacher[:, t], centre, Wp)
            subcell = cfg.subcell and teacher is None and t > 0
            rfield = field          # the field the view is registered with
            if subcell:             # at the refined peak, below the grid
                cont = refine_pose(field.detach(), centre)
                rfield = splat_field(cont, centre, Wp, r)
            reg = register(rfield, bank)                                        # (B, n, Wc, Wc)
            regm = register(rfield, mbank).clamp(0, 1)
            x = obs.new_zeros(B, Up, Up, n).index_put((bi, ri, ci), reg.permute(0, 2, 3, 1))
            xm = obs.new_zeros(B, Up, Up, 1).index_put((bi, ri, ci), regm.permute(0, 2, 3, 1))
            h, c = self.lstm(x.view(-1, n), (h, c))                             # every cell, shared weights
            oh, oc = self.occ_lstm(xm.detach().view(-1, 1), (oh, oc))    # the mask's loss stays in its LSTM
            seen = torch.maximum(seen, (xm.view(-1, 1) > 0.5).to(seen.dtype))
            est = peak_poses(field, centre).detach()
            if not subcell:
                cont = est.float()
            logits.append(lg)
            fields.append(field)
            centres.append(centre)
            ests.append(est)
        psi = h.view(B, U, U, n).permute(0, 3, 1, 2)
        oh = oh.view(B, U, U, 1).permute(0, 3, 1, 2)
        occ = (oh + 1) / 2 if cfg.occupancy == "affine" else torch.sigmoid(oh)
        seen = seen.view(B, U, U, 1).permute(0, 3, 1, 2)
        return {"psi": psi, "occ": occ, "seen": seen, "logits": torch.stack(logits, 1),
                "fields": torch.stack(fields, 1),
                "centres": torch.stack(centres, 1), "estimates": torch.stack(ests, 1), "features": feats}

    def _score(self, window: torch.Tensor, bank: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        """Localisation logits (B, r, P, P) of a memory window (B, n, W, W) and a rotation bank (B, r, n, q, q)."""
        n, q = self.cfg.features, self.cfg.view
        if self.cfg.correlation == "cosine":
            w = F.normalize(window, dim=1, eps=1e-6)
            b = F.normalize(bank, dim=2, eps=1e-6)
            return correlate(w, b) * (20.0 * torch.exp(self.log_beta) / m[0].sum().clamp(min=1))
        return correlate(window, bank) * torch.exp(self.log_beta) / (n * q) ** 0.5

    def _overlap_score(self, window: torch.Tensor, seen: torch.Tensor, bank: torch.Tensor, mbank: torch.Tensor,
                       m: torch.Tensor) -> torch.Tensor:
        """Localisation logits (B, r, P, P) scored on the observed memory only: :meth:`_score` of the window
        (B, n, W, W) with its never-observed cells (``seen`` (B, 1, W, W) = 0) zeroed, divided by the number of
        view cells (the turned view masks ``mbank`` (B, r, 1, q, q)) that land on observed cells and multiplied
        by the view's cell count (``m`` (B, 1, q, q)), so the trained temperature keeps its scale: the mean
        agreement per overlapping cell instead of the sum over the view. Not in the thesis. Why: the sum also
        scores the LSTM state of never-observed cells (its constant response to zero input) and grows with the
        overlap, so the pose that re-covers the last written view wins - measured on the shipped 3D model, the
        heading then never leaves the first frame's (docs/neural.md)."""
        overlap = correlate(seen, mbank)                                       # (B, r, P, P) view cells on seen
        return self._score(window * seen, bank, m) * (m[0].sum() / overlap.clamp(min=1.0))

    def _log_motion_prior(self, prev: torch.Tensor, centre: torch.Tensor, Wp: int,
                          sigmas: tuple[float, float]) -> torch.Tensor:
        """(B, r, Wp, Wp) log of an isotropic Gaussian on the move from the previous estimate ``prev`` (B, 3)
        (row, col, heading) to every pose of the local field centred on ``centre`` (B, 2): -d^2 / (2 s_c^2)
        - dk^2 / (2 s_k^2), d in cells, dk the heading difference in steps of 2 pi / r (the shorter way
        round). Not in the thesis (MapNet localises on the memory alone): an agent that moves little
        between two steps makes far jumps unlikely, which stops one wrong registration from pulling the
        next ones after it."""
        r, R = self.cfg.rotations, Wp // 2
        sc, sk = (float(v) for v in sigmas)
        if not (sc > 0 and sk > 0):
            raise ValueError(f"motion_prior sigmas must be > 0, got {sigmas}")
        ar = torch.arange(Wp, device=prev.device, dtype=torch.float32) - R
        dr = (centre[:, 0] - prev[:, 0]).float()[:, None] + ar[None]                 # (B, Wp)
        dc = (centre[:, 1] - prev[:, 1]).float()[:, None] + ar[None]
        ks = torch.arange(r, device=prev.device)
        dk = ((ks[None] - prev[:, 2:3].float()) % r).float()
        dk = torch.minimum(dk, r - dk)                                             # (B, r)
        lp = -(dr[:, :, None] ** 2 + dc[:, None, :] ** 2) / (2 * sc * sc)         # (B, Wp, Wp)
        return lp[:, None] - (dk ** 2 / (2 * sk * sk))[:, :, None, None]

    def _local_one_hot(self, poses: torch.Tensor, centre: torch.Tensor, Wp: int) -> torch.Tensor:
        """(B, r, Wp, Wp) one-hot of allocentric ``poses`` in windows centred on ``centre`` (all zero when
        the pose is outside its window)."""
        B = poses.shape[0]
        R = Wp // 2
        f = torch.zeros(B, self.cfg.rotations, Wp, Wp, device=poses.device)
        d = poses[:, :2] - centre + R
        ok = ((d >= 0) & (d < Wp)).all(1)
        b = torch.nonzero(ok).flatten()
        f[b, poses[b, 2] % self.cfg.rotations, d[b, 0], d[b, 1]] = 1.0
        return f

    # ------------------------------------------------------------------ recall
    def cull(self, psi: torch.Tensor, poses: torch.Tensor, view_mask: torch.Tensor,
             index: torch.Tensor | None = None) -> torch.Tensor:
        """(B, n, U, U) memories, (N, 3) allocentric poses -> (N, n + 1, q, q) culled windows: the window at
        the pose, turned back to the agent's heading, -1 outside the view field, plus the view-field
        channel. ``index`` (N,): the memory of each pose (default: pose i reads memory i, N = B)."""
        q, c, r = self.cfg.view, psi.shape[-1] // 2, self.cfg.rotations
        pad = q // 2
        P = F.pad(psi, (pad, pad, pad, pad))
        N = poses.shape[0]
        if poses.is_floating_point():        # exact poses (3D): the window is read at the nearest cell and heading
            poses = torch.round(poses).long()
        idx = torch.arange(N, device=psi.device) if index is None else index.to(psi.device)
        ar = torch.arange(q, device=psi.device)
        rows = (poses[:, 0].long() + c)[:, None, None] + ar[None, :, None]
        cols = (poses[:, 1].long() + c)[:, None, None] + ar[None, None, :]
        w = P.permute(0, 2, 3, 1)[idx[:, None, None], rows, cols].permute(0, 3, 1, 2)      # (N, n, q, q)
        ks = poses[:, 2].long() % r
        out = torch.empty_like(w)
        for k in torch.unique(ks).tolist():
            sel = torch.nonzero(ks == k).flatten()
            out[sel] = turn_features(w[sel], -int(k), r, self.cfg.equivariance == "regular")
        m = view_mask.to(psi.dtype)[None, None]
        return torch.cat([out * m - (1 - m), m.expand(N, 1, q, q)], 1)

    def recall(self, psi: torch.Tensor, poses: torch.Tensor, view_mask: torch.Tensor,
               index: torch.Tensor | None = None) -> torch.Tensor:
        """(N, C, q, q) decoded views (3D: (N, C, H, W) images) of the memories at the allocentric ``poses`` (N, 3):
        (row, col, heading index), integers or - 3D - reals (exact poses; the ``learned`` decoder rounds them,
        the ``rays`` decoder samples at them; the ``rays`` decoder's culling is its view frustum, ``view_mask``
        is not used)."""
        if isinstance(self.decoder, RayDecoder):
            idx = torch.arange(poses.shape[0], device=psi.device) if index is None else index.to(psi.device)
            return self.decoder(psi, poses, idx)
        return self.decoder(self.cull(psi, poses, view_mask, index))

    def hallucinate(self, psi: torch.Tensor, occ: torch.Tensor) -> torch.Tensor:
        return self.hallucinator(psi, occ)

