"""Evaluating a recogniser on a test set: accuracy, rotation and translation errors before and
after ICP, confusion matrix, and the CDF figures of thesis Fig. 3.12.

``accuracy`` is the pipeline's (with ICP: after verifying the top candidates, see
:meth:`recog.model.Recogniser.predict`); ``accuracy_descriptor`` the descriptor vote's alone.
Errors are computed on the scans whose object was recognised correctly (a pose of the wrong
object has no meaningful error); ``n_pose`` says how many that is. Rotation errors are reported
symmetry-aware (``rot_err_deg``: the minimum over the object's symmetry group, see
:mod:`recog.symmetry`) and plain (``rot_err_deg_plain``); translation errors are the distance
between estimated and true object centres (the origin of the model frame), metres.

    OUT/eval.json            the numbers (one result header; top level = after ICP)
    OUT/predictions.jsonl    one line per scan (with the estimated 4x4 object-to-camera ``pose``)
    OUT/figures/cdf_rotation.png, cdf_translation.png, confusion.png
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from recog.model import Recogniser
from recog.symmetry import rotation_error_deg
from recog.testset import read_testset

__all__ = ["evaluate", "summarise", "write_eval_json"]


def summarise(rot: list[float], rot_plain: list[float], trans: list[float]) -> dict:
    r, rp, t = (np.asarray(x, float) for x in (rot, rot_plain, trans))

    def stats(a):
        if a.size == 0:
            return {"median": None, "mean": None}
        return {"median": float(np.median(a)), "mean": float(np.mean(a))}
    out = {"rot_err_deg": stats(r), "rot_err_deg_plain": stats(rp), "trans_err_m": stats(t)}
    for th in (10, 20, 40):
        out["rot_err_deg"][f"acc_at_{th}"] = float(np.mean(r <= th)) if r.size else None
        out["rot_err_deg_plain"][f"acc_at_{th}"] = float(np.mean(rp <= th)) if rp.size else None
    return out


def evaluate(model: Recogniser, testset: str | os.PathLike, out: str | os.PathLike | None = None,
             icp: bool = True, k: int = 5, progress: bool = True, max_scans: int | None = None) -> dict:
    """Recognise every scan of ``testset``; write OUT (see the module docstring) when given and
    return the eval.json content (without header)."""
    from data_tools.sequence import read_depth_png
    camera, scans = read_testset(testset, known=model.names)
    if max_scans is not None:
        scans = scans[:max_scans]
    folder = Path(testset)
    intr = camera.intrinsics
    colour = model.reads_colour
    if colour and any(sc.rgb is None for sc in scans):
        from data_tools.errors import FormatError
        raise FormatError(folder / "labels.json", "this recogniser reads colour (recog train --input rgb), these "
                                                  "scans have none (a colour test set: 'realgap synda testset')"
                          if model.input == "rgb" else
                          "the SynDA generator reads colour images, these scans have none "
                          "(a colour test set: 'realgap synda testset'; or a depth generator)")
    names = model.names
    conf = np.zeros((len(names), len(names)), int)
    rows = []
    err = {"before": ([], [], []), "after": ([], [], [])}
    desc_correct = 0
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=len(scans), desc="recognising", unit="scan")
    t0 = time.perf_counter()
    for sc in scans:
        depth = read_depth_png(folder / sc.file, camera.depth_scale)
        if depth.shape != (intr.height, intr.width):
            from data_tools.errors import FormatError
            raise FormatError(folder / sc.file, f"image is {depth.shape[1]}x{depth.shape[0]}, camera.json says "
                                                f"{intr.width}x{intr.height}")
        rgb = None
        if colour:
            from data_tools.sequence import read_rgb_image
            rgb = read_rgb_image(folder / sc.rgb, (intr.height, intr.width))
        pred = model.predict(depth, intr, sc.bbox, icp=icp, k=k, colour=rgb)
        gi, pi = names.index(sc.object), names.index(pred.object)
        conf[gi, pi] += 1
        desc_correct += int(pred.descriptor_object == sc.object)
        row = {"file": sc.file, "object": sc.object, "predicted": pred.object, "correct": gi == pi,
               "descriptor_predicted": pred.descriptor_object, "verification": pred.verification,
               "distance": pred.distance, "icp_accepted": pred.icp_accepted,
               "pose": np.asarray(pred.pose, float).round(6).tolist()}
        if gi == pi:
            sym = model.objects[gi].get("symmetry") or {}
            for key, T in (("before", pred.pose_initial), ("after", pred.pose)):
                r = rotation_error_deg(T[:3, :3], sc.pose[:3, :3], sym)
                rp = rotation_error_deg(T[:3, :3], sc.pose[:3, :3], None)
                tr = float(np.linalg.norm(T[:3, 3] - sc.pose[:3, 3]))
                err[key][0].append(r)
                err[key][1].append(rp)
                err[key][2].append(tr)
                row[f"rot_err_deg_{key}_icp"], row[f"trans_err_m_{key}_icp"] = r, tr
        rows.append(row)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    acc = float(np.trace(conf) / max(conf.sum(), 1))
    after = summarise(*err["after"]) if icp else summarise(*err["before"])
    result = {"accuracy": acc, "accuracy_descriptor": desc_correct / max(len(scans), 1), **after, "before_icp": summarise(*err["before"]), "icp": bool(icp),
              "n_scans": len(scans), "n_pose": len(err["before"][0]), "objects": names,
              "synda": getattr(model, "patch_map_source", None),
              "confusion": conf.tolist(), "seconds": seconds,
              "per_object_accuracy": {n: float(conf[i, i] / max(conf[i].sum(), 1)) for i, n in enumerate(names)
                                      if conf[i].sum()}}
    if out is not None:
        _write(model, testset, Path(out), result, rows, err, names, conf)
    return result


def write_eval_json(model, testset, result: dict, path: str | os.PathLike) -> Path:
    """``result`` (:func:`evaluate`'s) with its result header, written atomically to ``path``: the
    eval.json of ``recog eval --out DIR``."""
    from data_tools.results import make_header, write_result
    inputs = {"model": model.folder / "recogniser.json", "testset": Path(testset) / "labels.json"}
    if result.get("synda"):
        inputs["synda"] = Path(result["synda"])
    header = make_header("recog.eval", inputs=inputs,
                         parameters={"icp": result["icp"]}, timings_s={"total": result["seconds"]},
                         metrics={"accuracy": result["accuracy"],
                                  "rot_err_deg_median": result["rot_err_deg"]["median"],
                                  "rot_err_deg_median_before_icp": result["before_icp"]["rot_err_deg"]["median"],
                                  "trans_err_m_median": result["trans_err_m"]["median"]})
    return write_result(path, header, result)


def _write(model, testset, out: Path, result: dict, rows, err, names, conf) -> None:
    from data_tools.results import atomic_write_bytes
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "predictions.jsonl", "".join(json.dumps(r) + "\n" for r in rows).encode())
    write_eval_json(model, testset, result, out / "eval.json")
    _figures(out / "figures", err, names, conf, str(model.data.variant))


def _figures(folder: Path, err, names, conf, label: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from data_tools.results import atomic_save_figure
    folder.mkdir(parents=True, exist_ok=True)
    for key, idx, unit, scale, xmax in (("rotation", 0, "deg", 1.0, 90.0), ("translation", 2, "mm", 1000.0, 100.0)):
        fig, ax = plt.subplots(figsize=(5, 3.6))
        for stage, style in (("before", "--"), ("after", "-")):
            a = np.sort(np.asarray(err[stage][idx], float) * scale)
            if a.size:
                ax.plot(np.concatenate([[0], a]), np.linspace(0, 100, a.size + 1), style,
                        label=f"{label}, {stage} ICP")
        ax.set_xlim(0, xmax)
        ax.set_ylim(0, 100)
        ax.set_xlabel(f"max {key} error ({unit})")
        ax.set_ylabel("scans (%)")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
        ax.set_title(f"CDF of the {key} error (correctly classified scans)", fontsize=9)
        fig.tight_layout()                      # the x label was cut off at the bottom edge
        atomic_save_figure(fig, folder / f"cdf_{key}.png")
        plt.close(fig)
    fig, ax = plt.subplots(figsize=(1.0 + 0.55 * len(names), 0.8 + 0.5 * len(names)))
    ax.imshow(conf, cmap="Blues")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.set_xlabel("recognised")
    ax.set_ylabel("true")
    for i in range(len(names)):
        for j in range(len(names)):
            if conf[i, j]:
                ax.text(j, i, str(conf[i, j]), ha="center", va="center", fontsize=7,
                        color="white" if conf[i, j] > conf.max() / 2 else "black")
    fig.tight_layout()
    atomic_save_figure(fig, folder / "confusion.png")
    plt.close(fig)
