"""Evaluating the neural memory in 2D, in one run (thesis Table 4.1 metrics, Table 4.2-style ablations).

On test environments never seen in training (other pictures, other faces, other floor-plan
seeds), agents walk ``steps`` steps; then

* localisation: the estimated allocentric positions (the pose-field maxima) against the true
  ones - APE (per pose, px: median, mean, std; also per kind of environment: picture, face, floor
  plan) and ATE (per sequence, RMSE after the best rigid 2D fit, px); and each step localised once
  against the memory of the earlier steps registered at their true poses (localisation without the
  drift of its own earlier errors);
* anamnesis: the views at the observed poses recalled from the final memory vs the observations
  (L1 on [0, 1] images over the view field, SSIM as in the thesis - non-overlapping N x N windows,
  c1 = 0.001, c2 = 0.003 on [0, 1] grey values, N = 5 - and ``skimage.metrics.structural_similarity``;
  also per kind of environment, and at the true poses - a memory registered with the true poses - overall and
  per kind, which separates what localisation errors cost from what the decoder cannot draw: the thesis'
  Table 4.1 B numbers are on portraits only);
* hallucination: views at poses the agent visits after the first ``observe`` steps (unseen when
  the memory was built), decoded from the hole-filled memory of the first steps;
* baselines and ablations in the same run: a mosaic of the observations pasted at the true poses
  (the classic, geometry-only memory: perfect recall of what was seen, unseen pixels filled by
  OpenCV inpainting - the 2D counterpart of TSDF raycast + inpainting), the memory without the
  hallucination module, and registration with the true poses (no localisation error);
* the ablations of thesis Table 4.2 at inference, *no localisation* and *no culling*
  (:mod:`slam.neural.ablations`, shared with the 3D evaluation). With a square agent the view field is the
  whole window and "no culling" changes nothing.
"""
from __future__ import annotations

import time

import numpy as np

from slam.neural.ablations import ANAMNESIS_SETS, HALLUCINATION_SETS, image_summary, recall_ablations, rigid_ate, \
    ssim_thesis

__all__ = ["evaluate_2d"]


def _grey01(x: np.ndarray) -> np.ndarray:
    """(3, q, q) in [-1, 1] -> (q, q) grey in [0, 1]."""
    return np.clip((x.mean(0) + 1) / 2, 0, 1)


def _image_metrics(pred: np.ndarray, true: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """L1 over the view field ([0, 1] units), thesis SSIM, skimage SSIM (masked pixels set equal)."""
    from skimage.metrics import structural_similarity
    p01, t01 = np.clip((pred + 1) / 2, 0, 1), np.clip((true + 1) / 2, 0, 1)
    l1 = float(np.abs(p01 - t01)[:, mask].mean())
    pg, tg = _grey01(pred), _grey01(true)
    pg = np.where(mask, pg, tg)
    return l1, ssim_thesis(pg, tg), float(structural_similarity(pg, tg, data_range=1.0, win_size=5))


def _mosaic_views(obs: np.ndarray, allo: np.ndarray, mask: np.ndarray, U: int, seen_steps: int, req: np.ndarray):
    """The classic memory: observations pasted at the true poses into a canvas; requested views
    cropped from it, unseen pixels inpainted (cv2.INPAINT_TELEA)."""
    import cv2
    q = obs.shape[-1]
    c = U // 2
    P = q // 2
    canvas = np.zeros((U + 2 * P, U + 2 * P, 3), np.float32)
    seen = np.zeros((U + 2 * P, U + 2 * P), np.uint8)
    for t in range(seen_steps):
        r0, c0, k = allo[t]
        view = np.rot90(np.transpose(obs[t], (1, 2, 0)), k)
        mk = np.rot90(mask, k)
        a, b = r0 + c, c0 + c
        win = canvas[a:a + q, b:b + q]
        win[mk] = view[mk]
        seen[a:a + q, b:b + q][mk] = 1
    img8 = ((np.clip(canvas, -1, 1) + 1) * 127.5).astype(np.uint8)
    filled = cv2.inpaint(img8, (1 - seen).astype(np.uint8), 3, cv2.INPAINT_TELEA).astype(np.float32) / 127.5 - 1
    out = []
    for r0, c0, k in req:
        a, b = r0 + c, c0 + c
        out.append(np.transpose(np.rot90(filled[a:a + q, b:b + q], -k), (2, 0, 1)))
    return np.stack(out)


def evaluate_2d(model, cfg, sequences: int = 64, seed: int = 12345, progress: bool = True,
                examples: dict | None = None) -> dict:
    """The numbers of the module docstring for ``sequences`` test walks (a fixed seed: the same walks
    for every model evaluated with it). ``examples``: a dict filled with what the figures need
    (:func:`slam.neural.figures.write_figures`): per-pose APE and environment kinds, two walks' images."""
    import torch

    from slam.neural.data2d import AGENTS, KINDS, make_batch, view_mask
    from slam.neural.fields import peak_poses
    agent = AGENTS[cfg.agent]
    mask = view_mask(agent)
    vm = torch.from_numpy(mask.astype(np.float32))
    rng = np.random.default_rng(seed)
    U = model.cfg.memory
    ape, ate, ape_kind, one = [], [], [], []
    img_kind = {"anam": [], "hallu": []}        # the environment kind of every row of rows["anam"] / rows["hallu"]
    rows = {k: [] for k in (*ANAMNESIS_SETS, *HALLUCINATION_SETS, "mosaic_anam", "mosaic_hallu")}

    def shown(x):       # example figures: outside the view field (not measured) grey, as the observations
        return list(x.numpy() * mask)
    t0 = time.perf_counter()
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=sequences, desc="evaluating neural memory", unit="sequence")
    B, T, k = 8, cfg.steps, cfg.observe
    done = 0
    while done < sequences:
        b = min(B, sequences - done)
        _, obs, _, allo, kinds = make_batch(rng, b, agent, T, cfg.image, split="test", with_kinds=True)
        a = torch.from_numpy(allo)
        v = recall_ablations(model, torch.from_numpy(obs), vm, a, a, k)
        est = v["own"]["estimates"].numpy()
        one_est = peak_poses(v["true"]["logits"], v["true"]["centres"]).numpy()  # each step against the true memory
        for i in range(b):
            d = np.linalg.norm(est[i, 1:, :2] - allo[i, 1:, :2], axis=1)
            ape += d.tolist()
            one += np.linalg.norm(one_est[i, 1:, :2] - allo[i, 1:, :2], axis=1).tolist()
            ape_kind += [int(kinds[i])] * len(d)
            ate.append(rigid_ate(est[i, :, :2].astype(float), allo[i, :, :2].astype(float)))
            mos = {"mosaic_anam": _mosaic_views(obs[i], allo[i], mask, U, T, allo[i]),
                   "mosaic_hallu": _mosaic_views(obs[i], allo[i], mask, U, k, allo[i, k:])}
            if examples is not None and done == 0 and i < 2:
                examples.setdefault("samples", []).append({"rows": [
                    (f"observed ({KINDS[int(kinds[i])]})", list(obs[i])), ("recalled", shown(v["anam"][i])),
                    ("hallucinated", [None] * k + shown(v["hallu"][i])),
                    ("mosaic + inpainting", [None] * k + list(mos["mosaic_hallu"]))]})
            img_kind["anam"] += [int(kinds[i])] * T
            img_kind["hallu"] += [int(kinds[i])] * (T - k)
            for name in (*ANAMNESIS_SETS, "mosaic_anam"):
                views = mos[name] if name in mos else v[name][i].numpy()
                rows[name] += [_image_metrics(views[t], obs[i, t], mask) for t in range(T)]
            for name in (*HALLUCINATION_SETS, "mosaic_hallu"):
                views = mos[name] if name in mos else v[name][i].numpy()
                rows[name] += [_image_metrics(views[t], obs[i, k + t], mask) for t in range(T - k)]
        done += b
        if bar is not None:
            bar.update(b)
    if bar is not None:
        bar.close()
    ape_a, ate_a, kind_a, one_a = np.asarray(ape), np.asarray(ate), np.asarray(ape_kind), np.asarray(one)
    if examples is not None:
        examples.update(ape=ape_a, kinds=kind_a, kind_names=KINDS)

    def stats(a):
        return {"median": float(np.median(a)), "mean": float(np.mean(a)), "std": float(np.std(a))}

    def images(key, sel=None):
        return image_summary(rows[key] if sel is None else np.asarray(rows[key])[sel])

    def by_kind(key, kinds_of=None):
        kk = np.asarray(img_kind[kinds_of or key])
        return {name: {**images(key, kk == j), "views": int((kk == j).sum())} for j, name in enumerate(KINDS)
                if (kk == j).any()}
    return {"sequences": sequences, "steps": cfg.steps, "observe": cfg.observe, "agent": cfg.agent,
            "ape_px": stats(ape_a), "ate_px": stats(ate_a), "localised_within_1px": float(np.mean(ape_a <= 1.0)),
            "ape_one_step_true_memory_px": {**stats(one_a), "localised_within_1px": float(np.mean(one_a <= 1.0))},
            "ape_px_by_environment": {name: {**stats(ape_a[kind_a == j]), "poses": int((kind_a == j).sum()),
                                             "localised_within_1px": float(np.mean(ape_a[kind_a == j] <= 1.0)),
                                             "one_step_true_memory_within_1px": float(np.mean(one_a[kind_a == j] <= 1.0))}
                                      for j, name in enumerate(KINDS) if (kind_a == j).any()},
            "anamnesis": images("anam"), "anamnesis_true_poses": images("anam_true_poses"),
            "anamnesis_by_environment": by_kind("anam"), "hallucination_by_environment": by_kind("hallu"),
            "anamnesis_true_poses_by_environment": by_kind("anam_true_poses", "anam"),
            "hallucination": images("hallu"), "ablation_no_hallucination_module": images("hallu_no_module"),
            "baseline_mosaic_anamnesis": images("mosaic_anam"), "baseline_mosaic_inpainting": images("mosaic_hallu"),
            "ablation_no_localisation_anamnesis": images("anam_no_localisation"),
            "ablation_no_culling_anamnesis": images("anam_no_culling"),
            "ablation_no_culling_hallucination": images("hallu_no_culling"),
            "thesis_targets_table_4_1_B": {"ape_median_px": 1.0, "anam_l1": 0.08, "anam_ssim": 0.79,
                                           "hallu_l1": 0.20, "hallu_ssim": 0.70},
            "seconds": time.perf_counter() - t0}
