"""Evaluating the neural memory in 3D, in one run (thesis 4.4.3 / Table 4.1 metrics).

* **Localisation** on whole sequences: every test room of the model's world configuration
  (``procedural_room`` seeds never used in training) and, when given, extra planar sequences
  (e.g. the built-in ``room``): ``slam run --backend neural`` and ``--backend icp`` on the same
  frames; APE (first poses aligned, evo's ``--align_origin``) and ATE (SE(3) alignment), metres and
  in memory cells; the heading error: APE of the rotation angle (degrees, first poses aligned; height, pitch and
  roll are the first frame's, so it is the yaw error), beside that of the first pose held for every frame
  (``heading_fixed_baseline_deg``: what an estimate that never turns scores); and the ablation
  ``neural_no_motion_prior`` (the backend's motion prior off and its score the thesis' sum: the thesis' plain
  pose field).
* **Images** on 10-step samples of the test rooms (frames ``stride`` apart): anamnesis - the
  observed views recalled from the memory the model registered itself (predicted poses, the thesis' plain pose
  field; ``anamnesis_backend_registration``: registered as ``slam run --backend neural`` does, with the
  backend's default score and motion prior, i.e. what ``slam render`` of a neural run recalls) - and
  hallucination - the last ``steps - observe`` views, unseen when the memory of the first
  ``observe`` was built, decoded after the hallucination module filled it; L1 of RGB in [0, 1] and
  of depth (metres), SSIM as in the thesis (5 x 5 windows, c1 = 0.001, c2 = 0.003) and by
  ``skimage.metrics.structural_similarity``, at the decoder's 40 x 30 pixels.
* **Baselines and ablations** (same samples): the classic memory - the first ``observe`` frames
  fused at their true poses into a TSDF (``slam.tsdf``), ray cast at the later poses, resized to
  40 x 30, holes filled by OpenCV inpainting (Telea) -; the ablations of :mod:`slam.neural.ablations`
  (shared with the 2D evaluation).
* **Top view** (when the model has a trained top-view decoder, :mod:`slam.neural.topview`): on the
  same samples, the decoded colour floor plan of the memory the model registered itself and of the
  memory at the true poses, L1 (RGB in [0, 1]) against the views' pixels binned per cell, on the
  cells they reached; baseline: the sample's own mean colour on every cell.
* **Speed**: register 5 views + localise + recall 5 + hallucinate 5 views (the thesis' < 1 s on a
  Titan X), median of 5 runs on this machine's CPU.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from slam.neural.ablations import ANAMNESIS_SETS, HALLUCINATION_SETS, image_summary, recall_ablations

__all__ = ["evaluate_3d", "worlds_root"]


def _metrics(pred: np.ndarray, true: np.ndarray, max_range_m: float) -> tuple[float, float, float, float]:
    """(RGB L1 in [0, 1], thesis SSIM, skimage SSIM, depth L1 m where the truth has depth) of (4, H, W)
    images in [-1, 1]."""
    from skimage.metrics import structural_similarity

    from slam.neural.ablations import ssim_thesis
    p, t = np.clip((pred[:3] + 1) / 2, 0, 1), np.clip((true[:3] + 1) / 2, 0, 1)
    l1 = float(np.abs(p - t).mean())
    pg, tg = p.mean(0), t.mean(0)
    valid = true[3] > -0.95
    dl1 = float(np.abs((pred[3] - true[3])[valid]).mean() / 2 * max_range_m) if valid.any() else float("nan")
    return l1, ssim_thesis(pg, tg), float(structural_similarity(pg, tg, data_range=1.0, win_size=5)), dl1


def _tsdf_baseline(reader, idx_seen, idx_later, w) -> list[np.ndarray]:
    """The later views of a TSDF of the seen frames (true poses), 40 x 30, holes inpainted; as (4, H, W)."""
    import cv2

    from slam.neural.data3d import block_resize
    from slam.tsdf import TSDFConfig, TSDFVolume
    vol = TSDFVolume(TSDFConfig())
    intr = reader.intrinsics
    for i in idx_seen:
        f = reader[int(i)]
        vol.integrate(f.depth, f.rgb, intr, f.pose)
    out = []
    for i in idx_later:
        r = vol.raycast(intr, reader.poses[int(i)], with_color=True, with_normal=False)
        depth = np.asarray(r.depth, np.float32)
        rgb = np.asarray(r.color) if r.color is not None else np.zeros((*depth.shape, 3))
        rgb8 = np.clip(rgb * (255 if rgb.max() <= 1.0 else 1), 0, 255).astype(np.uint8)
        col, d = block_resize(rgb8, depth, w.image_h, w.image_w)
        hole = (d <= 0).astype(np.uint8)
        col8 = cv2.inpaint((col * 255).astype(np.uint8), hole, 3, cv2.INPAINT_TELEA).astype(np.float32) / 255
        dd = cv2.inpaint(np.clip(d / w.max_range_m * 255, 0, 255).astype(np.uint8), hole, 3,
                         cv2.INPAINT_TELEA).astype(np.float32) / 255 * w.max_range_m
        dch = np.clip(dd / w.max_range_m, 0, 1) * 2 - 1
        out.append(np.concatenate([np.transpose(col8, (2, 0, 1)) * 2 - 1, dch[None]], 0))
    return out


def worlds_root(tcfg, log=None) -> Path:
    """The folder of the test rooms: the training's ``worlds_dir`` if it still exists, else the default one
    (:func:`slam.neural.data3d.default_worlds_dir`; the rooms are re-simulated there from their seeds if missing) -
    said through ``log`` when the training's folder is gone, so that a re-simulation is not a surprise."""
    from slam.neural.data3d import default_worlds_dir
    default = default_worlds_dir(tcfg.world)
    if not tcfg.worlds_dir:
        return default
    if Path(tcfg.worlds_dir).is_dir():
        return Path(tcfg.worlds_dir)
    if log is not None:
        log(f"the training's rooms folder {tcfg.worlds_dir} is gone; test rooms from {default} (simulated if missing)")
    return default


def evaluate_3d(model, tcfg, out_dir: str | Path, model_dir: str | Path, extra_sequences=(), samples: int = 24,
                seed: int = 12345, progress: bool = True, log=None, simulate=None, examples: dict | None = None) -> dict:
    """The numbers of the module docstring; ``examples``: a dict filled with two samples' images for the figures
    (:func:`slam.neural.figures.write_figures`)."""
    import torch

    from data_tools.sequence import SequenceReader
    from data_tools.trajectory import Trajectory
    from slam.metrics import ape, ate
    from slam.neural.data3d import WorldBank, build_worlds, cache_name, load_sequence_arrays
    from slam.pipeline import make_config, run_slam
    out_dir = Path(out_dir)
    w = tcfg.world
    root = worlds_root(tcfg, log)
    tests = build_worlds(root, w, "test", simulate=simulate, log=log)
    res: dict = {"cell_m": w.cell_m, "sequences": {}}
    # ---------------------------------------------------------------- localisation on whole sequences
    for seq in list(tests) + [Path(s) for s in extra_sequences]:
        reader = SequenceReader(seq)
        gt = reader.trajectory
        row = {}
        for name in ("neural", "icp", "neural_no_motion_prior"):
            backend = "icp" if name == "icp" else "neural"
            over = {"backend_config.model": str(Path(model_dir).resolve())} if backend == "neural" else {}
            if name == "neural_no_motion_prior":
                over.update({"backend_config.prior_move_m": 0.0, "backend_config.prior_turn_deg": 0.0,
                             "backend_config.score": "sum"})
            cfg = make_config(backend, overrides=over)
            t0 = time.perf_counter()
            run = run_slam(reader, out_dir / "runs" / f"{name}_{seq.name}", cfg, progress=progress)
            est = run.trajectory
            a = ape(gt, est, align="origin")
            t = ate(gt, est)
            rot = ape(gt, est, relation="rotation_angle_deg", align="origin")
            row[name] = {"ape_m": a.stats, "ate_m": t.stats, "ate_rmse_cells": t.stats["rmse"] / w.cell_m,
                         "ape_rotation_deg": rot.stats,
                         "seconds": time.perf_counter() - t0, "frames": len(reader)}
        fixed = np.repeat(gt.poses[:1], len(gt.poses), 0)          # a trajectory that never turns nor moves
        row["heading_fixed_baseline_deg"] = ape(gt, Trajectory(gt.timestamps.copy(), fixed),
                                                relation="rotation_angle_deg", align="origin").stats
        row["neural_minus_icp_ate_cells"] = row["neural"]["ate_rmse_cells"] - row["icp"]["ate_rmse_cells"]
        res["sequences"][seq.name] = row
    seqs = res["sequences"].values()
    res["localisation"] = {
        b: {"ape_median_m": float(np.median([s[b]["ape_m"]["median"] for s in seqs])),
            "ate_rmse_m_mean": float(np.mean([s[b]["ate_m"]["rmse"] for s in seqs])),
            "ape_rotation_deg_mean": float(np.mean([s[b]["ape_rotation_deg"]["mean"] for s in seqs]))}
        for b in ("neural", "icp", "neural_no_motion_prior")}
    res["localisation"]["heading_fixed_baseline_deg_mean"] = float(np.mean([s["heading_fixed_baseline_deg"]["mean"]
                                                                           for s in seqs]))
    res["localisation"]["within_2_cells_of_icp"] = bool(all(s["neural_minus_icp_ate_cells"] <= 2 for s in seqs))
    # ---------------------------------------------------------------- images on short samples
    arrays = [load_sequence_arrays(s, w, s / cache_name(w), progress=progress) for s in tests]
    bank = WorldBank(arrays, w)
    readers = [SequenceReader(s) for s in tests]
    rng = np.random.default_rng(seed)
    vm = torch.from_numpy(bank.wedge.astype(np.float32))
    k, T = tcfg.observe, tcfg.steps
    bcfg = make_config("neural").backend_config     # the defaults `slam run --backend neural` registers with
    prior = bcfg.motion_prior(w.cell_m, model.cfg.rotations)
    sets = (*ANAMNESIS_SETS, "anam_backend", *HALLUCINATION_SETS)
    rows = {key: [] for key in (*sets, "tsdf_inpainting")}
    from slam.neural.topview import load_topview, topview_targets
    topdec = load_topview(model_dir, model.cfg.features)
    top_rows = []
    for _ in range(samples):
        si = int(rng.integers(len(arrays)))
        s = arrays[si]
        stride = int(rng.integers(w.stride_min, w.stride_max + 1))
        N = len(s["images"])
        a0 = int(rng.integers(0, N - stride * (T - 1)))
        idx = a0 + stride * np.arange(T)
        obs = torch.from_numpy(s["images"][idx].astype(np.float32))[None]
        cells = torch.from_numpy(s["cells"][idx].astype(np.int64))[None]
        allo = torch.from_numpy(bank.allocentric(s["poses"][idx]))[None]
        a = torch.from_numpy(bank.exact(s["poses"][idx]).astype(np.float32))[None]      # recall at the exact poses
        v = recall_ablations(model, obs, vm, allo, a, k, cells=cells, backend={"motion_prior": prior,
                                                                               "score": bcfg.score})
        views = {key: v[key][0].numpy() for key in sets}
        rec, hal = views["anam"], views["hallu"]
        out, tru = v["own"], v["true"]
        if topdec is not None:      # the colour floor plan: decoded vs the views' pixels binned per cell
            with torch.no_grad():
                tgt, seen = topview_targets(obs, cells, allo, model.cfg.rotations, model.cfg.view, tru["psi"].shape[-1])
                m = seen[0, 0].numpy()
                tv = tgt[0].numpy()[:, m]
                d_self = topdec(out["psi"], out["occ"])[0].numpy()[:, m]
                d_true = topdec(tru["psi"], tru["occ"])[0].numpy()[:, m]
            if m.any():           # L1 in [0, 1] colour units; baseline: the sample's own mean colour everywhere
                top_rows.append((float(np.abs(d_self - tv).mean() / 2), float(np.abs(d_true - tv).mean() / 2),
                                 float(np.abs(tv.mean(1, keepdims=True) - tv).mean() / 2)))
        true = s["images"][idx].astype(np.float32)
        base = _tsdf_baseline(readers[si], idx[:k], idx[k:], w)
        if examples is not None and len(examples.setdefault("samples", [])) < 2:
            def depth(x):
                return np.repeat(x[3:4], 3, 0)
            examples["samples"].append({"rows": [
                ("observed", list(true)), ("recalled", list(rec)), ("hallucinated", [None] * k + list(hal)),
                ("TSDF + inpainting", [None] * k + list(base)), ("observed depth", [depth(x) for x in true]),
                ("hallucinated depth", [None] * k + [depth(x) for x in hal]),
                ("TSDF depth", [None] * k + [depth(x) for x in base])]})
        for key in (*ANAMNESIS_SETS, "anam_backend"):
            rows[key] += [_metrics(views[key][t], true[t], w.max_range_m) for t in range(T)]
        for key in HALLUCINATION_SETS:
            rows[key] += [_metrics(views[key][t], true[k + t], w.max_range_m) for t in range(T - k)]
        rows["tsdf_inpainting"] += [_metrics(base[t], true[k + t], w.max_range_m) for t in range(T - k)]

    def images(key):
        return image_summary(rows[key], ("l1", "ssim_thesis", "ssim_skimage", "depth_l1_m"))
    res.update({"samples": samples, "steps": T, "observe": k, "anamnesis": images("anam"),
                "anamnesis_backend_registration": images("anam_backend"),
                "anamnesis_true_poses": images("anam_true_poses"), "hallucination": images("hallu"),
                "ablation_no_hallucination_module": images("hallu_no_module"),
                "baseline_tsdf_inpainting": images("tsdf_inpainting"),
                "ablation_no_localisation_anamnesis": images("anam_no_localisation"),
                "ablation_no_culling_anamnesis": images("anam_no_culling"),
                "ablation_no_culling_hallucination": images("hallu_no_culling")})
    if top_rows:
        v = np.asarray(top_rows)
        res["topview"] = {"l1": float(v[:, 0].mean()), "l1_true_poses": float(v[:, 1].mean()),
                          "baseline_mean_colour_l1": float(v[:, 2].mean()), "cells": "observed in the sample"}
    res["hallucination_beats_tsdf_ssim"] = bool(res["hallucination"]["ssim_thesis"]
                                                > res["baseline_tsdf_inpainting"]["ssim_thesis"])
    # ---------------------------------------------------------------- speed
    s = arrays[0]
    idx = np.arange(0, 100, 10) % len(s["images"])
    obs = torch.from_numpy(s["images"][idx[:5]].astype(np.float32))[None]
    cells = torch.from_numpy(s["cells"][idx[:5]].astype(np.int64))[None]
    req = torch.from_numpy(bank.exact(s["poses"][idx]).astype(np.float32))
    times = []
    with torch.no_grad():
        for _ in range(5):
            t0 = time.perf_counter()
            o = model(obs, vm, None, cells=cells)
            model.recall(o["psi"].expand(5, -1, -1, -1), req[:5], vm)
            f = model.hallucinate(o["psi"], o["occ"])
            model.recall(f.expand(5, -1, -1, -1), req[5:], vm)
            times.append(time.perf_counter() - t0)
    res["speed_register5_recall5_hallucinate5_s"] = {"median": float(np.median(times)), "device": "cpu",
                                                     "threads": int(torch.get_num_threads())}
    res["thesis_targets"] = {"neural_ate_within_cells_of_icp": 2, "hallucination_ssim_above_tsdf_inpainting": True,
                             "speed_s_titan_x": 1.0}
    return res
