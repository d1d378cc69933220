"""The SynDA generator h_G (thesis section 5.3.1, Fig. 5.4): one encoder, one decoder per synthetic
modality, and a self-attentive distillation module h_R that decodes the final output.

* Encoder h_E: blocks of conv 4x4 stride 2 - batch norm - LeakyReLU(0.2), the side halving from
  ``size`` (64) down to 1x1 x ``widths[-1]`` (512 in the ``gpu`` preset): the bottleneck code.
* Decoders h_D^m (one per modality of ``decoders``): blocks of transposed conv 4x4 stride 2 -
  batch norm - ReLU, dropout 0.5 in the first ``dropout_blocks``; the output of each block is
  concatenated with the encoder block of the same side (U-Net skips, switchable); a final conv
  4x4 stride 1 gives the logits, tanh gives maps in [-1, 1] (the mask stays logits, for its
  cross-entropy loss).
* Distillation h_R: every decoded modality is re-encoded by two encoder blocks (to side / 4 x
  ``distill_width``), each re-encoding goes through its own SAGAN self-attention (Zhang et al.
  2019; thesis Eq. 4.11: o + gamma v(h(o) softmax(f(o)^T g(o))), gamma learnt, initialised 0),
  the results are summed and decoded by two decoder blocks and a conv 4x4 stride 1 + tanh into
  the ``target`` modality: the final output.

Deviations from Fig. 5.4, on purpose:

* The first and the last (1x1) encoder blocks have no batch norm (as pix2pix, whose U-Net the
  figure follows): batch statistics of a 1x1 map are those of the batch alone, and a batch of one
  could not be normalised at all.
* The mask enters h_R as probabilities in [-1, 1] (2 sigmoid - 1, or 2 softmax - 1 for
  classes), the same range as the other modalities; its decoder output stays logits.
* The last decoder block outputs ``widths[0]`` channels (the figure: C_m) before the 4x4 conv.
* Dropout acts in training only (``eval()`` turns it off; pix2pix keeps it at test time as its
  noise source, which a mapping in front of a recogniser should not have: outputs are repeatable).
"""
from __future__ import annotations

import math

import torch
from torch import nn

from data_tools.errors import FormatError
from recog.synda.config import GeneratorConfig, input_channels

__all__ = ["SelfAttention", "Generator", "check_input"]


def _enc(c_in: int, c_out: int, norm: bool) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, 4, 2, 1, bias=not norm)]
    if norm:
        layers.append(nn.BatchNorm2d(c_out))
    layers.append(nn.LeakyReLU(0.2))
    return nn.Sequential(*layers)


def _dec(c_in: int, c_out: int, dropout: float) -> nn.Sequential:
    layers: list[nn.Module] = [nn.ConvTranspose2d(c_in, c_out, 4, 2, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU()]
    if dropout > 0:
        layers.append(nn.Dropout(dropout))
    return nn.Sequential(*layers)


def _head(c_in: int, c_out: int) -> nn.Sequential:
    """conv 4x4 stride 1 keeping the side (padding 1 before, 2 after: a 4-tap kernel has no centre)."""
    return nn.Sequential(nn.ZeroPad2d((1, 2, 1, 2)), nn.Conv2d(c_in, c_out, 4))


class SelfAttention(nn.Module):
    """SAGAN self-attention on a (B, C, H, W) map: query/key 1x1 convs to C/8 channels, value 1x1
    conv to C, attention softmax over the H W positions, out = x + gamma * attended (gamma a
    learnt scalar, 0 at the start so the block begins as the identity)."""

    def __init__(self, channels: int):
        super().__init__()
        k = max(channels // 8, 1)
        self.query = nn.Conv2d(channels, k, 1)
        self.key = nn.Conv2d(channels, k, 1)
        self.value = nn.Conv2d(channels, channels, 1)
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q = self.query(x).flatten(2)                         # (B, k, N)
        k = self.key(x).flatten(2)                           # (B, k, N)
        attn = torch.softmax(q.transpose(1, 2) @ k, dim=-1)  # (B, N query, N key)
        v = self.value(x).flatten(2)                         # (B, C, N)
        out = (v @ attn.transpose(1, 2)).view(b, c, h, w)
        return x + self.gamma * out


class _Decoder(nn.Module):
    """Code (B, widths[-1], 1, 1) + encoder features -> (B, C_m, S, S) logits."""

    def __init__(self, cfg: GeneratorConfig, out_channels: int):
        super().__init__()
        w = list(cfg.widths)
        n = len(w)
        self.skips = cfg.skips
        blocks, c = [], w[-1]
        for i in range(n):
            c_out = w[n - 2 - i] if i < n - 1 else w[0]
            blocks.append(_dec(c, c_out, cfg.dropout if i < cfg.dropout_blocks else 0.0))
            c = c_out + (w[n - 2 - i] if cfg.skips and i < n - 1 else 0)
        self.blocks = nn.ModuleList(blocks)
        self.head = _head(c, out_channels)

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        n = len(feats)
        y = feats[-1]
        for i, block in enumerate(self.blocks):
            y = block(y)
            if self.skips and i < n - 1:
                y = torch.cat([y, feats[n - 2 - i]], 1)
        return self.head(y)


class _Distiller(nn.Module):
    """h_R: re-encode each modality (2 blocks), self-attention each, sum, decode (2 blocks) -> logits."""

    def __init__(self, cfg: GeneratorConfig, out_channels: int):
        super().__init__()
        w = cfg.distill_width
        self.reencode = nn.ModuleDict({m: nn.Sequential(_enc(cfg.channels(m), w, norm=False), _enc(w, w, norm=True))
                                       for m in cfg.decoders})
        self.attend = nn.ModuleDict({m: SelfAttention(w) if cfg.attention else nn.Identity() for m in cfg.decoders})
        self.decode = nn.Sequential(_dec(w, w, 0.0), _dec(w, w, 0.0))
        self.head = _head(w, out_channels)

    def forward(self, maps: dict[str, torch.Tensor]) -> torch.Tensor:
        total = None
        for m, x in maps.items():
            y = self.attend[m](self.reencode[m](x))
            total = y if total is None else total + y
        return self.head(self.decode(total))


def check_input(x, cfg: GeneratorConfig, domain: str, where=None) -> None:
    """Raise a one-line :class:`FormatError` unless ``x`` is a (B, C, S, S) float tensor with the
    domain's channel count C and the generator's side S (``where``: the file it came from)."""
    c, s = input_channels(domain), cfg.size
    if not isinstance(x, torch.Tensor) or x.dim() != 4 or x.shape[1] != c or x.shape[2] != s or x.shape[3] != s:
        shape = tuple(x.shape) if hasattr(x, "shape") else type(x).__name__
        raise FormatError(where, f"the {domain} generator takes (B, {c}, {s}, {s}) images, got {shape}")
    if not x.is_floating_point():
        raise FormatError(where, f"the {domain} generator takes float images in [-1, 1], got {x.dtype}")


class Generator(nn.Module):
    """h_G for one domain. ``forward(x)`` takes (B, C_in, S, S) inputs in [-1, 1] and returns a
    dict: one (B, C_m, S, S) map per decoded modality (tanh, the mask as logits), ``output``
    the final (B, C_target, S, S) map in [-1, 1], and ``code`` the flattened (B, widths[-1])
    bottleneck when ``cfg.triplet``."""

    def __init__(self, cfg: GeneratorConfig, domain: str = "rgb"):
        super().__init__()
        cfg.validate()
        self.cfg, self.domain = cfg, domain
        w, c = list(cfg.widths), input_channels(domain)
        enc = []
        for i, wi in enumerate(w):
            enc.append(_enc(c, wi, norm=0 < i < len(w) - 1))
            c = wi
        self.encoder = nn.ModuleList(enc)
        self.decoders = nn.ModuleDict({m: _Decoder(cfg, cfg.channels(m)) for m in cfg.decoders})
        self.distiller = _Distiller(cfg, cfg.channels(cfg.target)) if cfg.distillation else None
        self._init_weights(cfg.init_std)
        if "mask" in self.decoders:
            self._init_mask_prior(cfg.mask_prior)

    def _init_weights(self, std: float) -> None:
        for mod in self.modules():
            if isinstance(mod, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.normal_(mod.weight, 0.0, std)
                if mod.bias is not None:
                    nn.init.zeros_(mod.bias)
            elif isinstance(mod, nn.BatchNorm2d):
                nn.init.normal_(mod.weight, 1.0, std)
                nn.init.zeros_(mod.bias)

    def _init_mask_prior(self, prior: float) -> None:
        """Mask head bias = the prior's logit(s) (:attr:`GeneratorConfig.mask_prior`)."""
        bias = self.decoders["mask"].head[1].bias
        c = bias.numel()
        with torch.no_grad():
            if c == 1:
                bias.fill_(math.log(prior / (1.0 - prior)))
            else:
                bias.fill_(math.log(prior / (c - 1)))
                bias[0] = math.log(1.0 - prior)

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Encoder features, side S/2 first, the (B, widths[-1], 1, 1) code last."""
        feats = []
        for block in self.encoder:
            x = block(x)
            feats.append(x)
        return feats

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        check_input(x, self.cfg, self.domain)
        feats = self.encode(x)
        out: dict[str, torch.Tensor] = {}
        for m, dec in self.decoders.items():
            y = dec(feats)
            out[m] = y if m == "mask" else torch.tanh(y)
        if self.distiller is not None:
            maps = {m: (self._mask_map(v) if m == "mask" else v) for m, v in out.items()}
            out["output"] = torch.tanh(self.distiller(maps))
        else:
            out["output"] = out[self.cfg.target]
        if self.cfg.triplet:
            out["code"] = feats[-1].flatten(1)
        return out

    def _mask_map(self, logits: torch.Tensor) -> torch.Tensor:
        p = torch.sigmoid(logits) if logits.shape[1] == 1 else torch.softmax(logits, 1)
        return 2.0 * p - 1.0
