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

3D (``input = "image"``, thesis 4.4.3): the encoder runs on the RGB-D image (4 x 30 x 40) and its
per-pixel features are ground-projected (max-pool per cell, :func:`slam.neural.geometry3d.project_max`)
into the egocentric grid (15 cm cells; 33 x 33 in the 3D `cpu` preset, 49 x 49 in the shipped planar_3d; the
camera at the centre looking up the grid). The
rotation bank of r = 12 headings (30 deg, the thesis' Doom turn) is made by projecting the pixels into
each turned grid (points turned, then binned): exact, unlike resampling a grid - a deviation that also
keeps the bank cheap. Recall: the memory window at the pose rounded to the grid is culled
(turned by ``kornia.geometry.transform.rotate`` for headings that are not quarter turns) and an
:class:`ImageDecoder` learns the back-projection. Poses are estimated on the 15 cm / 30 deg grid; the ``neural`` registration
backend refines the field's maximum to sub-cell precision.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from slam.neural.config import POSE_SCORES, MemoryConfig
from slam.neural.fields import peak_poses
from slam.neural.networks import Decoder, Encoder, Hallucinator, ImageDecoder, init_weights

__all__ = ["NeuralMemory", "rotation_bank", "rotate_grid", "memory_index", "correlate", "register"]


def rotate_grid(x: torch.Tensor, k: int, r: int) -> torch.Tensor:
    """(B, c, q, q) turned counter-clockwise (seen from above) by k / r of a full turn: exact
    ``torch.rot90`` for multiples of 90 deg, else bilinear resampling about the centre cell
    (``kornia.geometry.transform.rotate``)."""
    if (4 * k) % r == 0:
        return torch.rot90(x, (4 * k) // r, dims=(-2, -1))
    from kornia.geometry.transform import rotate
    ang = torch.full((x.shape[0],), 360.0 * k / r, dtype=x.dtype, device=x.device)
    return rotate(x, ang, mode="bilinear", padding_mode="zeros", align_corners=True)


def memory_index(psi: torch.Tensor, n: int) -> torch.Tensor:
    """(B * n,) memory index of n consecutive poses per memory (0 x n, 1 x n, ...): the ``index`` of
    :meth:`NeuralMemory.cull` / :meth:`NeuralMemory.recall` when every memory is read at n poses."""
    return torch.arange(psi.shape[0], device=psi.device).repeat_interleave(n)


def rotation_bank(o: torch.Tensor, r: int = 4) -> torch.Tensor:
    """(B, n, q, q) -> (B, r, n, q, q): o turned counter-clockwise by k / r of a full turn, k = 0..r-1
    (quarter turns exact; see :func:`rotate_grid`)."""
    return torch.stack([rotate_grid(o, k, r) for k in range(r)], 1)


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
        self.cfg = cfg.validate()
        self.encoder = Encoder(cfg)
        if cfg.input == "image":
            self.decoder = ImageDecoder(cfg)
        else:
            self.decoder = Decoder(cfg)
        self.lstm = nn.LSTMCell(cfg.features, cfg.features)
        self.occ_lstm = nn.LSTMCell(1, 1)
        self.hallucinator = Hallucinator(cfg)
        self.log_beta = nn.Parameter(torch.tensor(0.0))
        init_weights(self)

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
        allocentric poses instead of the predicted field (training warm-up; integers: a one-hot field), or None;
        ``memory``: side
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
        if teacher is not None and teacher.is_floating_point():
            raise ValueError("teacher poses must be integers (allocentric cells and heading indices)")
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
        for t in range(T):
            if image:
                bank = self._image_bank(f_img[:, t], cells[:, t]) * mbank         # (B, r, n, q, q)
            else:
                bank = rotation_bank(feats[:, t] * m, r)                          # (B, r, n, q, q)
            if teacher is None or t == 0:
                want = est[:, :2].clone()
            else:
                want = teacher[:, t - 1, :2].clone()
            # the window starts R + q//2 cells before the wanted centre, moved inside the memory at its borders;
            # ``centre`` is the allocentric position of the window's middle (field index R, R)
            start = (want + U // 2 - R - h2).clamp(0, U - Wc)
            centre = start + R + h2 - U // 2
            ri = start[:, 0][:, None, None] + off[None, :, None]                # (B, Wc, 1)
            ci = start[:, 1][:, None, None] + off[None, None, :]                # (B, 1, Wc)
            if t == 0:       # the first view: at the origin, unrotated
                field = self.local_one_hot(torch.zeros(B, 3, dtype=torch.long, device=obs.device), centre, Wp)
                lg = obs.new_zeros(B, r, Wp, Wp)
            else:
                hw = h.view(B, Up, Up, n)[bi, ri, ci].permute(0, 3, 1, 2)       # (B, n, Wc, Wc): the window
                if score == "overlap":
                    sw = seen.view(B, Up, Up, 1)[bi, ri, ci].permute(0, 3, 1, 2)  # (B, 1, Wc, Wc) observed cells
                    lg = self._overlap_score(hw, sw, bank, mbank, m)
                else:
                    lg = self._score(hw, bank, m)
                post = lg
                if motion_prior is not None:       # centred on the previous step's estimate
                    post = lg + self._log_motion_prior(est.float(), centre, Wp, motion_prior)
                field = torch.softmax(post.flatten(1), 1).view_as(lg)
                if teacher is not None:
                    field = self.local_one_hot(teacher[:, t], centre, Wp)
            reg = register(field, bank)                                         # (B, n, Wc, Wc)
            regm = register(field, mbank).clamp(0, 1)
            x = obs.new_zeros(B, Up, Up, n).index_put((bi, ri, ci), reg.permute(0, 2, 3, 1))
            xm = obs.new_zeros(B, Up, Up, 1).index_put((bi, ri, ci), regm.permute(0, 2, 3, 1))
            h, c = self.lstm(x.view(-1, n), (h, c))                             # every cell, shared weights
            oh, oc = self.occ_lstm(xm.detach().view(-1, 1), (oh, oc))    # the mask's loss stays in its LSTM
            seen = torch.maximum(seen, (xm.view(-1, 1) > 0.5).to(seen.dtype))
            est = peak_poses(field, centre).detach()
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

    def local_one_hot(self, poses: torch.Tensor, centre: torch.Tensor, Wp: int) -> torch.Tensor:
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
            out[sel] = rotate_grid(w[sel], -int(k), r)
        m = view_mask.to(psi.dtype)[None, None]
        return torch.cat([out * m - (1 - m), m.expand(N, 1, q, q)], 1)

    def recall(self, psi: torch.Tensor, poses: torch.Tensor, view_mask: torch.Tensor,
               index: torch.Tensor | None = None) -> torch.Tensor:
        """(N, C, q, q) decoded views (3D: (N, C, H, W) images) of the memories at the allocentric ``poses`` (N, 3):
        (row, col, heading index), integers or - 3D - reals (exact poses, rounded to the grid by :meth:`cull`)."""
        return self.decoder(self.cull(psi, poses, view_mask, index))

    def hallucinate(self, psi: torch.Tensor, occ: torch.Tensor) -> torch.Tensor:
        return self.hallucinator(psi, occ)
