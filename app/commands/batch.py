"""``realgap batch``: run several backends on several sequences and write a comparison report."""
from __future__ import annotations

import argparse

from data_tools.errors import ConfigError

NAME = "batch"
HELP = "run SLAM backends on several sequences; REPORT/index.html + results.json"
DESCRIPTION = ("Run every --backends entry on every sequence (jobs in a local process pool or on a "
               "Ray cluster), score each run against the sequence's ground truth (ATE rmse, APE "
               "median, APE rotation after --align; RPE, frames/s, failed frames) and write REPORT/index.html (sequence x "
               "backend table, one page per sequence) and REPORT/results.json. Runs go to "
               "REPORT/runs/<sequence>/<backend>; re-running continues an interrupted batch; a finished report is replaced only with --overwrite.")


def _cm(x) -> str:
    return "-" if x is None else f"{100 * x:.2f}"


def _table(results, align: str = "auto") -> tuple[list[str], list[list[str]]]:
    """The sequence x backend table printed after a batch (ATE and APE in cm, APE rotation in degrees),
    each absolute metric's header naming the alignment ``align``; the column 'align used' says what
    ``auto`` chose for each run."""
    rows = []
    for r in results:
        if r["ok"]:
            fps = f"{r['frames_per_second']:.1f}" if r["frames_per_second"] else "-"
            rot = "-" if r["ape_rot_rmse_deg"] is None else f"{r['ape_rot_rmse_deg']:.2f}"
            rows.append([r["name"], r["backend"], _cm(r["ate_rmse_m"]), _cm(r["ape_median_m"]), rot,
                         r.get("align") or "-", fps, f"{r['frames_failed']}/{r['frames']}"])
        else:
            rows.append([r["name"], r["backend"], "error: " + (r["error"] or "").splitlines()[0], "", "", "", "", ""])
    return ["sequence", "backend", f"ATE cm ({align})", f"APE med cm ({align})", f"APE rot deg ({align})",
            "align used", "frames/s", "failed frames"], rows


def _run(args) -> int:
    from app.commands.slam import _camera, config_from_args
    from slam.batch import run_batch
    backends = [b.strip() for b in args.backends.split(",")]
    if not any(backends):
        raise ConfigError("--backends: give at least one backend, e.g. icp,rgbd_odometry")
    if not all(backends):     # ",icp" or "icp,,o3d": a name left out by mistake, not silently dropped
        raise ConfigError(f"--backends {args.backends!r}: an empty name in the list; separate names by one comma")
    twice = sorted({b for b in backends if backends.count(b) > 1})
    if twice:     # the same job twice would write into one run folder
        raise ConfigError(f"--backends: {', '.join(twice)} given twice; name each backend once")
    configs = {b: config_from_args(args, b, tuple(backends)) for b in backends}
    rep = run_batch(args.sequences, backends, args.out, configs, camera=_camera(args),
                    executor=args.executor, workers=args.workers, progress=not args.no_progress,
                    threads_per_job=args.threads_per_job, align=args.align,
                    overwrite=args.overwrite)
    from data_tools.results import format_table
    print(format_table(*_table(rep.results, args.align)))
    if rep.runs_kept:
        print(f"resumed: {rep.runs_kept} of {len(rep.results)} runs had finished before and were read, not redone")
    print(f"report: {rep.out / 'index.html'}")
    return 0 if all(r["ok"] for r in rep.results) else 1


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands.slam import add_config_arguments
    from slam.batch import EXECUTORS
    parser.add_argument("sequences", nargs="+", metavar="SEQ", help="TUM-layout sequence folders")
    parser.add_argument("--backends", default="icp,rgbd_odometry",
                        help="comma-separated backends (default: icp,rgbd_odometry)")
    from app.commands import RESUMES, add_shared
    add_shared(parser, "--out", "the report folder (runs/ with one run folder per sequence and backend)",
               required=True, metavar="REPORT")
    parser.add_argument("--executor", default="local", choices=sorted(EXECUTORS),
                        help="local: process pool on this machine; ray: Ray tasks (ray.init(), "
                             "RAY_ADDRESS for a cluster; needs the optional package ray)")
    add_shared(parser, "--workers", "jobs at once (default: the CPU count)", default=0)
    from app.commands import ranged
    parser.add_argument("--threads-per-job", type=ranged("--threads-per-job", int, 0), default=0, metavar="N",
                        help="Open3D/OpenMP threads per job (default: CPU count / workers); 1 makes the "
                             "numbers bit-for-bit reproducible (multi-threaded float sums differ in the "
                             "last bits from run to run)")
    add_shared(parser, "--no-progress")
    add_shared(parser, "--overwrite", "a finished report in REPORT: every run is done again (an interrupted "
                                      "batch is continued without it)")
    from app.commands import add_align
    add_align(parser)
    add_config_arguments(parser)
    parser.set_defaults(func=_run, on_interrupt=RESUMES)
