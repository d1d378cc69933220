"""What the 2D and 3D evaluations of the neural memory share (:mod:`slam.neural.evaluate`,
:mod:`slam.neural.evaluate3d`): the recalled and hallucinated views of one batch with each module in turn switched
off (:func:`recall_ablations`), the mean image metrics of a list of rows (:func:`image_summary`), the thesis' SSIM
(:func:`ssim_thesis`) and the ATE of 2D positions (:func:`rigid_ate`).

The ablations of thesis Table 4.2 are taken at inference (the thesis retrains a model without each module; here
the trained model has the module switched off, which measures how much the trained model relies on it - an
approximation): *no localisation* - every observation written at the first pose, views recalled at the true
poses; *no culling* - the decoder gets the whole q x q memory window at the pose instead of the view-field cells
(view-field channel all ones); *no hallucination module* - the later views recalled from the partial memory as it
is. Beside them: recall from a memory registered at the true poses (no localisation error).
"""
from __future__ import annotations

import numpy as np

__all__ = ["ANAMNESIS_SETS", "HALLUCINATION_SETS", "recall_ablations", "image_summary", "ssim_thesis", "rigid_ate"]

ANAMNESIS_SETS = ("anam", "anam_true_poses", "anam_no_localisation", "anam_no_culling")
"""Views at every observed pose (B, T, ...): from the memory the model registered itself, at the true poses, every
view at the first pose, without culling; 3D adds ``anam_backend`` (registered as the backend does)."""
HALLUCINATION_SETS = ("hallu", "hallu_no_module", "hallu_no_culling")
"""Views at the poses after the first ``observe`` (B, T - observe, ...): from the hole-filled partial memory, from
the partial memory as it is, the hole-filled one without culling."""


def recall_ablations(model, obs, vm, allo, exact, observe: int, cells=None, backend: dict | None = None) -> dict:
    """The views of one batch for the evaluation: ``obs`` (B, T, C, ...) observations, ``vm`` (q, q) view field,
    ``allo`` (B, T, 3) integer true allocentric poses (the teacher poses), ``exact`` (B, T, 3) the poses to recall
    at (integers or, 3D, reals), ``cells`` the 3D pixels' cells (or None), ``backend``: keyword arguments of the
    backend's registration (``motion_prior``, ``score``) for ``anam_backend`` (None: not computed). Returns the
    sets of :data:`ANAMNESIS_SETS` and :data:`HALLUCINATION_SETS` as tensors (B, T or T - observe, C, H, W) and the
    registrations: ``own`` (the model's own, the thesis' plain field), ``true`` (at the true poses), ``filled``
    (the hole-filled partial memory)."""
    import torch

    from slam.neural.memory import memory_index
    B, T = obs.shape[:2]
    k = observe
    full = torch.ones_like(vm)

    def cut(x, n):
        return None if x is None else x[:, :n]
    with torch.no_grad():
        own = model(obs, vm, None, cells=cells)
        tru = model(obs, vm, allo, cells=cells)
        part = model(obs[:, :k], vm, allo[:, :k], cells=cut(cells, k))
        filled = model.hallucinate(part["psi"], part["occ"])
        nol = model(obs, vm, allo[:, :1].expand_as(allo).contiguous(), cells=cells)
        every, later = exact.flatten(0, 1), exact[:, k:].flatten(0, 1)

        def recall(psi, poses, n, mask=vm):
            return model.recall(psi, poses, mask, memory_index(psi, n)).reshape(B, n, *model_shape(model, obs))
        out = {"own": own, "true": tru, "filled": filled,
               "anam": recall(own["psi"], every, T), "anam_true_poses": recall(tru["psi"], every, T),
               "anam_no_localisation": recall(nol["psi"], every, T),
               "anam_no_culling": recall(own["psi"], every, T, full),
               "hallu": recall(filled, later, T - k), "hallu_no_module": recall(part["psi"], later, T - k),
               "hallu_no_culling": recall(filled, later, T - k, full)}
        if backend is not None:
            reg = model(obs, vm, None, cells=cells, **backend)
            out["anam_backend"] = recall(reg["psi"], every, T)
    return out


def model_shape(model, obs) -> tuple:
    """(C, H, W) of the model's recalled views: the observations' in 2D, the decoder's image size in 3D."""
    if model.cfg.input == "image":
        return (model.cfg.channels, *model.cfg.image_size)
    return tuple(obs.shape[2:])


def image_summary(rows, names: tuple = ("l1", "ssim_thesis", "ssim_skimage")) -> dict:
    """Means over the rows (one per view; columns ``names``) of image metrics, NaN rows of a column left out."""
    v = np.asarray(rows, float)
    return {name: float(np.nanmean(v[:, i])) for i, name in enumerate(names)}


def ssim_thesis(a: np.ndarray, b: np.ndarray, n: int = 5, c1: float = 0.001, c2: float = 0.003) -> float:
    """Thesis Eq. 4.14: mean over non-overlapping n x n windows of grey [0, 1] images (H, W)."""
    H, W = a.shape
    vals = []
    for i in range(0, H - n + 1, n):
        for j in range(0, W - n + 1, n):
            x, y = a[i:i + n, j:j + n].astype(np.float64), b[i:i + n, j:j + n].astype(np.float64)
            mx, my = x.mean(), y.mean()
            vx, vy, cxy = x.var(), y.var(), ((x - mx) * (y - my)).mean()
            vals.append(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2)))
    return float(np.mean(vals)) if vals else float("nan")


def rigid_ate(est: np.ndarray, gt: np.ndarray) -> float:
    """RMSE (px) of (N, 2) positions after the best proper rotation + translation
    (:func:`slam.metrics.umeyama_alignment` in 2D); estimates all at one point (no rotation to fit): after the
    best translation."""
    from data_tools.errors import RealgapError
    from slam.metrics import umeyama_alignment
    est, gt = np.asarray(est, float), np.asarray(gt, float)
    try:
        R, t, _ = umeyama_alignment(est.T, gt.T)
    except RealgapError:
        R, t = np.eye(2), gt.mean(0) - est.mean(0)
    al = est @ R.T + t
    return float(np.sqrt(np.mean(np.sum((al - gt) ** 2, 1))))
