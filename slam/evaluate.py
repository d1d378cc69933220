"""Trajectory evaluation runs (``realgap eval ate|rpe|run``) as library functions.

Each reads the trajectories, computes the metrics of :mod:`slam.metrics` (evo's definitions),
and writes its outputs: a result JSON with the common header of :mod:`data_tools.results`, the
aligned estimate in TUM format and PNG plots. Messages that a reader dropped or repaired
something come as Python warnings (the CLI prints each as one line).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError
from data_tools.results import atomic_write_json, json_safe, make_header, write_result
from data_tools.outputs import check_output_dir
from data_tools.trajectory import Trajectory, write_tum
from slam.metrics import STAT_KEYS, EvalConfig, MetricResult, ape, ate, rpe

__all__ = ["read_for_eval", "evaluate_ate", "evaluate_rpe", "evaluate_run", "Evaluation", "stats_line"]


@dataclass
class Evaluation:
    """The metrics of an evaluation, by name, and the files written."""

    results: dict[str, MetricResult]
    """E.g. ``{"ate": ...}``, ``{"rpe_translation": ..., "rpe_rotation": ...}``."""
    files: list[Path]
    """Every file or folder written, the result JSON first."""
    info: dict
    """Counts of the inputs (poses, failed frames)."""
    documents: dict = field(default_factory=dict)
    """The result JSON of each file by stem (``{"ate": <ate.json>}``), also when nothing is
    written: ``realgap eval ... --json`` prints exactly this, so stdout and the file have one shape."""


def read_for_eval(path, cfg: EvalConfig, fmt: str = "auto") -> Trajectory:
    """A trajectory file in any format of :mod:`data_tools.trajectory_formats` (``fmt`` auto: from the
    extension or content) with the evaluation's duplicate-timestamp policy (``--strict-timestamps``)."""
    from data_tools.trajectory_formats import read_trajectory
    try:
        return read_trajectory(path, fmt, drop_duplicate_timestamps=not cfg.strict_timestamps)
    except FormatError as e:
        if "duplicated timestamp" in e.problem:
            raise FormatError(e.path, f"{e.problem} (--strict-timestamps; without it the first is kept)") from None
        raise


def stats_line(res: MetricResult) -> str:
    """One line of a metric's statistics (rmse, mean, median, std, min, max, counts)."""
    u = f" {res.unit}" if res.unit else ""
    s = res.stats
    return (f"rmse {s['rmse']:.6g}{u}, mean {s['mean']:.6g}{u}, median {s['median']:.6g}{u}, std {s['std']:.6g}{u}, "
            f"min {s['min']:.6g}{u}, max {s['max']:.6g}{u} ({len(res.errors)} values, {res.pairs} associated pairs)")


def _stats_dict(res: MetricResult) -> dict:
    d = {k: float(res.stats[k]) for k in STAT_KEYS}
    d.update(unit=res.unit, relation=res.relation, n_errors=int(len(res.errors)))
    return d


def _metrics(res: MetricResult, prefix: str = "") -> dict:
    d = {f"{prefix}{k}": float(res.stats[k]) for k in STAT_KEYS}
    d[f"{prefix}pairs"] = int(res.pairs)
    return d


def _header(kind: str, cfg: EvalConfig, inputs: dict, metrics: dict, how: str) -> dict:
    """The result header; ``parameters.alignment_used`` is the alignment's label (``auto: origin``), which
    ``realgap show`` prints next to the metrics."""
    return make_header(kind, inputs=inputs, parameters={**cfg.to_dict(), "alignment_used": how}, metrics=metrics)


def evaluate_ate(ref_path, est_path, cfg: EvalConfig, out_dir=None, *, overwrite: bool = False,
                 fmt: str = "auto") -> Evaluation:
    """ATE of ``est_path`` against ``ref_path`` (trajectory files in ``fmt``, default: detected).
    With ``out_dir``: ``ate.json`` (statistics + header), ``ate_aligned.txt`` (TUM) and
    ``ate_top.png`` there (a finished ate.json is replaced only with ``overwrite``). Without:
    the statistics only, no file written."""
    from slam.plots import plot_top_view
    if out_dir is not None:
        check_output_dir(out_dir, finished="ate.json", overwrite=overwrite)
    ref, est = read_for_eval(ref_path, cfg, fmt), read_for_eval(est_path, cfg, fmt)
    res = ate(ref, est, cfg.align, cfg.max_dt, ref_name=str(ref_path), est_name=str(est_path))
    info = {"reference_poses": len(ref), "estimate_poses": len(est)}
    d = res.to_dict()
    d["config"] = cfg.to_dict()
    header = _header("eval.ate", cfg, {"reference": ref_path, "estimate": est_path}, _metrics(res),
                     res.alignment.label)
    if out_dir is None:
        return Evaluation({"ate": res}, [], info, {"ate": json_safe({"header": header, **d})})
    outdir = Path(out_dir)
    out = outdir / "ate.json"
    aligned_path, png = outdir / f"{out.stem}_aligned.txt", outdir / f"{out.stem}_top.png"
    d["files"] = {"aligned_estimate": str(aligned_path), "plot": str(png)}
    write_result(out, header, d, allow_nan=False)
    outdir.mkdir(parents=True, exist_ok=True)
    how = res.alignment.label
    write_tum(aligned_path, res.aligned, header=f"{est_path} after {how} alignment onto {ref_path}")
    plot_top_view(png, res.reference, res.aligned, labels=("reference", f"estimate (align {how})"),
                  title=f"ATE (align {how}): rmse {res.rmse:.4f} m over {res.pairs} poses")
    return Evaluation({"ate": res}, [out, aligned_path, png], info, {"ate": json.loads(out.read_text())})


def rpe_pair(ref, est, cfg: EvalConfig, ref_name: str, est_name: str) -> tuple[MetricResult, MetricResult]:
    """(translation RPE in metres, rotation RPE in degrees) with the configuration's delta."""
    kw = dict(delta=cfg.delta, delta_unit=cfg.delta_unit, all_pairs=cfg.all_pairs, align=cfg.align,
              max_dt=cfg.max_dt, rel_delta_tol=cfg.rel_delta_tol, ref_name=ref_name, est_name=est_name)
    return rpe(ref, est, relation="translation", **kw), rpe(ref, est, relation="rotation_angle_deg", **kw)


def _rpe_dict(tr: MetricResult, rot: MetricResult, cfg: EvalConfig) -> dict:
    d = tr.to_dict()
    d["rotation"] = _stats_dict(rot)
    d["config"] = cfg.to_dict()
    return d


def evaluate_rpe(ref_path, est_path, cfg: EvalConfig, out_dir=None, *, overwrite: bool = False,
                 fmt: str = "auto") -> Evaluation:
    """RPE (translation and rotation) of ``est_path`` against ``ref_path``. With ``out_dir``:
    ``rpe.json``, ``rpe_aligned.txt`` and ``rpe_errors.png`` there (a finished rpe.json is
    replaced only with ``overwrite``). Without: the statistics only, no file written."""
    from slam.plots import plot_errors_over_time
    if out_dir is not None:
        check_output_dir(out_dir, finished="rpe.json", overwrite=overwrite)
    ref, est = read_for_eval(ref_path, cfg, fmt), read_for_eval(est_path, cfg, fmt)
    tr, rot = rpe_pair(ref, est, cfg, str(ref_path), str(est_path))
    info = {"reference_poses": len(ref), "estimate_poses": len(est)}
    d = _rpe_dict(tr, rot, cfg)
    metrics = {**_metrics(tr), **_metrics(rot, "rotation_")}
    header = _header("eval.rpe", cfg, {"reference": ref_path, "estimate": est_path}, metrics,
                     tr.alignment.label)
    if out_dir is None:
        return Evaluation({"rpe_translation": tr, "rpe_rotation": rot}, [], info,
                          {"rpe": json_safe({"header": header, **d})})
    outdir = Path(out_dir)
    out = outdir / "rpe.json"
    aligned_path, png = outdir / f"{out.stem}_aligned.txt", outdir / f"{out.stem}_errors.png"
    d["files"] = {"aligned_estimate": str(aligned_path), "plot": str(png)}
    write_result(out, header, d)
    outdir.mkdir(parents=True, exist_ok=True)
    write_tum(aligned_path, tr.aligned, header=f"{est_path} after {tr.alignment.label} alignment onto {ref_path}")
    delta = f"delta {cfg.delta:g} {cfg.delta_unit}"
    plot_errors_over_time(png, [("RPE translation", tr.timestamps, tr.errors, "m"),
                                ("RPE rotation", rot.timestamps, rot.errors, "deg")],
                          title=f"RPE ({delta}, align {tr.alignment.label})")
    return Evaluation({"rpe_translation": tr, "rpe_rotation": rot}, [out, aligned_path, png], info,
                      {"rpe": json.loads(out.read_text())})


def read_failed_timestamps(stats_path: Path) -> np.ndarray:
    """The ``failed_timestamps`` of a run's stats.json (empty when the file is absent)."""
    if not stats_path.is_file():
        return np.zeros(0)
    try:
        stats = json.loads(stats_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(stats_path, f"invalid JSON ({e})") from None
    if not isinstance(stats, dict):
        raise FormatError(stats_path, "expected a JSON object")
    failed = stats.get("failed_timestamps", [])
    if not isinstance(failed, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                               and math.isfinite(x) for x in failed):
        raise FormatError(stats_path, "failed_timestamps must be a list of finite numbers (seconds)")
    return np.asarray(failed, dtype=np.float64)


def ground_truth_path(gt) -> Path:
    """A ground-truth TUM file, or a sequence folder's groundtruth.txt."""
    p = Path(gt)
    if p.is_dir():
        g = p / "groundtruth.txt"
        if not g.is_file():
            raise FormatError(p, "sequence folder has no groundtruth.txt")
        return g
    if not p.exists():
        raise FormatError(p, "ground truth not found (expected a sequence folder or a TUM file)")
    return p


def nearest_positions(traj: Trajectory, ts: np.ndarray, max_dt: float) -> np.ndarray:
    """(K, 3) positions of ``traj`` nearest in time to ``ts`` (only those within max_dt)."""
    if not len(ts) or not len(traj):
        return np.zeros((0, 3))
    k = np.clip(np.searchsorted(traj.timestamps, ts), 1, len(traj) - 1) if len(traj) > 1 else np.zeros(len(ts), int)
    if len(traj) > 1:
        k = np.where(np.abs(traj.timestamps[k - 1] - ts) <= np.abs(traj.timestamps[k] - ts), k - 1, k)
    ok = np.abs(traj.timestamps[k] - ts) <= max_dt
    return traj.positions[k[ok]]


def evaluate_run(run_dir, gt, cfg: EvalConfig, out_dir=None, *, overwrite: bool = False,
                 fmt: str = "auto") -> Evaluation:
    """ATE, rotation APE and RPE of ``run_dir/trajectory.txt`` against ``gt`` (a sequence folder
    or a TUM file), written to ``out_dir`` (default ``run_dir/eval``): ate.json, ape_rotation.json,
    rpe.json, config.json, estimate_aligned.txt, the metric folders, top_view.png (failed frames
    marked) and errors_over_time.png. A finished evaluation there is replaced only with
    ``overwrite``. ``fmt``: format of a ground-truth file (default: detected)."""
    from slam.plots import plot_errors_over_time, plot_top_view
    run = Path(run_dir)
    if not run.is_dir():
        raise FormatError(run, "run folder not found")
    traj_path = run / "trajectory.txt"
    if not traj_path.is_file():
        raise FormatError(run, "run folder has no trajectory.txt (written by 'realgap slam run')")
    out = Path(out_dir) if out_dir else run / "eval"
    check_output_dir(out, finished="ate.json", overwrite=overwrite)
    from data_tools.outputs import incomplete_text, read_incomplete
    marker = read_incomplete(run)
    if marker is not None:          # a killed run: its numbers are of the part it registered (said, not hidden)
        from data_tools.errors import warn
        warn(f"{run}: an unfinished run ({incomplete_text(marker)}); the numbers are of the frames it registered")
    failed = read_failed_timestamps(run / "stats.json")
    gt_path = ground_truth_path(gt)
    gt_traj = read_for_eval(gt_path, cfg, fmt)
    est = read_for_eval(traj_path, cfg)
    names = dict(ref_name=str(gt_path), est_name=str(traj_path))

    res_t = ate(gt_traj, est, cfg.align, cfg.max_dt, **names)
    res_r = ape(gt_traj, est, "rotation_angle_deg", cfg.align, cfg.max_dt, **names)
    rpe_t, rpe_r = rpe_pair(gt_traj, est, cfg, **names)

    out.mkdir(parents=True, exist_ok=True)
    run_info = {"failed_frames": int(len(failed)), "estimate_poses": len(est), "reference_poses": len(gt_traj),
                "run_complete": marker is None}
    inputs = {"run": run, "trajectory": traj_path, "ground_truth": gt_path}
    metrics = {**_metrics(res_t, "ate_"), **_metrics(res_r, "ape_rotation_"), **_metrics(rpe_t, "rpe_"),
               **_metrics(rpe_r, "rpe_rotation_"), "failed_frames": int(len(failed))}
    d = res_t.to_dict()
    d["run"] = run_info
    d["config"] = cfg.to_dict()
    write_result(out / "ate.json", _header("eval.run", cfg, inputs, metrics, res_t.alignment.label), d, allow_nan=False)
    d = res_r.to_dict()
    d["config"] = cfg.to_dict()
    atomic_write_json(out / "ape_rotation.json", d, allow_nan=False)
    atomic_write_json(out / "rpe.json", _rpe_dict(rpe_t, rpe_r, cfg), allow_nan=False)
    atomic_write_json(out / "config.json", cfg.to_dict(), allow_nan=False)
    how = res_t.alignment.label
    write_tum(out / "estimate_aligned.txt", res_t.aligned, header=f"{traj_path} after {how} alignment onto {gt_path}")
    res_t.save(out / "ate")
    res_r.save(out / "ape_rotation")
    rpe_t.save(out / "rpe")

    plot_top_view(out / "top_view.png", res_t.reference, res_t.aligned,
                  labels=("ground truth", f"estimate (align {how})"),
                  markers=nearest_positions(gt_traj, failed, cfg.max_dt),
                  title=f"{run.name}: ATE rmse {res_t.rmse:.4f} m (align {how}, {res_t.pairs} poses)")
    delta = f"delta {cfg.delta:g} {cfg.delta_unit}"
    plot_errors_over_time(out / "errors_over_time.png",
                          [(f"ATE (align {how})", res_t.timestamps, res_t.errors, "m"),
                           (f"APE rotation (align {how})", res_r.timestamps, res_r.errors, "deg"),
                           (f"RPE ({delta})", rpe_t.timestamps, rpe_t.errors, "m")],
                          failed_timestamps=failed, title=f"{run.name} vs {gt_path.name} (align {how})")
    return Evaluation({"ate": res_t, "ape_rotation": res_r, "rpe_translation": rpe_t, "rpe_rotation": rpe_r},
                      [out / "ate.json", out], {**run_info, "ground_truth": str(gt_path)},
                      {n: json.loads((out / f"{n}.json").read_text()) for n in ("ate", "ape_rotation", "rpe")})
