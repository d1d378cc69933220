"""The losses of the neural memory's training (thesis 4.3-4.4.1): L_loc (:func:`loc_loss`) and the hallucination
phase's update (:func:`hallucination_step`: L_hallu + L_corrupt + the non-saturating GAN loss, and the
discriminator's), shared by the memory training and ``neural refine-hallucination``."""
from __future__ import annotations

__all__ = ["loc_loss", "hallucination_step", "GAN_WEIGHT"]

GAN_WEIGHT = 0.05
"""Weight of the generator's GAN loss beside L_hallu + L_corrupt."""


def loc_loss(logits, truth_field):
    """Thesis Eq. 4.6 per step: -[p log p~ + (1 - p) log(1 - p~)] summed over the field, averaged over t >= 1."""
    import torch
    lg = logits[:, 1:].flatten(2)
    logp = torch.log_softmax(lg, -1)
    p = truth_field[:, 1:].flatten(2)
    inside = p.sum(-1) > 0                  # the true pose lies in the searched window
    pos = -(p * logp).sum(-1)
    neg = -((1 - p) * torch.log1p(-logp.exp().clamp(max=1 - 1e-6))).sum(-1)
    return ((pos + neg) * inside).sum() / inside.sum().clamp(min=1)


def hallucination_step(model, disc, opt_h, opt_d, obs_t, allo_t, vm, observe: int, cells_t=None, img_mask=None,
                       exact_t=None) -> dict:
    """One hallucination update: memorise the first ``observe`` steps (no gradient into the memory
    path), fill the holes, predict the later views (recalled at ``exact_t``, default ``allo_t``);
    discriminator on culled windows."""
    import torch
    import torch.nn.functional as F

    from slam.neural.memory import memory_index
    B, T = obs_t.shape[:2]
    k = observe
    img_mask = vm if img_mask is None else img_mask
    with torch.no_grad():
        part = model(obs_t[:, :k], vm, allo_t[:, :k], cells=None if cells_t is None else cells_t[:, :k])
        full = model(obs_t, vm, allo_t, cells=cells_t)
    filled = model.hallucinate(part["psi"], part["occ"])
    later = allo_t[:, k:].flatten(0, 1)
    later_exact = (allo_t if exact_t is None else exact_t)[:, k:].flatten(0, 1)
    rec = model.recall(filled, later_exact, vm, memory_index(filled, T - k))
    l_hallu = (torch.abs(rec - obs_t[:, k:].flatten(0, 1)) * img_mask).mean()
    l_corrupt = (torch.abs(filled - part["psi"]) * part["occ"]).mean()
    fake = model.cull(filled, later, vm, memory_index(filled, T - k))[:, :-1]
    real = model.cull(full["psi"], later, vm, memory_index(full["psi"], T - k))[:, :-1]
    l_gan = F.softplus(-disc(fake)).mean()
    loss = l_hallu + l_corrupt + GAN_WEIGHT * l_gan
    opt_h.zero_grad(set_to_none=True)
    loss.backward()
    opt_h.step()
    d_loss = F.softplus(-disc(real.detach())).mean() + F.softplus(disc(fake.detach())).mean()
    opt_d.zero_grad(set_to_none=True)
    d_loss.backward()
    opt_d.step()
    return {"hallu": float(l_hallu.detach()), "corrupt": float(l_corrupt.detach()), "disc": float(d_loss.detach())}
