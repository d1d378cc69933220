"""A trained top-view decoder of the 3D neural memory: memory cells -> the colour of the floor plan.

The memory psi (n x U x U) is allocentric and seen from above, but its features are learned: the
thesis reads it out only through culled windows decoded into the agent's view (anamnesis). The
``slam run --backend neural`` snapshot also wants a picture of the whole map, so this module learns
a second, per-cell read-out:

* **target** (:func:`topview_targets`): the mean colour of the RGB-D pixels that fall into each memory
  cell, over all views of a training sequence, each view ground-projected into its egocentric grid at
  its true (grid-rounded) allocentric pose - exactly the placement the memory's registration uses
  (:func:`slam.neural.memory.register` with a one-hot field), so target and memory are aligned cell by
  cell. Cells no pixel reached have no target.
* **model** (:class:`TopViewDecoder`): features + occupancy (n + 1 channels) -> a 3x3 convolution, a
  residual block and a 1x1 convolution to RGB in [-1, 1] (tanh). The 3x3 context lets a cell borrow
  from its neighbours (the memory is written at 15 cm / 30 deg grid resolution), nothing more: the
  decoder is a read-out, not a second hallucination module.
* **training** (:func:`train_topview`): the memory model is frozen (its weights stay byte-identical);
  memories are built from training sequences with the true poses (teacher-forced registration, as the
  hallucination phase does), and the decoder minimises the L1 to the target on the cells that have one.
  Adam (beta1 = 0.5, lr 2e-4, N(0, 0.02) weights), as the rest of the model.

It is stored beside the memory's weights as ``topview.pt`` (``save_topview`` / ``load_topview``); a model
folder without it still works, its snapshot then has only the principal-component picture
(``features.png``). Approximation: colour only (the depth channel of the images is the distance from
the camera, not a property of the cell, so it has no top-view meaning).
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import nn

from data_tools.errors import FormatError
from slam.neural.memory import register
from slam.neural.networks import ResBlock, init_weights

__all__ = ["TopViewDecoder", "project_sum", "topview_targets", "train_topview", "save_topview", "load_topview",
           "decode_topview", "topview_picture", "TOPVIEW_FILE"]

TOPVIEW_FILE = "topview.pt"
"""File of the decoder's weights inside a model folder."""


class TopViewDecoder(nn.Module):
    """(B, n + 1, U, U) memory features + occupancy -> (B, 3, U, U) RGB in [-1, 1]."""

    def __init__(self, features: int, width: int = 16):
        super().__init__()
        self.features, self.width = int(features), int(width)
        self.net = nn.Sequential(nn.Conv2d(self.features + 1, self.width, 3, padding=1), nn.LeakyReLU(0.2),
                                 ResBlock(self.width), nn.Conv2d(self.width, 3, 1), nn.Tanh())
        init_weights(self)

    def forward(self, psi, occ):
        return self.net(torch.cat([psi, occ], 1))


def project_sum(values, cells, q: int):
    """(sums (B, c, q, q), counts (B, 1, q, q)) of per-pixel values (B, c, H * W) binned by their flat
    egocentric cells (B, H * W; -1 = dropped) - the mean-pool counterpart of
    :func:`slam.neural.geometry3d.project_max`."""
    B, c, N = values.shape
    ok = cells >= 0
    safe = torch.where(ok, cells, torch.full_like(cells, q * q))
    s = values.new_zeros(B, c, q * q + 1).scatter_add(2, safe[:, None].expand(B, c, N), values * ok[:, None])
    n = values.new_zeros(B, 1, q * q + 1).scatter_add(2, safe[:, None], ok[:, None].to(values.dtype))
    return s[:, :, :q * q].reshape(B, c, q, q), n[:, :, :q * q].reshape(B, 1, q, q)


def topview_targets(imgs, cells, allo, rotations: int, view: int, memory: int):
    """(colour (B, 3, U, U) in [-1, 1], seen (B, 1, U, U) bool) of sequences: images (B, T, C, H, W) with
    RGB in channels 0-2, their pixels' cells (B, T, r, H * W) in the r turned egocentric grids and the
    true allocentric poses (B, T, 3) (row, col, heading index; the first view at 0, 0, 0): every view's
    pixels binned in the grid turned to its heading and pasted at its position (the adjoint of the
    localisation's correlation, :func:`slam.neural.memory.register`), averaged over the views."""
    B, T = imgs.shape[:2]
    r, q, U = int(rotations), int(view), int(memory)
    P = U - q + 1
    bi = torch.arange(B, device=imgs.device)
    acc = imgs.new_zeros(B, 4, U, U)
    for t in range(T):
        k = allo[:, t, 2].long() % r
        s, n = project_sum(imgs[:, t, :3].flatten(2), cells[bi, t, k], q)
        bank = imgs.new_zeros(B, r, 4, q, q)
        bank[bi, k] = torch.cat([s, n], 1)
        field = imgs.new_zeros(B, r, P, P)
        i = allo[:, t, 0].long() + U // 2 - q // 2       # the view centred on memory cell (row + U // 2)
        j = allo[:, t, 1].long() + U // 2 - q // 2
        inside = (i >= 0) & (i < P) & (j >= 0) & (j < P)
        b = bi[inside]
        field[b, k[inside], i[inside], j[inside]] = 1.0
        acc = acc + register(field, bank)
    seen = acc[:, 3:] > 0
    return acc[:, :3] / acc[:, 3:].clamp(min=1.0), seen


def train_topview(model, bank, steps: int, batch: int = 8, seq_steps: int = 10, lr: float = 2e-4, seed: int = 0,
                  progress: bool = True, log: Callable[[str], None] | None = None, decoder=None):
    """Train a :class:`TopViewDecoder` on a frozen 3D memory ``model`` with samples of ``bank``
    (:class:`slam.neural.data3d.WorldBank`); returns (decoder in eval mode, losses per 50 steps, seconds).
    ``decoder``: continue training this one (default: a new one)."""
    cfg = model.cfg
    torch.manual_seed(seed)
    dev = next(model.parameters()).device
    dec = (decoder if decoder is not None else TopViewDecoder(cfg.features, cfg.width)).to(dev)
    opt = torch.optim.Adam(dec.parameters(), lr=lr, betas=(0.5, 0.999))
    rng = np.random.default_rng(seed)
    vm = torch.from_numpy(bank.wedge.astype(np.float32)).to(dev)
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    from data_tools.training import run_steps

    def step_fn(step: int) -> dict:
        imgs, cells, allo, _ = bank.sample(rng, batch, seq_steps)
        imgs, cells, allo = (torch.from_numpy(a).to(dev) for a in (imgs, cells, allo))
        with torch.no_grad():
            out = model(imgs, vm, allo, cells=cells)
            target, seen = topview_targets(imgs, cells, allo, cfg.rotations, cfg.view, out["psi"].shape[-1])
        pred = dec(out["psi"], out["occ"])
        loss = (torch.abs(pred - target) * seen).sum() / (3 * seen.sum()).clamp(min=1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"topview_l1": float(loss.detach())}

    hist: list = []
    dec.train()
    seconds = run_steps(step_fn, int(steps), history=hist, progress=progress, desc="training top-view decoder",
                        postfix=lambda r: f"L1 {r['topview_l1']:.3f}")
    for p in model.parameters():
        p.requires_grad_(True)
    dec.eval()
    return dec, hist, seconds


def save_topview(folder: str | Path, decoder, info: dict | None = None) -> Path:
    """MODEL/topview.pt: the decoder's state dict, its sizes and ``info`` (command, losses)."""
    from data_tools.results import atomic_write_bytes
    buf = io.BytesIO()
    torch.save({"features": decoder.features, "width": decoder.width, "state": decoder.state_dict(),
                "info": info or {}}, buf)
    p = Path(folder) / TOPVIEW_FILE
    atomic_write_bytes(p, buf.getvalue())
    return p


def load_topview(folder: str | Path, features: int):
    """The decoder of a model folder (eval mode), or None when the folder has none; one-line error when
    it does not fit a memory of ``features`` features."""
    p = Path(folder) / TOPVIEW_FILE
    if not p.is_file():
        return None
    try:
        st = torch.load(p, map_location="cpu", weights_only=True)
        if int(st["features"]) != int(features):
            raise FormatError(p, f"a top-view decoder for {st['features']} memory features, the model has {features}")
        dec = TopViewDecoder(int(st["features"]), int(st["width"]))
        dec.load_state_dict(st["state"])
    except FormatError:
        raise
    except Exception as e:
        raise FormatError(p, f"unreadable top-view decoder ({type(e).__name__})") from None
    dec.eval()
    return dec


def decode_topview(decoder, psi: np.ndarray, occ: np.ndarray) -> np.ndarray:
    """(U, U, 3) float RGB in [0, 1] of one memory psi (n, U, U) with occupancy (U, U)."""
    with torch.no_grad():
        y = decoder(torch.from_numpy(np.asarray(psi, np.float32))[None],
                    torch.from_numpy(np.asarray(occ, np.float32))[None, None])
    return ((y[0].permute(1, 2, 0).numpy() + 1.0) / 2.0).clip(0.0, 1.0)


def topview_picture(rgb01: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(U, U, 3) uint8 BGR for a PNG: the decoded colours on ``seen`` cells, dimmed to a quarter elsewhere
    (unobserved cells are decoded too - what the memory holds there is shown, but marked)."""
    a = np.where(np.asarray(seen, bool)[..., None], rgb01, 0.25 * rgb01)
    return (a[..., ::-1] * 255.0 + 0.5).astype(np.uint8)
