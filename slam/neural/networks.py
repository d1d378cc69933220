"""The network parts of the neural memory (thesis 4.3; the sequence model that joins them is
:class:`slam.neural.memory.NeuralMemory`): the encoder and the recall decoders (shallow ResNets, instance norm,
LeakyReLU 0.2), the hallucination auto-encoder (spectral norm, one SAGAN self-attention layer), the patch
discriminator of its GAN loss, and the thesis' N(0, 0.02) weight initialisation."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from slam.neural.config import MemoryConfig

__all__ = ["ResBlock", "Encoder", "Decoder", "ImageDecoder", "SelfAttention", "Hallucinator", "PatchDiscriminator",
           "init_weights"]


class ResBlock(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(c, c, 3, padding=1), nn.InstanceNorm2d(c, affine=True),
                                  nn.LeakyReLU(0.2), nn.Conv2d(c, c, 3, padding=1), nn.InstanceNorm2d(c, affine=True))

    def forward(self, x):
        return F.leaky_relu(x + self.body(x), 0.2)


class Encoder(nn.Module):
    """x (B, C, q, q) in [-1, 1] (3D: (B, C, H, W)) -> o (B, n, q, q) (3D: (B, n, H, W))."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        w = cfg.width
        self.net = nn.Sequential(nn.Conv2d(cfg.channels, w, 3, padding=1), nn.LeakyReLU(0.2),
                                 *[ResBlock(w) for _ in range(4)], nn.Conv2d(w, cfg.features, 1))

    def forward(self, x):
        return self.net(x)


class Decoder(nn.Module):
    """culled window (B, n + 1, q, q) (features + view-field channel) -> image (B, C, q, q) in [-1, 1]."""

    def __init__(self, cfg: MemoryConfig):
        super().__init__()
        w = cfg.width
        self.net = nn.Sequential(nn.Conv2d(cfg.features + 1, w, 3, padding=1), nn.LeakyReLU(0.2),
                                 *[ResBlock(w) for _ in range(4)], nn.Conv2d(w, cfg.channels, 3, padding=1), nn.Tanh())

    def forward(self, x):
        return self.net(x)


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
