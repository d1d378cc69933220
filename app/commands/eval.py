"""``realgap eval``: trajectory accuracy (ATE / APE / RPE) against ground truth, as evo computes it."""
from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from dataclasses import fields
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError
from data_tools.trajectory import Trajectory, read_tum, write_tum
from slam.metrics import ALIGNERS, DELTA_UNITS, PRESETS, STAT_KEYS, EvalConfig, MetricResult, ape, ate, rpe

NAME = "eval"
HELP = "evaluate estimated trajectories against ground truth (ATE, APE, RPE; agrees with evo)"
DESCRIPTION = (
    "Evaluate camera trajectories (TUM format, camera-to-world, metres) against a reference. "
    "Poses are associated by nearest timestamp (within --max-dt s), the estimate is aligned "
    "(--align), then the errors are computed with evo's definitions. Outputs: JSON statistics, "
    "the aligned estimate in TUM format and PNG plots.")

_CHOICES = {"align": list(ALIGNERS), "delta_unit": list(DELTA_UNITS)}
_ATE_FIELDS = ("align", "max_dt", "drop_duplicate_timestamps")
_RPE_FIELDS = ("align", "max_dt", "delta", "delta_unit", "all_pairs", "rel_delta_tol", "drop_duplicate_timestamps")
_RUN_FIELDS = _RPE_FIELDS


def _add_config_flags(p: argparse.ArgumentParser, names: tuple[str, ...], note: dict[str, str] | None = None) -> None:
    """One flag per EvalConfig field (help from the field's metadata); defaults come from --preset."""
    p.add_argument("--preset", choices=sorted(PRESETS), default="tum",
                   help="named option set the flags below override (default: tum)")
    by_name = {f.name: f for f in fields(EvalConfig)}
    for name in names:
        f = by_name[name]
        flag = "--" + name.replace("_", "-")
        extra = (note or {}).get(name, "")
        help_ = f.metadata.get("help", "") + (f" ({extra})" if extra else f" (preset default: {f.default})")
        if f.type in (bool, "bool"):
            p.add_argument(flag, dest=name, action="store_const", const=True, default=None, help=help_)
        else:
            typ = {"float": float, "str": str, "int": int}.get(f.type if isinstance(f.type, str) else f.type.__name__, str)
            p.add_argument(flag, dest=name, type=typ, default=None, choices=_CHOICES.get(name),
                           metavar=None if name in _CHOICES else name.split("_")[-1].upper(), help=help_)


def _config(args: argparse.Namespace, names: tuple[str, ...], defaults: dict | None = None) -> EvalConfig:
    d = PRESETS[args.preset].to_dict()
    d.update(defaults or {})
    for name in names:
        v = getattr(args, name, None)
        if v is not None:
            d[name] = v
    return EvalConfig.from_dict(d)


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands import add_group

    sub = add_group(parser)

    p = sub.add_parser("ate", help="absolute trajectory error (translation APE after alignment)",
                       description="Absolute trajectory error of EST against REF (metres).")
    p.add_argument("ref", metavar="REF", help="reference trajectory (TUM file)")
    p.add_argument("est", metavar="EST", help="estimated trajectory (TUM file)")
    _add_config_flags(p, _ATE_FIELDS)
    p.add_argument("--json", required=True, metavar="OUT", help="statistics JSON to write")
    p.add_argument("--out-dir", metavar="D", help="folder for the aligned TUM and the plot (default: next to OUT)")
    p.set_defaults(func=cmd_ate)

    p = sub.add_parser("rpe", help="relative pose error (drift per delta frames or metres)",
                       description="Relative pose error of EST against REF: translation (m) and rotation (deg).")
    p.add_argument("ref", metavar="REF", help="reference trajectory (TUM file)")
    p.add_argument("est", metavar="EST", help="estimated trajectory (TUM file)")
    _add_config_flags(p, _RPE_FIELDS, note={"align": "default: none, as evo_rpe; RPE is invariant to se3"})
    p.add_argument("--json", required=True, metavar="OUT", help="statistics JSON to write")
    p.add_argument("--out-dir", metavar="D", help="folder for the aligned TUM and the plot (default: next to OUT)")
    p.set_defaults(func=cmd_rpe)

    p = sub.add_parser("run", help="evaluate a folder written by 'realgap slam run'",
                       description="ATE, rotation APE and RPE of RUN/trajectory.txt against ground truth, "
                                   "with plots marking the frames where registration failed "
                                   "(RUN/stats.json: failed_timestamps).")
    p.add_argument("run", metavar="RUN", help="folder with trajectory.txt and optionally stats.json")
    p.add_argument("--gt", required=True, metavar="SEQ_OR_TUM",
                   help="ground truth: a sequence folder (uses SEQ/groundtruth.txt) or a TUM file")
    _add_config_flags(p, _RUN_FIELDS)
    p.add_argument("--out", metavar="DIR", help="output folder (default: RUN/eval)")
    p.set_defaults(func=cmd_run)


# ------------------------------------------------------------------------------------------


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")


def _stats_line(res: MetricResult) -> str:
    u = f" {res.unit}" if res.unit else ""
    s = res.stats
    return (f"rmse {s['rmse']:.6g}{u}, mean {s['mean']:.6g}, median {s['median']:.6g}, std {s['std']:.6g}, "
            f"min {s['min']:.6g}, max {s['max']:.6g} ({len(res.errors)} values, {res.pairs} associated pairs)")


def _stats_dict(res: MetricResult) -> dict:
    d = {k: float(res.stats[k]) for k in STAT_KEYS}
    d.update(unit=res.unit, relation=res.relation, n_errors=int(len(res.errors)))
    return d


def _outputs(args) -> tuple[Path, Path, str]:
    out = Path(args.json)
    outdir = Path(args.out_dir) if args.out_dir else out.parent
    return out, outdir, out.stem


def _read(path, cfg: EvalConfig) -> Trajectory:
    """read_tum, with its warnings (dropped duplicates) printed as one line each."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            traj = read_tum(path, drop_duplicate_timestamps=cfg.drop_duplicate_timestamps)
        except FormatError as e:
            if "duplicated timestamp" in e.problem:
                raise FormatError(e.path, f"{e.problem}; --drop-duplicate-timestamps keeps the first") from None
            raise
    for w in caught:
        print(f"realgap: warning: {w.message}", file=sys.stderr)
    return traj


def _read_pair(args, cfg: EvalConfig) -> tuple[Trajectory, Trajectory]:
    return _read(args.ref, cfg), _read(args.est, cfg)


def cmd_ate(args) -> int:
    from slam.plots import plot_top_view

    cfg = _config(args, _ATE_FIELDS)
    ref, est = _read_pair(args, cfg)
    res = ate(ref, est, cfg.align, cfg.max_dt, ref_name=str(args.ref), est_name=str(args.est))
    out, outdir, stem = _outputs(args)
    aligned_path, png = outdir / f"{stem}_aligned.txt", outdir / f"{stem}_top.png"
    d = res.to_dict()
    d["config"] = cfg.to_dict()
    d["files"] = {"aligned_estimate": str(aligned_path), "plot": str(png)}
    _write_json(out, d)
    outdir.mkdir(parents=True, exist_ok=True)
    write_tum(aligned_path, res.aligned, header=f"{args.est} after {cfg.align} alignment onto {args.ref}")
    plot_top_view(png, res.reference, res.aligned,
                  labels=("reference", f"estimate ({cfg.align}-aligned)"),
                  title=f"ATE ({cfg.align}): rmse {res.rmse:.4f} m over {res.pairs} poses")
    print(f"ATE ({cfg.align}): {_stats_line(res)}")
    print(f"wrote {out}, {aligned_path}, {png}")
    return 0


def _rpe_pair(ref, est, cfg: EvalConfig, ref_name: str, est_name: str) -> tuple[MetricResult, MetricResult]:
    kw = dict(delta=cfg.delta, delta_unit=cfg.delta_unit, all_pairs=cfg.all_pairs, align=cfg.align,
              max_dt=cfg.max_dt, rel_delta_tol=cfg.rel_delta_tol, ref_name=ref_name, est_name=est_name)
    return rpe(ref, est, relation="translation", **kw), rpe(ref, est, relation="rotation_angle_deg", **kw)


def _rpe_dict(tr: MetricResult, rot: MetricResult, cfg: EvalConfig) -> dict:
    d = tr.to_dict()
    d["rotation"] = _stats_dict(rot)
    d["config"] = cfg.to_dict()
    return d


def cmd_rpe(args) -> int:
    from slam.plots import plot_errors_over_time

    cfg = _config(args, _RPE_FIELDS, defaults={"align": "none"})
    ref, est = _read_pair(args, cfg)
    tr, rot = _rpe_pair(ref, est, cfg, str(args.ref), str(args.est))
    out, outdir, stem = _outputs(args)
    aligned_path, png = outdir / f"{stem}_aligned.txt", outdir / f"{stem}_errors.png"
    d = _rpe_dict(tr, rot, cfg)
    d["files"] = {"aligned_estimate": str(aligned_path), "plot": str(png)}
    _write_json(out, d)
    outdir.mkdir(parents=True, exist_ok=True)
    write_tum(aligned_path, tr.aligned, header=f"{args.est} after {cfg.align} alignment onto {args.ref}")
    delta = f"delta {cfg.delta:g} {cfg.delta_unit}"
    plot_errors_over_time(png, [("RPE translation", tr.timestamps, tr.errors, "m"),
                                ("RPE rotation", rot.timestamps, rot.errors, "deg")],
                          title=f"RPE ({delta}, align: {cfg.align})")
    print(f"RPE translation ({delta}): {_stats_line(tr)}")
    print(f"RPE rotation    ({delta}): {_stats_line(rot)}")
    print(f"wrote {out}, {aligned_path}, {png}")
    return 0


def _read_failed_timestamps(stats_path: Path) -> np.ndarray:
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


def _gt_path(gt: str) -> Path:
    p = Path(gt)
    if p.is_dir():
        g = p / "groundtruth.txt"
        if not g.is_file():
            raise FormatError(p, "sequence folder has no groundtruth.txt")
        return g
    if not p.exists():
        raise FormatError(p, "ground truth not found (expected a sequence folder or a TUM file)")
    return p


def _nearest_positions(traj: Trajectory, ts: np.ndarray, max_dt: float) -> np.ndarray:
    """(K, 3) positions of ``traj`` nearest in time to ``ts`` (only those within max_dt)."""
    if not len(ts) or not len(traj):
        return np.zeros((0, 3))
    k = np.clip(np.searchsorted(traj.timestamps, ts), 1, len(traj) - 1) if len(traj) > 1 else np.zeros(len(ts), int)
    if len(traj) > 1:
        k = np.where(np.abs(traj.timestamps[k - 1] - ts) <= np.abs(traj.timestamps[k] - ts), k - 1, k)
    ok = np.abs(traj.timestamps[k] - ts) <= max_dt
    return traj.positions[k[ok]]


def cmd_run(args) -> int:
    from slam.plots import plot_errors_over_time, plot_top_view

    cfg = _config(args, _RUN_FIELDS)
    run = Path(args.run)
    if not run.is_dir():
        raise FormatError(run, "run folder not found")
    traj_path = run / "trajectory.txt"
    if not traj_path.is_file():
        raise FormatError(run, "run folder has no trajectory.txt (written by 'realgap slam run')")
    failed = _read_failed_timestamps(run / "stats.json")
    gt_path = _gt_path(args.gt)
    gt = _read(gt_path, cfg)
    est = _read(traj_path, cfg)
    names = dict(ref_name=str(gt_path), est_name=str(traj_path))

    res_t = ate(gt, est, cfg.align, cfg.max_dt, **names)
    res_r = ape(gt, est, "rotation_angle_deg", cfg.align, cfg.max_dt, **names)
    rpe_t, rpe_r = _rpe_pair(gt, est, cfg, **names)

    out = Path(args.out) if args.out else run / "eval"
    out.mkdir(parents=True, exist_ok=True)
    run_info = {"failed_frames": int(len(failed)), "estimate_poses": len(est), "reference_poses": len(gt)}
    d = res_t.to_dict()
    d["run"] = run_info
    d["config"] = cfg.to_dict()
    _write_json(out / "ate.json", d)
    d = res_r.to_dict()
    d["config"] = cfg.to_dict()
    _write_json(out / "ape_rotation.json", d)
    _write_json(out / "rpe.json", _rpe_dict(rpe_t, rpe_r, cfg))
    _write_json(out / "config.json", cfg.to_dict())
    write_tum(out / "estimate_aligned.txt", res_t.aligned, header=f"{traj_path} after {cfg.align} alignment onto {gt_path}")
    res_t.save(out / "ate")
    res_r.save(out / "ape_rotation")
    rpe_t.save(out / "rpe")

    plot_top_view(out / "top_view.png", res_t.reference, res_t.aligned,
                  labels=("ground truth", f"estimate ({cfg.align}-aligned)"),
                  markers=_nearest_positions(gt, failed, cfg.max_dt),
                  title=f"{run.name}: ATE rmse {res_t.rmse:.4f} m ({cfg.align}, {res_t.pairs} poses)")
    delta = f"delta {cfg.delta:g} {cfg.delta_unit}"
    plot_errors_over_time(out / "errors_over_time.png",
                          [("ATE", res_t.timestamps, res_t.errors, "m"),
                           ("APE rotation", res_r.timestamps, res_r.errors, "deg"),
                           (f"RPE ({delta})", rpe_t.timestamps, rpe_t.errors, "m")],
                          failed_timestamps=failed, title=f"{run.name} vs {gt_path.name} (align: {cfg.align})")

    print(f"{run}: {len(est)} estimated poses, {res_t.pairs} associated with {gt_path} "
          f"(max_dt {cfg.max_dt:g} s), {len(failed)} failed frames")
    for label, res in ((f"ATE ({cfg.align})", res_t), ("APE rotation", res_r),
                       (f"RPE translation ({delta})", rpe_t), (f"RPE rotation ({delta})", rpe_r)):
        print(f"  {label + ':':<30} {_stats_line(res)}")
    print(f"wrote {out}/ (ate.json, ape_rotation.json, rpe.json, top_view.png, errors_over_time.png)")
    return 0

