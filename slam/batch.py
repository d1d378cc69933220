"""Batch evaluation: every (sequence, backend) pair is a job that runs SLAM and scores it.

A job runs :func:`slam.pipeline.run_slam` into ``REPORT/runs/<sequence>/<backend>`` (so an
interrupted batch resumes where its runs stopped) and evaluates the trajectory against the
sequence's ground truth with :mod:`slam.metrics`:

* ``ate_rmse_m``: ATE, RMS of the position error after the batch's alignment (``align``, default
  ``auto``: SE(3) when the run's motion determines a rotation, else first poses; ``slam.metrics``), metres;
* ``ape_median_m``: median of the same absolute position errors (metres);
* ``ape_rot_rmse_deg``: RMS of the absolute rotation error (angle, degrees) after the same alignment, so that
  every absolute number of a row has one meaning and equals what ``realgap eval run --align`` prints for the
  run. (A fitted SE(3) is undetermined about the line of a near-straight path and may turn the estimate by up
  to 180 deg about it - measured on a neural run of the built-in planar room - which is why ``auto`` falls back
  to the first poses there.) ``align`` holds the alignment used (``auto: se3``, ``auto: origin``, ``se3``...);
* ``rpe_trans_rmse_m`` / ``rpe_rot_rmse_deg``: RPE between consecutive registered frames
  (evo's default, delta = 1 frame), translation (metres) and rotation angle (degrees);
* ``frames_per_second`` and the failed frames from the run's stats.json.

Executors are registered by name. ``local`` runs the jobs in a process pool; ``ray`` runs the
same job function as Ray tasks (``ray.init()`` connects to the cluster in ``RAY_ADDRESS`` or
starts a local one; ray is an optional dependency, imported only here). Each worker gets
``cpu_count // workers`` threads (``open3d.utility.set_max_threads`` and OMP_NUM_THREADS), so
that parallel jobs do not oversubscribe the CPU; with one thread per job the results are
bit-for-bit reproducible, whichever executor ran them (Open3D's parallel float reductions
otherwise differ in the last bits from run to run).

REPORT/results.json holds every number; REPORT/index.html shows the sequence x backend
table and links a page per sequence (metrics, failures, plots).
"""
from __future__ import annotations

import html
import json
import os
import time
import traceback
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar

from data_tools.camera import Camera, camera_from_dict
from data_tools.errors import ConfigError, RealgapError
from slam.pipeline import SlamConfig

# --------------------------------------------------------------------------------------------
# jobs


@dataclass
class BatchJob:
    """One SLAM run + evaluation (plain data: it travels to worker processes / Ray tasks)."""

    sequence: str
    """Sequence folder (absolute path)."""
    name: str
    """Short unique name of the sequence in the report."""
    backend: str
    run_dir: str
    config: dict
    """SlamConfig as JSON data (backend already set)."""
    camera: dict | None = None
    """camera.json content overriding the sequence's camera, or None."""
    threads: int = 0
    """OMP_NUM_THREADS for Open3D in the worker (0 = leave as is)."""
    align: str = "auto"
    """Alignment of the absolute errors (a key of :data:`slam.metrics.ALIGNERS`)."""
    overwrite: bool = False
    """Run again even when the run folder holds a finished run (``batch --overwrite``)."""


@dataclass
class JobResult:
    """Numbers of one job (the rows of results.json)."""

    sequence: str
    name: str
    backend: str
    run_dir: str
    ok: bool
    error: str | None = None
    frames: int = 0
    frames_tracked: int = 0
    frames_failed: int = 0
    failed_timestamps: list = field(default_factory=list)
    frames_per_second: float | None = None
    ate_rmse_m: float | None = None
    ape_median_m: float | None = None
    ape_rot_rmse_deg: float | None = None
    rpe_trans_rmse_m: float | None = None
    rpe_rot_rmse_deg: float | None = None
    align: str | None = None
    """The alignment the absolute errors were computed after (:attr:`slam.metrics.Alignment.label`)."""
    pairs: int = 0
    seconds: float = 0.0


def run_job(job: dict) -> dict:
    """Run and score one job (a :class:`BatchJob` as a dict); never raises for a bad
    sequence: the error is reported in the result."""
    j = BatchJob(**job)
    t0 = time.perf_counter()
    res = JobResult(j.sequence, j.name, j.backend, j.run_dir, ok=False)
    try:
        from slam.pipeline import run_slam
        cfg = SlamConfig.from_dict(j.config)
        cam = camera_from_dict(j.camera) if j.camera is not None else None
        run = run_slam(j.sequence, j.run_dir, cfg, camera=cam, progress=False, overwrite=j.overwrite)
        s = run.stats
        res.frames, res.frames_tracked = int(s["frames"]), int(s["frames_tracked"])
        res.frames_failed = int(s["frames_failed"])
        res.failed_timestamps = list(s["failed_timestamps"])
        res.frames_per_second = s.get("frames_per_second")
        # score the trajectory as written (what `realgap eval run` reads): a fresh run and a
        # finished one read back after an interrupted batch give the same numbers
        from slam.pipeline import load_run
        from slam.pipeline import poor_tracking
        bad = poor_tracking(s)          # a run that lost track is a failed job, not a number in the table
        if bad:
            raise RealgapError(f"failed run: {bad}")
        _score(res, j, load_run(j.run_dir).trajectory if run.complete else run.trajectory, cam)
        res.ok = True
    except RealgapError as e:
        res.error = str(e)
    except Exception as e:  # a bug in one job must not lose the other results
        res.error = f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=5)}"
    res.seconds = time.perf_counter() - t0
    return asdict(res)


def _score(res: JobResult, job: BatchJob, est, camera: Camera | None) -> None:
    from data_tools.sequence import SequenceReader
    from slam import metrics
    reader = SequenceReader(job.sequence, camera=camera)
    if not reader.has_groundtruth or est is None:
        return
    ref = reader.trajectory
    a = metrics.ate(ref, est, align=job.align, ref_name="ground truth", est_name=job.backend)
    res.ate_rmse_m, res.ape_median_m, res.pairs = a.stats["rmse"], a.stats["median"], a.pairs
    res.align = a.alignment.label
    res.ape_rot_rmse_deg = metrics.ape(ref, est, relation="rotation_angle_deg", align=job.align,
                                       ref_name="ground truth", est_name=job.backend).stats["rmse"]
    if a.pairs >= 2:
        rt = metrics.rpe(ref, est, delta=1, delta_unit="frames", relation="translation")
        rr = metrics.rpe(ref, est, delta=1, delta_unit="frames", relation="rotation_angle_deg")
        res.rpe_trans_rmse_m, res.rpe_rot_rmse_deg = rt.stats["rmse"], rr.stats["rmse"]


def _set_threads(n: int) -> None:
    """Limit this worker's Open3D (TBB), OpenMP and numba threads to ``n`` (0 = no limit)."""
    if n > 0:
        os.environ["OMP_NUM_THREADS"] = str(n)
        import numba
        import open3d as o3d
        o3d.utility.set_max_threads(n)
        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))


def _worker_init(threads: int) -> None:
    import warnings
    from data_tools.workers import exit_with_parent
    exit_with_parent()
    # numba's note that this machine's TBB is too old for its TBB layer (it uses another one; results are the
    # same) would be a raw two-line Python warning with colour codes in the middle of the report
    warnings.filterwarnings("ignore", message=r".*TBB threading layer")
    _set_threads(threads)


# --------------------------------------------------------------------------------------------
# executors


class Executor(ABC):
    """Runs :func:`run_job` over a list of jobs and returns the results in job order."""

    name: ClassVar[str] = ""

    def __init__(self, workers: int = 0):
        self.workers = workers if workers > 0 else max(1, os.cpu_count() or 1)

    @abstractmethod
    def map(self, jobs: list[BatchJob], progress: bool = True,
            on_result: Callable[[int], None] | None = None) -> list[dict]:
        """Results in job order; ``on_result(n_done)`` is called after each finished job."""
        ...


EXECUTORS: dict[str, type[Executor]] = {}


def register_executor(cls: type[Executor]) -> type[Executor]:
    EXECUTORS[cls.name] = cls
    return cls


def get_executor(name: str, workers: int = 0) -> Executor:
    if name not in EXECUTORS:
        raise ConfigError(f"unknown executor {name!r}; choose one of {', '.join(EXECUTORS)}")
    return EXECUTORS[name](workers)


def _bar(progress: bool, total: int):
    if not progress:
        return None
    from data_tools.progress import progress_bar
    return progress_bar(total=total, desc="batch", unit="job")


@register_executor
class LocalExecutor(Executor):
    """A process pool on this machine (spawned workers, one job each at a time)."""

    name = "local"

    def map(self, jobs, progress=True, on_result=None):
        import multiprocessing as mp  # noqa: F401
        from concurrent.futures import ProcessPoolExecutor, as_completed
        if not jobs:
            return []
        n = min(self.workers, len(jobs))
        out: list[dict | None] = [None] * len(jobs)
        bar = _bar(progress, len(jobs))
        with ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                                 initargs=(jobs[0].threads,)) as pool:
            futs = {pool.submit(run_job, asdict(j)): k for k, j in enumerate(jobs)}
            for f in as_completed(futs):
                out[futs[f]] = f.result()
                if bar is not None:
                    bar.update(1)
                if on_result is not None:
                    on_result(sum(r is not None for r in out))
        if bar is not None:
            bar.close()
        return out


def _ray_task(job: dict) -> dict:
    _set_threads(job.get("threads", 0))
    return run_job(job)


@register_executor
class RayExecutor(Executor):
    """Ray tasks on the cluster of ``ray.init()`` (RAY_ADDRESS, or a new local cluster)."""

    name = "ray"

    def map(self, jobs, progress=True, on_result=None):
        try:
            import ray
        except ImportError:
            raise RealgapError("the ray executor needs the optional package ray "
                               "(pip install 'ray==2.60.0'); or use --executor local") from None
        if not jobs:
            return []
        started = False
        if not ray.is_initialized():
            env = {"OMP_NUM_THREADS": str(jobs[0].threads)} if jobs[0].threads > 0 else {}
            repo = str(Path(__file__).resolve().parents[1])
            env["PYTHONPATH"] = os.pathsep.join([repo] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
            kwargs = {"ignore_reinit_error": True, "include_dashboard": False, "log_to_driver": False,
                      "runtime_env": {"env_vars": env}}
            if not os.environ.get("RAY_ADDRESS"):
                kwargs["num_cpus"] = self.workers
            ray.init(**kwargs)
            started = True
        try:
            task = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
            refs = [task.remote(asdict(j)) for j in jobs]
            index = {r: k for k, r in enumerate(refs)}
            out: list[dict | None] = [None] * len(jobs)
            bar = _bar(progress, len(jobs))
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for r in done:
                    out[index[r]] = ray.get(r)
                    if bar is not None:
                        bar.update(1)
                    if on_result is not None:
                        on_result(sum(x is not None for x in out))
            if bar is not None:
                bar.close()
            return out
        finally:
            if started:
                ray.shutdown()


# --------------------------------------------------------------------------------------------
# the batch


@dataclass
class BatchReport:
    """What :func:`run_batch` produced."""

    out: Path
    results: list[dict]
    runs_kept: int = 0
    """Runs already finished in REPORT/runs before this call (an interrupted batch re-run): read, not redone."""

    def table(self) -> dict[tuple[str, str], dict]:
        return {(r["name"], r["backend"]): r for r in self.results}


def _names(sequences: list[Path]) -> list[str]:
    names, seen = [], {}
    for s in sequences:
        base = s.name or "sequence"
        k = seen.get(base, 0)
        seen[base] = k + 1
        names.append(base if k == 0 else f"{base}_{k + 1}")
    return names


def run_batch(sequences: list[str | os.PathLike], backends: list[str], out: str | os.PathLike,
              config: SlamConfig | dict[str, SlamConfig] | None = None, camera: Camera | None = None,
              executor: str = "local", workers: int = 0, progress: bool = True,
              write_html: bool = True, threads_per_job: int = 0, align: str = "auto",
              overwrite: bool = False) -> BatchReport:
    """Run every backend on every sequence and write REPORT/results.json and index.html.

    ``threads_per_job``: Open3D/OpenMP threads of each job (0 = ``cpu_count // workers``); 1 makes
    every number bit-for-bit reproducible across runs and executors.

    ``overwrite``: every run is done again, finished ones included (default: a finished run is read).
    ``align``: alignment of the absolute errors (ATE, APE median, APE rotation), one for all three.

    ``config``: one SlamConfig (its backend is replaced per job, the backend options reset to
    that backend's defaults unless it is the same backend) or a dict backend -> SlamConfig.
    """
    from slam.registration import get_backend
    if not sequences:
        raise ConfigError("no sequences given")
    if not backends:
        raise ConfigError("no backends given")
    if len(set(backends)) != len(backends):
        raise ConfigError(f"backends given twice: {', '.join(sorted({x for x in backends if list(backends).count(x) > 1}))}")
    if threads_per_job < 0:
        raise ConfigError(f"threads per job must be >= 0 (0 = automatic), got {threads_per_job}")
    for b in backends:
        get_backend(b)
    from slam.metrics import ALIGNERS
    if align not in ALIGNERS:
        raise ConfigError(f"--align: unknown alignment {align!r}; choose one of {', '.join(ALIGNERS)}")
    from data_tools.outputs import check_input_dir, check_output_dir
    seqs = [check_input_dir(s, "sequence folder").resolve() for s in sequences]
    twice = sorted({str(s) for s in seqs if seqs.count(s) > 1})
    if twice:   # the same sequence twice: two jobs into one run folder
        raise ConfigError(f"sequence {twice[0]} is given twice (after resolving links); give each sequence once")
    out = check_output_dir(out, what="report folder")
    out.mkdir(parents=True, exist_ok=True)
    ex = get_executor(executor, workers)
    n_jobs = len(seqs) * len(backends)
    threads = threads_per_job or max(1, (os.cpu_count() or 1) // min(ex.workers, n_jobs))
    jobs = []
    for s, name in zip(seqs, _names(seqs)):
        for b in backends:
            cfg = _config_for(config, b)
            jobs.append(BatchJob(str(s), name, b, str((out / "runs" / name / b).resolve()), cfg.to_dict(),
                                 camera.to_json() if camera is not None else None, threads, align, overwrite))
    from data_tools.outputs import clear_incomplete, mark_incomplete
    kept = 0 if overwrite else sum(_run_finished(Path(j.run_dir)) for j in jobs)
    mark_incomplete(out, "realgap batch", kept, n_jobs, unit="runs")
    t0 = time.perf_counter()
    results = ex.map(jobs, progress=progress,
                     on_result=lambda n: mark_incomplete(out, "realgap batch", max(n, kept), n_jobs, unit="runs"))
    meta = {"executor": ex.name, "workers": ex.workers, "threads_per_job": threads,
            "seconds": time.perf_counter() - t0, "sequences": [str(s) for s in seqs],
            "backends": list(backends), "created": time.strftime("%Y-%m-%d %H:%M:%S"),
            "align": align,
            "metrics": {"ate_rmse_m": f"ATE: RMS position error after alignment '{align}' (per run: align), metres",
                        "ape_median_m": f"median absolute position error after alignment '{align}', metres",
                        "ape_rot_rmse_deg": f"RMS absolute rotation error (angle) after alignment '{align}', degrees",
                        "rpe_trans_rmse_m": "RPE translation RMS, consecutive registered frames, metres",
                        "rpe_rot_rmse_deg": "RPE rotation RMS, consecutive registered frames, degrees",
                        "frames_per_second": "frames processed per second (read + register + fuse)"}}
    from data_tools.results import make_header, write_result
    metrics = {f"{r['name']}/{r['backend']}.{k}": r.get(k) for r in results
               for k in ("ate_rmse_m", "frames_per_second", "frames_failed") if r.get("ok")}
    header = make_header("batch", inputs={f"sequence {n}": s for s, n in zip(seqs, _names(seqs))},
                         parameters={"backends": list(backends), "executor": ex.name, "workers": ex.workers,
                                     "align": align,
                                     "config": config.to_dict() if hasattr(config, "to_dict") else config},
                         timings_s={"total": meta["seconds"]}, metrics=metrics)
    write_result(out / "results.json", header, {"meta": meta, "results": results})
    report = BatchReport(out, results, runs_kept=kept)
    if write_html:
        write_html_report(report, meta)
    clear_incomplete(out)
    return report


def _run_finished(run_dir: Path) -> bool:
    """A run folder whose run completed (its stats.json says so)."""
    try:
        return bool(json.loads((run_dir / "stats.json").read_text()).get("complete"))
    except (OSError, ValueError, AttributeError):
        return False


def _config_for(config, backend: str) -> SlamConfig:
    if isinstance(config, dict):
        if backend in config:
            return config[backend]
        config = None
    if config is None:
        return SlamConfig(backend=backend).validate()
    d = config.to_dict()
    if d["backend"] != backend:
        d["backend"], d["backend_config"] = backend, {}
    return SlamConfig.from_dict(d)


# --------------------------------------------------------------------------------------------
# HTML


def _fmt(v, scale=1.0, digits=2, unit=""):
    if v is None:
        return "&ndash;"
    return f"{v * scale:.{digits}f}{unit}"


_CSS = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #bbb;padding:4px 8px;text-align:right}th{background:#eee}"
        "td.l,th.l{text-align:left}.err{color:#b00}")


def write_html_report(report: BatchReport, meta: dict) -> Path:
    """index.html (sequence x backend table) and one page per sequence."""
    out = report.out
    names = list(dict.fromkeys(r["name"] for r in report.results))
    backends = list(dict.fromkeys(r["backend"] for r in report.results))
    tab = report.table()
    rows = []
    head = "".join(f'<th colspan="6">{html.escape(b)}</th>' for b in backends)
    al = html.escape(meta.get("align", "se3"))
    sub = "".join(f"<th>ATE rmse [cm] (align {al})</th><th>APE median [cm] (align {al})</th>"
                  f"<th>APE rot rmse [deg] (align {al})</th><th>RPE [mm, deg]</th>"
                  "<th>frames/s</th><th>failed</th>" for _ in backends)
    for n in names:
        cells = []
        for b in backends:
            r = tab.get((n, b))
            if r is None:
                cells.append('<td colspan="6">&ndash;</td>')
            elif not r["ok"]:
                msg = html.escape((r["error"] or "").splitlines()[0] if r["error"] else "failed")
                cells.append(f'<td colspan="6" class="l err">{msg}</td>')
            else:
                rpe = (f'{_fmt(r["rpe_trans_rmse_m"], 1000, 1)}, {_fmt(r["rpe_rot_rmse_deg"], 1, 2)}'
                       if r["rpe_trans_rmse_m"] is not None else "&ndash;")
                cells.append(f'<td>{_fmt(r["ate_rmse_m"], 100)}</td><td>{_fmt(r["ape_median_m"], 100)}</td>'
                             f'<td>{_fmt(r["ape_rot_rmse_deg"], 1, 2)}</td>'
                             f'<td>{rpe}</td><td>{_fmt(r["frames_per_second"], 1, 1)}</td>'
                             f'<td>{r["frames_failed"]}/{r["frames"]}</td>')
        rows.append(f'<tr><td class="l"><a href="{html.escape(n)}.html">{html.escape(n)}</a></td>{"".join(cells)}</tr>')
        _sequence_page(out, n, [tab[(n, b)] for b in backends if (n, b) in tab])
    comparison = _comparison_plot(out, names, backends, tab, meta.get("align", ""))
    doc = (f"<!doctype html><html><head><meta charset='utf-8'><title>realgap batch</title><style>{_CSS}</style>"
           f"</head><body><h1>SLAM batch report</h1>"
           f"<p>{len(names)} sequence(s) x {len(backends)} backend(s), executor <b>{html.escape(meta['executor'])}</b> "
           f"({meta['workers']} workers, {meta['threads_per_job']} thread(s) per job), {meta['seconds']:.0f} s, "
           f"{html.escape(meta['created'])}. Numbers: <a href='results.json'>results.json</a>.</p>"
           f"<table><tr><th class='l' rowspan='2'>sequence</th>{head}</tr><tr>{sub}</tr>{''.join(rows)}</table>"
           f"<p>ATE: RMS position error after alignment <b>{al}</b> (auto: SE(3) when the run's motion determines "
           f"a rotation - at least 10 poses spread in two directions - else the first poses; each run's page says "
           f"which); APE median: median of the same errors; APE rot: RMS rotation angle error after the same "
           f"alignment; "
           f"RPE: RMS between consecutive registered frames; failed: frames the backend could not "
           f"register (left out of the trajectory).</p>"
           + (f"<p><img src='{html.escape(comparison)}' width='720'></p>" if comparison else "") + "</body></html>")
    from data_tools.results import atomic_write_text
    atomic_write_text(out / "index.html", doc)
    return out / "index.html"


def _sequence_page(out: Path, name: str, results: list[dict]) -> None:
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(name)}</title>"
             f"<style>{_CSS}</style></head><body><p><a href='index.html'>&larr; all sequences</a></p>"
             f"<h1>{html.escape(name)}</h1>"]
    if results:
        parts.append(f"<p>{html.escape(results[0]['sequence'])}</p>")
    for r in results:
        parts.append(f"<h2>{html.escape(r['backend'])}</h2>")
        if not r["ok"]:
            parts.append(f"<pre class='err'>{html.escape(r['error'] or '')}</pre>")
            continue
        rel = os.path.relpath(r["run_dir"], out)
        parts.append("<table>" + "".join(
            f"<tr><th class='l'>{k}</th><td>{v}</td></tr>" for k, v in [
                ("alignment", html.escape(str(r.get("align") or "se3"))),
                ("ATE rmse", _fmt(r["ate_rmse_m"], 100, 2, " cm")), ("APE median", _fmt(r["ape_median_m"], 100, 2, " cm")),
                ("APE rotation rmse", _fmt(r["ape_rot_rmse_deg"], 1, 3, " deg")),
                ("RPE translation rmse", _fmt(r["rpe_trans_rmse_m"], 1000, 2, " mm")),
                ("RPE rotation rmse", _fmt(r["rpe_rot_rmse_deg"], 1, 3, " deg")),
                ("frames/s", _fmt(r["frames_per_second"], 1, 1)),
                ("frames registered", f"{r['frames_tracked']}/{r['frames']}"),
                ("run folder", f"<a href='{html.escape(rel)}'>{html.escape(rel)}</a>")]) + "</table>")
        if r["failed_timestamps"]:
            ts = ", ".join(f"{t:.3f}" for t in r["failed_timestamps"][:50])
            more = " ..." if len(r["failed_timestamps"]) > 50 else ""
            parts.append(f"<p>failed frames (timestamps, s): {ts}{more}</p>")
        png = _plot(out, name, r)
        if png:
            parts.append(f"<p><img src='{html.escape(png)}' width='560'></p>")
    parts.append("</body></html>")
    from data_tools.results import atomic_write_text
    atomic_write_text(out / f"{name}.html", "".join(parts))


def _comparison_plot(out: Path, names: list[str], backends: list[str], tab: dict, align: str = "") -> str | None:
    """plots/comparison.png: ATE, APE median and frames/s of every backend on every sequence, side by side
    (:func:`slam.plots.plot_backend_comparison`; failed runs marked n/a). None when nothing ran."""
    values = {k: r for k, r in tab.items() if r["ok"]}
    if not values:
        return None
    from slam import plots
    (out / "plots").mkdir(exist_ok=True)
    plots.plot_backend_comparison(out / "plots" / "comparison.png", names, backends, values, align=align,
                                  title=f"{len(names)} sequence(s) x {len(backends)} backend(s)")
    return "plots/comparison.png"


def _plot(out: Path, name: str, r: dict) -> str | None:
    """Top-view plot of estimate vs ground truth (None when there is nothing to plot)."""
    if r["ate_rmse_m"] is None:
        return None
    try:
        from data_tools.sequence import SequenceReader
        from data_tools.trajectory import read_tum
        from slam import metrics, plots
        run = Path(r["run_dir"])
        cam_path = run / "camera.json"
        from data_tools.camera import read_camera_json
        ref = SequenceReader(r["sequence"], camera=read_camera_json(cam_path)).trajectory
        how = r.get("align") or "se3"
        a = metrics.ate(ref, read_tum(run / "trajectory.txt"), align=how.split(": ")[-1])
        rel = f"plots/{name}_{r['backend']}.png"
        (out / "plots").mkdir(exist_ok=True)
        plots.plot_top_view(out / rel, a.reference, a.aligned, title=f"{name}: {r['backend']} "
                            f"(ATE {a.stats['rmse'] * 100:.2f} cm, align {how})")
        return rel
    except Exception:  # plots are a convenience; the numbers are in results.json
        return None


def load_results(report_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The job results of REPORT/results.json."""
    p = Path(report_dir) / "results.json"
    try:
        return json.loads(p.read_text())["results"]
    except FileNotFoundError:
        raise RealgapError(f"{p}: file not found") from None
