"""Training the neural memory (thesis 4.3-4.4.1), in three phases, resumable.

1. ``pretrain`` (``pretrain_steps``): encoder and decoder as an auto-encoder of single views.
2. ``memory``: encoder, LSTMs, decoder on whole sequences: L_loc (binary cross-entropy between the
   pose field and the one-hot true pose, thesis Eq. 4.6) + L_anam (L1 of the recalled views at
   the true poses). Registration uses the predicted field; during the first ``teacher_steps`` it
   uses the true pose with a probability falling linearly from 1 to 0 (teacher forcing: without
   it the memory is noise while localisation is still random, and neither learns - a deviation
   from the thesis, which does not describe how it starts).
3. ``hallucination`` (after ``hallucination_from``): the hallucination AE on the final memory,
   L_hallu (L1 of views at the poses the agent visits *after* the first ``observe`` steps,
   decoded from the hole-filled memory of those first steps) + L_corrupt (masked by occupancy) +
   the non-saturating GAN loss against the patch discriminator (trained on culled windows of the
   full memory as real, of the hole-filled partial memory at unvisited poses as fake).

The configuration is :class:`slam.neural.config.NeuralTrainConfig`, the batches come from
:func:`slam.neural.data.batch_source`, the losses from :mod:`slam.neural.losses`. Adam (beta1 = 0.5, lr 2e-4),
weights N(0, 0.02), as in the thesis. ``checkpoint.pt`` every ``checkpoint_every``
steps (models, optimisers, step, random states; :class:`data_tools.training.TrainingState`): a re-run continues
there. The loop is :func:`data_tools.training.run_steps`, shared with every other trainer.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from data_tools.errors import ConfigError
from data_tools.training import TrainingState, linear_ramp, run_steps, set_lr, settings_of
from slam.neural.config import OCC_LR, NeuralTrainConfig

__all__ = ["train_memory", "TrainLog", "lr_factor"]


@dataclass
class TrainLog:
    """What a training run did: the loss log (records of :func:`data_tools.training.run_steps`), the seconds of
    this run and the step it resumed from."""

    steps: list = field(default_factory=list)
    seconds: float = 0.0
    resumed_from: int = 0


def lr_factor(cfg: NeuralTrainConfig, step: int) -> float:
    """The learning rate of ``step`` over the base one: 1 until ``lr_decay_from``, then linear to ``lr_final`` at
    the last step (:func:`data_tools.training.linear_ramp`)."""
    return linear_ramp(step, cfg.lr_decay_from, cfg.iterations, cfg.lr_final)


def train_memory(cfg: NeuralTrainConfig, checkpoint: str | Path | None = None, progress: bool = True,
                 log: Callable[[str], None] | None = None, simulate=None,
                 on_checkpoint: Callable[[int], None] | None = None):
    """Train; returns (model, discriminator, TrainLog); the model's configuration is ``cfg.resolved().model``.
    3D: ``simulate`` makes missing training rooms (:data:`slam.neural.data3d.Simulator`). ``on_checkpoint(step)`` is called after each checkpoint is written
    (and with the resumed step on a resume): the command's progress marker follows it."""
    import numpy as np
    import torch
    import torch.nn.functional as F

    from slam.neural.data import batch_source, batch_tensors
    from slam.neural.losses import hallucination_step, loc_loss
    from slam.neural.memory import NeuralMemory, memory_index
    from slam.neural.networks import PatchDiscriminator, init_weights
    cfg = cfg.validate().resolved()
    dev = torch.device(cfg.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' requested but no GPU is available here (use --preset cpu)")
    torch.manual_seed(cfg.seed)
    source = batch_source(cfg, simulate, progress, log)
    mcfg = cfg.model
    model = NeuralMemory(mcfg).to(dev)
    if cfg.lstm_forget_bias:
        with torch.no_grad():
            for cell in (model.lstm, model.occ_lstm):
                hs = cell.hidden_size
                cell.bias_ih[hs:2 * hs].fill_(float(cfg.lstm_forget_bias))    # gate order: input, forget, cell, output
    disc = PatchDiscriminator(mcfg).to(dev)
    init_weights(disc)
    occ_own = cfg.occ_weight > 0       # a trained mask: its LSTM learns on its own optimiser, at OCC_LR
    main_params = [p for n, p in model.named_parameters()
                   if not n.startswith("hallucinator") and not (occ_own and n.startswith("occ_lstm"))]
    opt = torch.optim.Adam(main_params, lr=cfg.lr, betas=(0.5, 0.999))
    opt_occ = torch.optim.Adam(model.occ_lstm.parameters(), lr=OCC_LR, betas=(0.5, 0.999)) if occ_own else None
    opt_h = torch.optim.Adam(model.hallucinator.parameters(), lr=cfg.lr, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.lr, betas=(0.5, 0.999))
    rng = np.random.default_rng(cfg.seed)
    vm = torch.from_numpy(source.wedge.astype(np.float32)).to(dev)
    tlog = TrainLog()
    parts = {"model": model, "disc": disc, "opt": opt, "opt_h": opt_h, "opt_d": opt_d}
    if occ_own:
        parts["opt_occ"] = opt_occ
    state = TrainingState(checkpoint, parts, rng, "training checkpoint", map_location=dev, on_save=on_checkpoint,
                          settings=settings_of(cfg))
    resumed = state.resume(log, cfg.iterations)
    if resumed is not None:
        tlog.resumed_from, tlog.steps = resumed
    img_mask = 1.0 if cfg.mode == "3d" else vm         # 3D recalls whole images, 2D the view field

    def step_fn(step: int) -> dict:
        obs_t, cells_t, allo_t, exact_t = batch_tensors(source, rng, cfg.batch, cfg.steps, dev)
        # exact_t: the recall poses, in 3D not rounded to the grid
        T = obs_t.shape[1]
        losses = {}
        if step < cfg.pretrain_steps:
            x = obs_t.flatten(0, 1)
            f = model.encode(obs_t, cells_t).flatten(0, 1)
            # each view's own grid as a memory (U = q), recalled at its centre: the auto-encoder of single views
            rec = model.recall(f, f.new_zeros(len(x), 3), vm)
            loss = (torch.abs(rec - x) * img_mask).mean()
            losses["anam"] = float(loss.detach())
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            return losses
        s = step - cfg.pretrain_steps
        p_teacher = max(0.0, 1.0 - s / max(cfg.teacher_steps, 1))
        teacher = allo_t if rng.random() < p_teacher else None
        out = model(obs_t, vm, teacher, cells=cells_t)
        Wp = out["logits"].shape[-1]
        truth = torch.stack([model.local_one_hot(allo_t[:, t], out["centres"][:, t], Wp)
                             for t in range(cfg.steps)], 1)
        l_loc = loc_loss(out["logits"], truth)
        rec = model.recall(out["psi"], exact_t.flatten(0, 1), vm, memory_index(out["psi"], T))
        l_anam = (torch.abs(rec - obs_t.flatten(0, 1)) * img_mask).mean()
        loss = cfg.loc_weight * l_loc + l_anam
        losses.update(loc=float(l_loc.detach()), anam=float(l_anam.detach()))
        if occ_own:       # its gradient reaches the occupancy LSTM only (its input is detached)
            l_occ = F.binary_cross_entropy(out["occ"].clamp(1e-6, 1 - 1e-6), out["seen"])
            loss = loss + cfg.occ_weight * l_occ
            losses["occ"] = float(l_occ.detach())
            opt_occ.zero_grad(set_to_none=True)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if occ_own:
            opt_occ.step()
        if step >= cfg.hallucination_from:
            losses.update(hallucination_step(model, disc, opt_h, opt_d, obs_t, allo_t, vm, cfg.observe, cells_t,
                                              img_mask, exact_t))
        return losses

    model.train()
    tlog.seconds = run_steps(step_fn, cfg.iterations, start=tlog.resumed_from, history=tlog.steps,
                             log_every=cfg.log_every, state=state, checkpoint_every=cfg.checkpoint_every,
                             lr=lambda step: set_lr((opt, opt_h, opt_d), cfg.lr * lr_factor(cfg, step)),
                             progress=progress, desc="training neural memory")
    model.eval()
    return model, disc, tlog
