"""Part 3 of the demo: recognition from simulated scans.

A few scans of the three embedded office chairs are made by another sensor than the one the
recogniser was trained with (the ``structure`` preset's physical pipeline; training used kinect_v1),
at random viewpoints with clutter. The shipped recogniser (a triplet CNN trained only on simulated
depth, ``recog/weights/chairs``) names each chair and estimates its 6-DoF pose; the figure draws each
recognised CAD model at its estimated pose over the scan. Every step is kept when finished.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["SHIPPED_RECOGNISER", "run_recog_part"]

SHIPPED_RECOGNISER = Path(__file__).resolve().parents[2] / "recog" / "weights" / "chairs"
"""The recogniser shipped with the package (its MODEL_CARD.md says how it was made)."""


def _overlay(testset: Path, eval_dir: Path, model, out: Path, n: int = 6) -> str:
    """Up to ``n`` scans (as many of each object; depth in grey) with the recognised CAD model drawn at
    the estimated pose (green: right object, red: wrong): ``out``."""
    from data_tools.camera import read_camera_json
    from data_tools.results import atomic_save_figure, new_figure
    from data_tools.sequence import read_depth_png
    cam = read_camera_json(testset / "camera.json")
    intr = cam.intrinsics
    rows = [json.loads(line) for line in (eval_dir / "predictions.jsonl").read_text().splitlines() if line.strip()]
    boxes = {lab["file"]: [int(x) for x in lab["bbox"]] for lab in json.loads((testset / "labels.json").read_text())}
    per = max(1, n // max(1, len({r["object"] for r in rows})))        # the same number of scans of each object
    rows = [r for k, r in enumerate(rows) if sum(q["object"] == r["object"] for q in rows[:k]) < per][:n]
    ncol = min(3, len(rows))
    nrow = -(-len(rows) // ncol)
    fig = new_figure(4.2 * ncol + 0.8, 3.9 * nrow + 0.4)
    axes = np.atleast_1d(fig.subplots(nrow, ncol)).ravel()
    for ax in axes[len(rows):]:
        ax.set_axis_off()
    axes = axes[:len(rows)]
    for ax, r in zip(axes, rows):
        depth = read_depth_png(testset / r["file"], cam.depth_scale)
        shown = np.where(depth > 0, depth, np.nan)
        im = ax.imshow(shown, cmap="gray_r")
        T = np.asarray(r["pose"], float)
        obj = model.object(model.index_of(r["predicted"]))
        _draw_mesh(ax, obj.meshes, T, intr, "tab:green" if r["correct"] else "tab:red")
        x0, y0, x1, y1 = boxes[r["file"]]
        ax.set_xlim(max(0, x0 - 20), min(intr.width, x1 + 20))
        ax.set_ylim(min(intr.height, y1 + 20), max(0, y0 - 20))
        err = r.get("rot_err_deg_after_icp")
        ax.set_title(f"{r['object']} -> {r['predicted']}" + (f"\nrotation error {err:.1f} deg" if err is not None
                                                             else ""), fontsize=9)
        ax.set_xlabel("u (px)", fontsize=8)
        ax.set_ylabel("v (px)", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=list(axes), shrink=0.6, label="measured depth (m)")
    fig.suptitle("Recognised CAD model at its estimated pose over the scan (green: right chair, red: wrong)",
                 fontsize=10)
    atomic_save_figure(fig, out, dpi=90)
    return str(out)


def _draw_mesh(ax, meshes, T: np.ndarray, intr, colour: str) -> None:
    """The meshes' triangles projected at object-to-camera pose ``T`` (4x4), filled semi-transparent:
    the CAD model as the recogniser placed it (triangles behind the camera are left out)."""
    from matplotlib.collections import PolyCollection
    polys = []
    for m in meshes:
        P = m.vertices @ T[:3, :3].T + T[:3, 3]
        tri = P[m.triangles]                                          # (F, 3, 3) camera frame, metres
        tri = tri[(tri[:, :, 2] > 0.05).all(axis=1)]
        uv = np.stack([intr.fx * tri[:, :, 0] / tri[:, :, 2] + intr.cx,
                       intr.fy * tri[:, :, 1] / tri[:, :, 2] + intr.cy], axis=-1)
        polys.append(uv)
    if polys:
        ax.add_collection(PolyCollection(np.concatenate(polys), facecolors=colour, edgecolors="none", alpha=0.18))


def run_recog_part(out: Path, per_object: int, model_dir: str, seed: int, log: Callable[[str], None] = print,
                   progress: bool = True) -> dict:
    """Recognition into ``out`` (``out/testset``, ``out/eval``, ``out/overlay.png``). Returns the facts."""
    from recog.evaluate import evaluate
    from recog.model import Recogniser
    from recog.objects import load_objects
    from recog.testset import TestsetConfig, make_testset
    model_dir = Path(model_dir) if model_dir else SHIPPED_RECOGNISER
    testset = out / "testset"
    if not (testset / "labels.json").is_file() or (testset / "incomplete.json").exists():
        log(f"      {per_object} scans of each chair by the structure sensor -> {testset}")
        make_testset(load_objects("chairs"), testset, TestsetConfig(per_object=per_object, seed=1000 + seed),
                     overwrite=True, progress=progress)
    model = Recogniser.load(model_dir)
    eval_dir = out / "eval"
    if not (eval_dir / "eval.json").is_file():
        log(f"      recognising them with {model_dir}")
        evaluate(model, testset, eval_dir, icp=True, progress=progress)
    r = json.loads((eval_dir / "eval.json").read_text())
    overlay = out / "overlay.png"
    if not overlay.is_file():
        _overlay(testset, eval_dir, model, overlay)
    return {"model": str(model_dir), "scans": r["n_scans"], "accuracy": r["accuracy"],
            "accuracy_descriptor": r["accuracy_descriptor"],
            "rot_err_deg_median": r["rot_err_deg"]["median"],
            "rot_err_deg_median_before_icp": r["before_icp"]["rot_err_deg"]["median"],
            "trans_err_m_median": r["trans_err_m"]["median"], "eval": str(eval_dir / "eval.json"),
            "figures": sorted(str(p) for p in (eval_dir / "figures").glob("*.png")), "overlay": str(overlay)}
