"""Refining the recall decoder of a trained memory, the memory frozen (3D: on more rooms; 2D: on more walks).

Why: the memory phases (:mod:`slam.neural.train`) see 12 simulated rooms; the decoder that turns a
culled memory window into an RGB-D image then learns those rooms' looks and generalises poorly -
measured on the shipped ``planar_3d`` (decoder alone retrained on its own 12 rooms: the test rooms'
hallucination SSIM *falls* from 0.58 to 0.55 while the training loss falls; on 48 rooms it rises to
0.62). The memory itself (encoder, localisation, LSTMs, hallucination module) is left byte-identical,
so localisation - and every ATE of the ``neural`` backend - is unchanged; only recall changes.

* **pool** (:func:`build_pool`): ``pool_batches`` x ``batch`` samples of ``steps`` views from the
  ``rooms`` training rooms (seeds 0 .. rooms - 1, simulated on first use; the first 12 are the memory's
  own). Per sample, as :mod:`slam.neural.evaluate3d` measures: the memory the model registers itself
  (no poses given: anamnesis, recalled at all ``steps`` views) and the memory of the first ``observe``
  views registered at the true poses and filled by the hallucination module (hallucination, recalled at
  the later views). Stored float16 in RAM (1.5 GB for the default 3600 samples; measured peak of the whole
  process 4.1 GB with 96 rooms and 7200 samples).
* **training** (:func:`refine_decoder`): random (memory, pose) pairs of the pool, the decoder's
  current weights as the start, Adam (beta1 = 0.5, lr 2e-4 falling linearly to a tenth over the last
  40 % of the steps), loss = L1 of the RGB-D image (thesis L_anam) + ``ssim_weight`` x (1 - SSIM) / 2 of
  the grey image (``kornia.losses.ssim_loss``, 5 x 5 Gaussian windows). The SSIM term is a deviation
  from the thesis' L1-only recall loss, on purpose: L1 alone makes the recall the blurred mean of what
  a window could show, which SSIM (the thesis' image metric) scores low; measured on the test rooms,
  48 rooms with L1 alone give hallucination SSIM 0.62, with the SSIM term 0.65 (L1 0.155 both).

2D (:class:`slam.neural.data.Walks2D`): the pool holds training walks of the model's agent (``rooms`` unused), the L1 is taken
on the view field and the SSIM on the view field with the truth outside it, as :mod:`slam.neural.evaluate`
measures.

Checkpointed (``checkpoint`` path: decoder, optimiser, step, random state every ``checkpoint_every``
steps); a resumed run rebuilds the same pool (same seed) and continues.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from slam.neural.config import RefineConfig

__all__ = ["build_pool", "refine_decoder", "POOL_BATCH"]

POOL_BATCH = 8
"""Samples memorised per pool batch (one forward pass of the memory)."""


def build_pool(model, bank, batches: int, batch: int, steps: int, observe: int, seed: int,
               progress: bool = True) -> dict:
    """The frozen memories to recall from: {mem (2 N, n, U, U) float16 - the N self-registered memories, then the
    N hole-filled partial ones -, poses (N, steps, 3) float32 exact allocentric poses, images (N, steps, C, H, W)
    float16 targets}, N = batches x batch (see the module docstring)."""
    import torch
    rng = np.random.default_rng(seed)
    dev = next(model.parameters()).device
    vm = torch.from_numpy(bank.wedge.astype(np.float32)).to(dev)
    N = int(batches) * int(batch)
    mem = poses = images = None           # allocated at the first batch's sizes: no copy of the whole pool at the end
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=batches, desc="memorising the refinement pool", unit="batch")
    with torch.no_grad():
        for b in range(int(batches)):
            imgs, cells, allo, P = bank.sample(rng, batch, steps)
            obs, allo_t = torch.from_numpy(imgs).to(dev), torch.from_numpy(allo).to(dev)
            cells_t = None if cells is None else torch.from_numpy(cells).to(dev)
            out = model(obs, vm, None, cells=cells_t)
            part = model(obs[:, :observe], vm, allo_t[:, :observe],
                         cells=None if cells_t is None else cells_t[:, :observe])
            filled = model.hallucinate(part["psi"], part["occ"])
            if mem is None:
                mem = torch.empty((2 * N, *out["psi"].shape[1:]), dtype=torch.float16)
                poses = torch.empty((N, steps, 3), dtype=torch.float32)
                images = torch.empty((N, *imgs.shape[1:]), dtype=torch.float16)
            sl = slice(b * batch, (b + 1) * batch)
            mem[sl] = out["psi"].half().cpu()
            mem[N + b * batch:N + (b + 1) * batch] = filled.half().cpu()
            poses[sl] = torch.from_numpy(np.stack([bank.exact(p) for p in P]).astype(np.float32))
            images[sl] = torch.from_numpy(imgs).half()
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return {"mem": mem, "poses": poses, "images": images, "observe": int(observe)}


def _pairs(pool: dict, rng: np.random.Generator, n: int):
    """``n`` random (memory, pose, target) triples of the pool: (mem (n, f, U, U), poses (n, 3),
    targets (n, C, H, W))."""
    N, T = pool["poses"].shape[:2]
    k = pool["observe"]
    s = rng.integers(0, N, n)
    slot = rng.integers(0, T + (T - k), n)        # 0..T-1: anamnesis of view slot; T..: hallucination of view k + ..
    hallu = slot >= T
    t = np.where(hallu, k + slot - T, slot)
    midx = np.where(hallu, N + s, s)
    return (pool["mem"][midx].float(), pool["poses"][s, t], pool["images"][s, t].float())


def refine_decoder(model, bank, rcfg: RefineConfig, steps_per_sample: int, observe: int,
                   checkpoint: str | Path | None = None, progress: bool = True,
                   log: Callable[[str], None] | None = None,
                   on_checkpoint: Callable[[int], None] | None = None) -> dict:
    """Refine ``model.decoder`` in place on ``bank`` (3D: :class:`slam.neural.data3d.WorldBank` of ``rcfg.rooms``
    rooms; 2D: :class:`slam.neural.data.Walks2D`, ``rooms`` unused), every other weight frozen; returns the info saved with the
    model (config, losses, seconds). ``on_checkpoint(step)``: called after each checkpoint (and on a resume)."""
    import torch
    from kornia.losses import ssim_loss

    from data_tools.training import RESUMABLE_CHANGES, TrainingState, linear_ramp, run_steps, set_lr, settings_of
    rcfg.validate()
    torch.manual_seed(rcfg.seed)
    for p in model.parameters():
        p.requires_grad_(False)
    dec = model.decoder
    for p in dec.parameters():
        p.requires_grad_(True)
    opt = torch.optim.Adam(dec.parameters(), lr=rcfg.lr, betas=(0.5, 0.999))
    rng = np.random.default_rng(rcfg.seed + 1)
    state = TrainingState(checkpoint, {"decoder": dec, "opt": opt}, rng, "decoder refinement checkpoint",
                          on_save=on_checkpoint, settings=settings_of(rcfg, RESUMABLE_CHANGES + ("steps",)))
    start, hist = state.resume(log, rcfg.steps) or (0, [])
    t0 = time.perf_counter()
    model.eval()
    pool = build_pool(model, bank, rcfg.pool_batches, POOL_BATCH, steps_per_sample, observe, rcfg.seed,
                      progress=progress)
    t_pool = time.perf_counter() - t0
    dev = next(model.parameters()).device
    vm = torch.from_numpy(bank.wedge.astype(np.float32)).to(dev)
    img_mask = 1.0 if model.cfg.input == "image" else vm      # as the memory's training: 2D on the view field only

    def step_fn(step: int) -> dict:
        mem, poses, y = (x.to(dev) for x in _pairs(pool, rng, rcfg.batch))      # the pool stays in host memory
        pred = model.recall(mem, poses, vm)
        l1 = ((pred - y).abs() * img_mask).mean()
        pred = pred * img_mask + y * (1 - img_mask)     # SSIM as the evaluation: the truth outside a 2D view field
        loss = l1
        s = torch.zeros((), device=dev)
        if rcfg.ssim_weight > 0:
            grey_p = ((pred[:, :3] + 1) / 2).mean(1, keepdim=True)
            grey_y = ((y[:, :3] + 1) / 2).mean(1, keepdim=True)
            s = ssim_loss(grey_p, grey_y, window_size=5, max_val=1.0)      # (1 - SSIM) / 2, kornia's convention
            loss = l1 + rcfg.ssim_weight * s
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"l1": float(l1.detach()), "ssim_loss": float(s.detach())}

    dec.train()
    # the lr schedule of the memory training: constant, then linear to a tenth over the last 40 %
    run_steps(step_fn, rcfg.steps, start=start, history=hist, state=state, checkpoint_every=rcfg.checkpoint_every,
              save_last=False, lr=lambda step: set_lr((opt,), rcfg.lr * linear_ramp(step, int(0.6 * rcfg.steps),
                                                                                     rcfg.steps, 0.1)),
              progress=progress, desc="refining the recall decoder",
              postfix=lambda r: f"L1 {r['l1']:.3f} ssim loss {r['ssim_loss']:.3f}")
    dec.eval()
    for p in model.parameters():
        p.requires_grad_(True)
    from dataclasses import asdict
    return {"config": asdict(rcfg), "log": hist[-10:], "seconds": round(time.perf_counter() - t0, 1),
            "pool_seconds": round(t_pool, 1), "resumed_from_step": start}
