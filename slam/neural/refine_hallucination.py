"""Retraining the occupancy mask and the hallucination module of a trained memory, the memory frozen.

Why: a model trained with ``occ_weight`` 0 (both shipped memories were) has an occupancy LSTM that no
loss reached; its mask b = sigmoid(h) lies in (0.27, 0.73) and, measured on ``planar_3d``, in 0.36-0.42 on every
cell, observed or not. The hallucination module mixes ``b * psi + (1 - b) * filled``, so with that mask it cannot
pass observed cells through: measured on 8 samples of the test rooms, the shipped 3D module changed the observed
cells by 0.061 (mean |filled - psi|, about half their magnitude 0.127) and the never-observed ones by 0.0035 - the
opposite of its job - and its hallucination scored the same as no module at all (0.141 / 0.703 / 0.597 both, 96
samples). About half of the cells a later view culls were never observed by the first five (52 %), so a module
that fills them has room to help.

Two stages, on the model's own training data (3D: its training rooms; 2D: training walks), every other weight
(encoder, localisation, memory LSTM, recall decoder) frozen and byte-identical - localisation and anamnesis do not
change:

1. **occupancy** (``occ_steps``): the model switched to the ``affine`` mask b = (h + 1) / 2 and its occupancy LSTM
   trained alone to the observed cells ``seen`` (L_occ, BCE - the deviation documented in
   :mod:`slam.neural.memory`), Adam at :data:`slam.neural.config.OCC_LR`, memories registered at the true poses.
2. **hallucination** (``steps``): the module and a new patch discriminator, both re-initialised N(0, 0.02), trained
   with the thesis' L_hallu + L_corrupt + 0.05 L_GAN (:func:`slam.neural.losses.hallucination_step`, the same step
   as the memory training's last phase), Adam (beta1 0.5) at ``lr`` falling linearly to a tenth over the stage -
   as the hallucination phase of the 3D ``cpu-long`` recipe, which lies wholly inside its learning-rate decay.

The top-view decoder (:mod:`slam.neural.topview`) reads the occupancy, so a 3D model's is retrained afterwards by
:func:`slam.neural.run.refine_hallucination_folder`. Checkpointed every ``checkpoint_every`` steps of either stage
(occupancy LSTM, module, discriminator, their optimisers, the batch generator); a re-run continues.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Callable

import numpy as np

from slam.neural.config import OCC_LR, HallucinationConfig

__all__ = ["refine_hallucination"]


def refine_hallucination(model, bank, cfg, hcfg: HallucinationConfig, checkpoint: str | Path | None = None,
                         progress: bool = True, log: Callable[[str], None] | None = None,
                         on_checkpoint: Callable[[int], None] | None = None) -> dict:
    """Retrain ``model``'s occupancy LSTM (switching it to the ``affine`` mask) and hallucination module in place on
    ``bank`` (3D: :class:`slam.neural.data3d.WorldBank`; 2D: :class:`slam.neural.data.Walks2D`); ``cfg``: the
    model's :class:`slam.neural.config.NeuralTrainConfig` (batch, steps, observe). Returns the info saved with the
    model (config, losses, seconds). ``on_checkpoint(step)``: called after each checkpoint (and on a resume)."""
    import torch
    import torch.nn.functional as F

    from slam.neural.data import batch_tensors
    from slam.neural.losses import hallucination_step
    from slam.neural.networks import PatchDiscriminator, init_weights
    from data_tools.training import RESUMABLE_CHANGES, TrainingState, linear_ramp, run_steps, set_lr, settings_of
    hcfg.validate()
    torch.manual_seed(hcfg.seed)
    dev = next(model.parameters()).device
    model.cfg.occupancy = "affine"
    init_weights(model.hallucinator)
    disc = PatchDiscriminator(model.cfg).to(dev)
    init_weights(disc)
    for p in model.parameters():
        p.requires_grad_(False)
    for p in (*model.occ_lstm.parameters(), *model.hallucinator.parameters()):
        p.requires_grad_(True)
    opt_occ = torch.optim.Adam(model.occ_lstm.parameters(), lr=OCC_LR, betas=(0.5, 0.999))
    opt_h = torch.optim.Adam(model.hallucinator.parameters(), lr=hcfg.lr, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(disc.parameters(), lr=hcfg.lr, betas=(0.5, 0.999))
    rng = np.random.default_rng(hcfg.seed + 2)
    vm = torch.from_numpy(bank.wedge.astype(np.float32)).to(dev)
    img_mask = 1.0 if model.cfg.input == "image" else vm        # 3D recalls whole images, 2D the view field
    parts = {"occ_lstm": model.occ_lstm, "hallucinator": model.hallucinator, "disc": disc, "opt_occ": opt_occ,
             "opt_h": opt_h, "opt_d": opt_d}
    total = hcfg.occ_steps + hcfg.steps
    state = TrainingState(checkpoint, parts, rng, "hallucination training checkpoint", map_location=dev, on_save=on_checkpoint,
                          settings=settings_of(hcfg, RESUMABLE_CHANGES + ("steps",)))
    start, hist = state.resume(log, total) or (0, [])

    def lr(step: int) -> None:                  # stage 2: linear to a tenth from its start
        if step >= hcfg.occ_steps:
            set_lr((opt_h, opt_d), hcfg.lr * linear_ramp(step - hcfg.occ_steps, 1, hcfg.steps, 0.1))

    def step_fn(step: int) -> dict:
        obs, cells, allo, exact = batch_tensors(bank, rng, cfg.batch, cfg.steps, dev)
        if step < hcfg.occ_steps:
            model.eval()
            out = model(obs, vm, allo, cells=cells)
            l_occ = F.binary_cross_entropy(out["occ"].clamp(1e-6, 1 - 1e-6), out["seen"])
            opt_occ.zero_grad(set_to_none=True)
            l_occ.backward()
            opt_occ.step()
            return {"occ": float(l_occ.detach())}
        model.train()         # spectral norm's power iteration runs in training mode, as in the memory training
        losses = hallucination_step(model, disc, opt_h, opt_d, obs, allo, vm, cfg.observe, cells, img_mask, exact)
        model.eval()
        return losses

    # save_last: a re-run after an interruption in a later phase (the top-view decoder) skips this one
    seconds = run_steps(step_fn, total, start=start, history=hist, log_every=25, log_also=(hcfg.occ_steps,),
                        state=state, checkpoint_every=hcfg.checkpoint_every, lr=lr, progress=progress,
                        desc="training occupancy + hallucination",
                        postfix=lambda r: " ".join(f"{k} {v:.4f}" for k, v in r.items() if k != "step"))
    model.eval()
    for p in model.parameters():
        p.requires_grad_(True)
    occ_log = [h for h in hist if "occ" in h]
    hal_log = [h for h in hist if "hallu" in h]
    return {"config": asdict(hcfg), "occ_log": occ_log[-4:], "log": hal_log[-8:],
            "seconds": round(seconds, 1), "resumed_from_step": start}
