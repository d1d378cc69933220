"""Figures of a neural-memory evaluation (``realgap neural eval``): PNG files next to neural_eval.json.

* ``images.png``: L1 and SSIM (thesis windows) of recall and hallucination, with the baselines and the
  ablations measured in the same run, one bar each;
* 2D ``ape_cdf.png``: the share of poses localised within d pixels, for all test walks and per kind of
  environment (pictures, faces, floor plans);
* 3D ``ate.png``: ATE RMSE of ``neural`` (and without its motion prior) and ``icp`` per sequence, in memory
  cells, with the 2-cell margin;
* ``examples.png``: test samples row by row - the observations, their recall from the memory the model
  registered itself, the hallucinated later views and the classic baseline's (mosaic or TSDF +
  inpainting) for the same views.

matplotlib is imported inside the functions and draws on an Agg canvas (no pyplot state), as
:mod:`slam.plots`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.plots import _figure, _save

__all__ = ["write_figures"]

_IMAGE_ROWS = (("anamnesis", "recall (own poses)"), ("anamnesis_backend_registration", "recall (backend's poses)"),
               ("anamnesis_true_poses", "recall (true poses)"),
               ("ablation_no_localisation_anamnesis", "recall, no localisation"),
               ("ablation_no_culling_anamnesis", "recall, no culling"),
               ("baseline_mosaic_anamnesis", "mosaic (true poses)"),
               ("hallucination", "hallucination"), ("ablation_no_hallucination_module", "hallu., no module"),
               ("ablation_no_culling_hallucination", "hallu., no culling"),
               ("baseline_mosaic_inpainting", "mosaic + inpainting"),
               ("baseline_tsdf_inpainting", "TSDF + inpainting"))


def _image_bars(path: Path, res: dict) -> Path:
    rows = [(label, res[key]) for key, label in _IMAGE_ROWS if isinstance(res.get(key), dict)]
    fig = _figure(10.0, 4.2)
    for j, (metric, name) in enumerate((("l1", "L1 (lower is better)"), ("ssim_thesis", "SSIM, thesis (higher is better)"))):
        ax = fig.add_subplot(1, 2, j + 1)
        vals = [r[metric] for _, r in rows]
        colours = ["tab:blue" if "hallu" not in lab and "inpainting" not in lab else "tab:orange" for lab, _ in rows]
        ax.barh(range(len(rows)), vals, color=colours)
        ax.set_yticks(range(len(rows)))
        ax.set_yticklabels([lab for lab, _ in rows] if j == 0 else [], fontsize=8)
        ax.invert_yaxis()
        for i, v in enumerate(vals):
            ax.text(v, i, f" {v:.3f}" if metric == "l1" else f" {v:.2f}", va="center", fontsize=7)
        ax.set_title(name, fontsize=9)
        ax.grid(True, axis="x", alpha=0.3)
    fig.suptitle("images: recall (blue) and hallucination (orange), baselines and ablations", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def _ape_cdf(path: Path, ape: np.ndarray, kinds: np.ndarray, names: tuple) -> Path:
    fig = _figure(6.0, 4.2)
    ax = fig.add_subplot(1, 1, 1)
    d = np.linspace(0, 15, 151)
    ax.plot(d, [(ape <= x).mean() for x in d], "k-", lw=2, label=f"all ({len(ape)} poses)")
    for j, name in enumerate(names):
        a = ape[kinds == j]
        if len(a):
            ax.plot(d, [(a <= x).mean() for x in d], "-", lw=1.2, label=f"{name}s ({len(a)})")
    ax.axvline(1.0, color="0.5", ls=":", lw=1)
    ax.set_xlabel("position error [px]")
    ax.set_ylabel("share of poses within")
    ax.set_ylim(0, 1)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("2D localisation: APE distribution on the test walks", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


_BACKENDS = (("neural_no_motion_prior", "neural, thesis field (no prior, summed score)", "tab:gray"),
             ("neural", "neural", "tab:orange"), ("icp", "icp", "tab:blue"))


def _bar_panel(ax, names: list, per_backend, mark, mark_label: str, ylabel: str, title: str) -> None:
    """Bars of the three backends per sequence (``per_backend(key)``: their values), a black tick per sequence at
    ``mark`` labelled ``mark_label``."""
    x = np.arange(len(names))
    for off, (key, label, colour) in zip((-0.3, 0.0, 0.3), _BACKENDS):
        ax.bar(x + off, per_backend(key), 0.3, label=label, color=colour)
    ax.plot(x, mark, "k_", ms=18, mew=1.5, label=mark_label)
    ax.set_xticks(x)
    ax.set_xticklabels(names, fontsize=8)
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=10)


def _ate_bars(path: Path, res: dict) -> Path:
    """Two panels per sequence: the ATE in memory cells (with icp + 2 cells, the target) and the mean heading error
    (with that of a trajectory that never turns)."""
    seqs = res["sequences"]
    names = list(seqs)
    fig = _figure(2 * max(5.0, 1.4 * len(names) + 2), 4.0)
    icp = np.array([seqs[s]["icp"]["ate_rmse_cells"] for s in names])
    _bar_panel(fig.add_subplot(1, 2, 1), names, lambda k: [seqs[s][k]["ate_rmse_cells"] for s in names], icp + 2,
               "icp + 2 cells (target)", f"ATE RMSE [cells of {res['cell_m']:g} m]",
               "3D localisation: neural vs icp on the same frames")
    _bar_panel(fig.add_subplot(1, 2, 2), names, lambda k: [seqs[s][k]["ape_rotation_deg"]["mean"] for s in names],
               [seqs[s]["heading_fixed_baseline_deg"]["mean"] for s in names], "never turning",
               "heading error, mean [deg]", "3D heading (yaw) error, first poses aligned")
    fig.tight_layout()
    return _save(fig, path)


def _rgb(x: np.ndarray) -> np.ndarray:
    """(C, h, w) in [-1, 1] -> (h, w, 3) in [0, 1] (RGB of the first three channels)."""
    return np.clip((np.transpose(x[:3], (1, 2, 0)) + 1) / 2, 0, 1)


def _examples(path: Path, ex: list[dict]) -> Path:
    """Each example: {"rows": [(label, [(C, h, w) images or None])]} - one figure row per label."""
    rows = [(lab, ims) for e in ex for lab, ims in e["rows"]]
    cols = max(len(ims) for _, ims in rows)
    h, w = next(im for _, ims in rows for im in ims if im is not None).shape[-2:]
    scale = 1.6 / max(h, w)
    fig = _figure(1.2 + cols * w * scale, 0.3 + len(rows) * h * scale)
    for r, (lab, ims) in enumerate(rows):
        for c in range(cols):
            ax = fig.add_subplot(len(rows), cols, r * cols + c + 1)
            ax.set_xticks([])
            ax.set_yticks([])
            im = ims[c] if c < len(ims) else None
            if im is None:      # an empty cell: no frame, but the row's label (column 0) stays visible
                for sp in ax.spines.values():
                    sp.set_visible(False)
            else:
                ax.imshow(_rgb(im), interpolation="nearest")
            if c == 0:
                ax.set_ylabel(lab, fontsize=9, rotation=0, ha="right", va="center")
            if r == 0:
                ax.set_title(f"step {c + 1}", fontsize=9)
    fig.suptitle("test walks: each view observed, recalled from the memory at its pose, and - for the steps not "
                 "yet observed - hallucinated (beside the true-pose mosaic + inpainting baseline)", fontsize=10)
    fig.subplots_adjust(left=0.16, right=0.99, top=0.93, bottom=0.01, wspace=0.05, hspace=0.08)
    return _save(fig, path)


def write_figures(folder: str | Path, res: dict, examples: dict) -> list[str]:
    """The module docstring's PNGs for an evaluation result ``res`` and its ``examples`` (the arrays the
    evaluation kept: 2D ``ape`` / ``kinds`` / ``kind_names`` and ``samples``; 3D ``samples``); returns the names
    written."""
    folder = Path(folder)
    out = [_image_bars(folder / "images.png", res).name]
    if res.get("mode") == "3d":
        out.append(_ate_bars(folder / "ate.png", res).name)
    if "ape" in examples:
        out.append(_ape_cdf(folder / "ape_cdf.png", np.asarray(examples["ape"]), np.asarray(examples["kinds"]),
                            tuple(examples["kind_names"])).name)
    if examples.get("samples"):
        out.append(_examples(folder / "examples.png", examples["samples"]).name)
    return out
