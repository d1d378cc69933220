"""``realgap eval``: trajectory accuracy (ATE / APE / RPE) against ground truth, as evo computes it."""
from __future__ import annotations

import argparse
from dataclasses import fields

from slam.metrics import ALIGNERS, DELTA_UNITS, PRESETS, EvalConfig

NAME = "eval"
HELP = "evaluate estimated trajectories against ground truth (ATE, APE, RPE; agrees with evo)"
DESCRIPTION = (
    "Evaluate camera trajectories (camera-to-world, metres; TUM, KITTI, EuRoC CSV or Open3D .log, "
    "detected from the extension and content) against a reference. "
    "Poses are associated by nearest timestamp (within --max-dt s), the estimate is aligned "
    "(--align), then the errors are computed with evo's definitions. Outputs: JSON statistics, "
    "the aligned estimate in TUM format and PNG plots.")

_CHOICES = {"align": list(ALIGNERS), "delta_unit": list(DELTA_UNITS)}
_ATE_FIELDS = ("align", "max_dt", "strict_timestamps")
_RPE_FIELDS = ("align", "max_dt", "delta", "delta_unit", "all_pairs", "rel_delta_tol", "strict_timestamps")
_RUN_FIELDS = _RPE_FIELDS


def _ranges() -> dict:
    from app.commands import positive_float, ranged
    return {"max_dt": ranged("--max-dt", float, 0), "delta": positive_float("--delta"),
            "rel_delta_tol": ranged("--rel-delta-tol", float, 0)}


_RANGES = _ranges()
"""argparse types of the EvalConfig fields with a range: a bad value is one line naming the flag."""


def _add_config_flags(p: argparse.ArgumentParser, names: tuple[str, ...], note: dict[str, str] | None = None) -> None:
    """One flag per EvalConfig field (help from the field's metadata); defaults come from --preset."""
    p.add_argument("--preset", choices=sorted(PRESETS), default="tum",
                   help="named option set the flags below override (default: tum)")
    by_name = {f.name: f for f in fields(EvalConfig)}
    for name in names:
        if name == "align":          # the shared --align of eval, batch and demo (default from --preset)
            from app.commands import add_align
            add_align(p, None, (note or {}).get(name, f"preset default: {by_name[name].default}"))
            continue
        f = by_name[name]
        flag = "--" + name.replace("_", "-")
        extra = (note or {}).get(name, "")
        help_ = f.metadata.get("help", "") + (f" ({extra})" if extra else f" (preset default: {f.default})")
        if f.type in (bool, "bool"):
            p.add_argument(flag, dest=name, action="store_const", const=True, default=None, help=help_)
        else:
            typ = _RANGES.get(name) or {"float": float, "str": str, "int": int}.get(
                f.type if isinstance(f.type, str) else f.type.__name__, str)
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
    p.add_argument("ref", metavar="REF", help="reference trajectory file")
    p.add_argument("est", metavar="EST", help="estimated trajectory file")
    _add_config_flags(p, _ATE_FIELDS)
    _add_io_flags(p, "ate")
    p.set_defaults(func=cmd_ate)

    p = sub.add_parser("rpe", help="relative pose error (drift per delta frames or metres)",
                       description="Relative pose error of EST against REF: translation (m) and rotation (deg).")
    p.add_argument("ref", metavar="REF", help="reference trajectory file")
    p.add_argument("est", metavar="EST", help="estimated trajectory file")
    _add_config_flags(p, _RPE_FIELDS, note={"align": "default: none, as evo_rpe; RPE is invariant to se3"})
    _add_io_flags(p, "rpe")
    p.set_defaults(func=cmd_rpe)

    p = sub.add_parser("run", help="evaluate a folder written by 'realgap slam run'",
                       description="ATE, rotation APE and RPE of RUN/trajectory.txt against ground truth, "
                                   "with plots marking the frames where registration failed "
                                   "(RUN/stats.json: failed_timestamps).")
    p.add_argument("run", metavar="RUN", help="folder with trajectory.txt and optionally stats.json")
    p.add_argument("--gt", required=True, metavar="SEQ_OR_FILE",
                   help="ground truth: a sequence folder (uses SEQ/groundtruth.txt) or a trajectory file")
    _add_config_flags(p, _RUN_FIELDS)
    _add_io_flags(p, "run")
    p.set_defaults(func=cmd_run, _io_allow_inside=("RUN",))  # RUN/eval is the default --out


def _add_io_flags(p: argparse.ArgumentParser, kind: str) -> None:
    from app.commands import add_shared
    from data_tools.trajectory_formats import FORMATS
    p.add_argument("--format", default="auto", choices=("auto",) + FORMATS,
                   help="trajectory file format (default auto: .csv EuRoC, .log Open3D, .kitti KITTI; .txt by its "
                        "columns, 8 TUM or 12 KITTI). KITTI and .log have no time: pose k is paired with pose k")
    if kind == "run":
        add_shared(p, "--out", "folder for the JSON statistics, aligned trajectory and plots (default: RUN/eval)",
                   metavar="DIR")
    else:
        add_shared(p, "--out", f"folder for {kind}.json, the aligned trajectory and the plot (default: print "
                               f"only, write nothing)", metavar="DIR")
    add_shared(p, "--overwrite", f"a finished {'evaluation' if kind == 'run' else kind + '.json'} in DIR")
    add_shared(p, "--json")


# ------------------------------------------------------------------------------------------

def _print_json(ev) -> None:
    """The result JSON exactly as the file holds it: ``eval ate --json`` prints ate.json's content
    (``rmse`` at the top level), ``eval rpe`` rpe.json's; ``eval run`` writes three result files and
    prints them by name (``{"ate": <ate.json>, "ape_rotation": ..., "rpe": ...}``)."""
    import json
    from data_tools.results import json_safe
    docs = ev.documents
    print(json.dumps(json_safe(next(iter(docs.values())) if len(docs) == 1 else docs), indent=2))


def cmd_ate(args) -> int:
    from slam.evaluate import evaluate_ate, stats_line
    cfg = _config(args, _ATE_FIELDS)
    ev = evaluate_ate(args.ref, args.est, cfg, args.out, overwrite=args.overwrite, fmt=args.format)
    if args.json:
        _print_json(ev)
        return 0
    print(f"ATE (align {ev.results['ate'].alignment.label}): {stats_line(ev.results['ate'])}")
    if ev.files:
        print(f"wrote {', '.join(str(f) for f in ev.files)}")
    return 0


def cmd_rpe(args) -> int:
    from slam.evaluate import evaluate_rpe, stats_line
    cfg = _config(args, _RPE_FIELDS, defaults={"align": "none"})
    ev = evaluate_rpe(args.ref, args.est, cfg, args.out, overwrite=args.overwrite, fmt=args.format)
    if args.json:
        _print_json(ev)
        return 0
    delta = f"delta {cfg.delta:g} {cfg.delta_unit}, align {ev.results['rpe_translation'].alignment.label}"
    print(f"RPE translation ({delta}): {stats_line(ev.results['rpe_translation'])}")
    print(f"RPE rotation    ({delta}): {stats_line(ev.results['rpe_rotation'])}")
    if ev.files:
        print(f"wrote {', '.join(str(f) for f in ev.files)}")
    return 0


def cmd_run(args) -> int:
    from slam.evaluate import evaluate_run, stats_line
    cfg = _config(args, _RUN_FIELDS)
    ev = evaluate_run(args.run, args.gt, cfg, args.out, overwrite=args.overwrite, fmt=args.format)
    if args.json:
        _print_json(ev)
        return 0
    i, delta = ev.info, f"delta {cfg.delta:g} {cfg.delta_unit}"
    print(f"{args.run}: {i['estimate_poses']} estimated poses, {ev.results['ate'].pairs} associated with "
          f"{i['ground_truth']} (max_dt {cfg.max_dt:g} s), {i['failed_frames']} failed frames")
    how = ev.results["ate"].alignment.label
    rpe_how = ev.results["rpe_translation"].alignment.label
    labels = {"ate": f"ATE (align {how})", "ape_rotation": f"APE rotation (align {how})",
              "rpe_translation": f"RPE translation ({delta}, align {rpe_how})",
              "rpe_rotation": f"RPE rotation ({delta}, align {rpe_how})"}
    for key, res in ev.results.items():
        print(f"  {labels[key] + ':':<46} {stats_line(res)}")
    print(f"wrote {ev.files[-1]}/ (ate.json, ape_rotation.json, rpe.json, top_view.png, errors_over_time.png)")
    return 0
