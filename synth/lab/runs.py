"""The sensor lab's four runs on a measured sequence, as library functions (the ``realgap sensor``
commands, a notebook and the viewer call the same code).

A run starts from a :class:`LabRequest` (the measured sequence SEQ and the sensor model: effect
names and/or a model file, optionally fitted first) and writes its outputs:

* :func:`simulate_sequence`: a simulated copy of SEQ in the TUM layout (:func:`write_simulated_sequence`);
* :func:`compare_sequence`: ``metrics.json`` (gap + breakdowns), ``report.html``, one more step
  in ``history.json``;
* :func:`diagnose_sequence`: ``diagnosis.json`` (missing effects ranked by gain), ``diagnosis.html``,
  reusable model files of the best candidates;
* :func:`fit_sequence`: the fitted model JSON.

Each writes the effective configuration next to its output (``lab_config.json``,
``sensor_config.json``) and its result JSON with the common header of
:mod:`data_tools.results`. Messages for the user (what a fit found) go to ``log`` (default: none).
"""
from __future__ import annotations

import dataclasses
import json
import shutil
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from data_tools.config import config_from_options
from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.outputs import check_input_dir, check_input_file, check_output_dir, check_output_file, clear_incomplete, mark_incomplete
from data_tools.results import atomic_write_json, make_header

__all__ = ["LabRequest", "parse_effects", "build_config", "simulate_sequence", "write_simulated_sequence",
           "compare_sequence", "diagnose_sequence", "fit_sequence", "save_diagnosis_models",
           "diagnosis_figure_data", "IDEAL_WORDS", "PIPELINE_WORDS", "LAB_CONFIG_FILE"]

IDEAL_WORDS = ("none", "ideal")
"""Effect-list values meaning 'no effect at all' (the ideal depth)."""
PIPELINE_WORDS = ("physical", "direct")
"""Effect-list values naming a preset pipeline."""
LAB_CONFIG_FILE = "lab_config.json"
"""Effective run configuration written next to every output."""
SIGNATURE_FILE = ".simulate_signature.json"
"""What a simulated sequence was made with (a re-run with the same continues it)."""


def parse_effects(text: str | None) -> list[str] | str | None:
    """An effect list as written by a user -> list of names ([] = ideal), a pipeline word, or None
    (not given). A pipeline word inside a comma list (``physical,disparity_distortion``) is kept
    in the list and expanded by :func:`synth.sensor.config.expand_pipelines` when the preset is
    known. Unknown names raise ConfigError listing the known ones."""
    if text is None:
        return None
    t = text.strip()
    if t.lower() in IDEAL_WORDS or t == "":
        return []
    if t.lower() in PIPELINE_WORDS:
        return t.lower()
    from synth.sensor.registry import effect_class
    names = [x.strip() for x in t.split(",") if x.strip()]
    names = [n.lower() if n.lower() in PIPELINE_WORDS else n for n in names]
    seen = set()
    for n in names:
        if n not in PIPELINE_WORDS:
            effect_class(n)  # ConfigError: unknown sensor effect 'x'; known effects: ...
        if n in seen:
            raise ConfigError(f"--effects lists {n!r} twice")
        seen.add(n)
    return names


def effect_names_option(text: str, flag: str) -> list[str]:
    """A non-empty comma list of effect names given to ``flag``."""
    names = parse_effects(text)
    if not isinstance(names, list) or not names or any(n in PIPELINE_WORDS for n in names):
        raise ConfigError(f"{flag} needs a comma list of effect names (not a pipeline word)")
    return names


@dataclass
class LabRequest:
    """The measured sequence and the sensor model of a lab run."""

    seq: str
    """Measured sequence folder (TUM layout + camera.json + groundtruth.txt + scene.json)."""
    effects: str | None = None
    """Effects of the model as the user wrote them: comma list of names, 'none' (ideal depth),
    'physical' or 'direct' (the preset's pipelines); None = only the model file's."""
    model: str | None = None
    """A model saved by a fit (or any sensor_config.json); ``effects`` adds effects it lacks."""
    fit: bool = False
    """Fit the model's parameters to SEQ first."""
    max_frames: int | None = None
    """Use at most this many frames, evenly spread (None = all)."""
    preset: str | None = None
    """Sensor preset to start from (default from camera.json's sensor type)."""
    frame_slice: str | None = None
    """``START:STOP:STEP`` over the frames with a pose, before ``max_frames`` (e.g. fit on ``0::2``,
    compare on ``1::2``); None = all."""
    seed: int = 0
    """Seed of the simulation and of the pixel samples."""
    fit_options: list[str] = field(default_factory=list)
    """FitConfig overrides, ``KEY=VALUE`` (values as JSON)."""

    def __post_init__(self) -> None:
        if self.effects is None and not self.model:
            raise ConfigError("give the sensor model: --effects E1,E2,... (or 'none' for the ideal model) "
                              "and/or --model MODEL.json")
        if self.max_frames is not None and self.max_frames < 1:
            raise ConfigError(f"--max-frames must be >= 1, got {self.max_frames}")
        self.effect_list = parse_effects(self.effects)
        if self.model:
            check_input_file(self.model, "model file", "--model")

    def fit_config(self):
        from synth.lab.fit import FitConfig
        return config_from_options(FitConfig, self.fit_options, "--fit-option", {"seed": self.seed})

    def load(self, preload: bool = True):
        """(MeasuredSequence of SEQ, the sensor model). With ``preload`` every kept frame's
        measured depth is decoded now, so a corrupt image fails with one line before any
        progress bar starts."""
        from synth.lab.measured import MeasuredSequence
        _quiet_opencv()
        m = MeasuredSequence.load(self.seq, max_frames=self.max_frames, preset=self.preset,
                                  frame_slice=self.frame_slice)
        if preload:
            for k in range(len(m)):
                m.measured_depth(k)
        return m, build_config(m, self.effect_list, self.model)

    def describe(self, cmd: str, measured, config, extra: dict | None = None) -> dict:
        """The effective configuration of a run (``lab_config.json``)."""
        d = {"command": f"sensor {cmd}", "sequence": str(Path(self.seq).resolve()),
             "effects": self.effects, "model": self.model, "fit": bool(self.fit),
             "frames": self.max_frames, "frame_slice": self.frame_slice, "preset": self.preset, "seed": self.seed,
             "fit_options": list(self.fit_options or []),
             "measured": measured.describe(), "effects_used": config.names(enabled_only=True)}
        d.update(extra or {})
        return d

    def header(self, kind: str, config, timings: dict, metrics: dict, parameters: dict | None = None) -> dict:
        """The result header (:func:`data_tools.results.make_header`) of a run."""
        params = {"effects": self.effects, "model": self.model, "fit": self.fit, "max_frames": self.max_frames,
                  "preset": self.preset, "fit_options": list(self.fit_options or []),
                  "effects_used": config.names(enabled_only=True)}
        params.update(parameters or {})
        return make_header(kind, inputs={"sequence": self.seq, "model": self.model}, parameters=params,
                           seed=self.seed, timings_s=timings, metrics=metrics)


def _quiet_opencv() -> None:
    """OpenCV prints its own multi-line warnings for corrupt images before realgap's one-line
    FormatError; silence them (this process only)."""
    try:
        import cv2.utils.logging as cvlog
        cvlog.setLogLevel(cvlog.LOG_LEVEL_SILENT)
    except Exception:  # pragma: no cover - other OpenCV builds
        pass


def build_config(measured, effects, model_path=None):
    """The sensor model of a run: the model file's effects (with their parameters) on the
    measured sequence's preset, plus ``effects`` it lacks (preset defaults); without a model
    file, ``measured.default_config(effects)``."""
    from synth.sensor.registry import make_effect
    if not model_path:
        return measured.default_config(list(effects) if isinstance(effects, list) else effects)
    from synth.lab.model import load_model
    model = load_model(model_path)
    pre = measured.preset
    effs = list(model.effects)
    have = {e.name for e in effs}
    from synth.sensor.config import expand_pipelines
    if isinstance(effects, str):  # a pipeline word
        effects = [effects]
    for n in expand_pipelines(effects or [], pre):
        if n not in have:
            effs.append(make_effect(n, pre.effect_params.get(n)))
    return dataclasses.replace(model, preset=pre, effects=effs)  # keeps the model's other fields (motion)


def require_fittable(config, prefix: str = "") -> None:
    """Raise when the fit would have nothing to search: the lab's parameter space
    (:func:`synth.lab.fit.param_specs`: the effects' FITTABLE plus the lab-side extras such as
    the lens distortion coefficients), not the effects' FITTABLE alone."""
    from synth.lab.fit import param_specs
    if not param_specs(config):
        raise ConfigError(f"{prefix}the model has no fittable parameter (add effects with --effects)")


def _maybe_fit(req: LabRequest, measured, config, out_dir: Path | None, log: Callable[[str], None] | None):
    """Fit the parameters when the request asks for it; saves out_dir/model.json and returns
    (config, FitResult | None)."""
    if not req.fit:
        return config, None
    require_fittable(config, "--fit: ")
    from synth.lab.fit import fit_model
    from synth.lab.model import save_model
    with evaluation_journal(measured, None if out_dir is None else out_dir / FIT_JOURNAL_FILE, log):
        res = fit_model(measured, config, fit_config=req.fit_config(), progress=True)
    if out_dir is not None:
        save_model(res.config, out_dir / "model.json", fit_info=res.to_json())
    if log is not None:
        log(f"fitted {len(res.params)} parameters in {res.evaluations} evaluations ({res.seconds:.1f} s): "
            f"gap {res.gap_before:.4f} -> {res.gap:.4f}")
    return res.config, res


FIT_JOURNAL_FILE = "fit_journal.jsonl"
"""Evaluations of an unfinished ``--fit`` inside an output folder (:mod:`synth.lab.journal`)."""


@contextmanager
def evaluation_journal(measured, path: Path | None, log: Callable[[str], None] | None = None,
                       keep: bool = False):
    """Record (and replay) the objective evaluations of the searches run inside the block in the
    journal ``path`` (:class:`~synth.lab.journal.EvalJournal`), so a killed fit or diagnosis
    continues where it stopped with an identical result. The journal is removed when the block
    finishes without error (unless ``keep``). ``path`` None: no journal."""
    if path is None:
        yield None
        return
    from synth.lab.journal import EvalJournal
    journal = EvalJournal(path)
    if journal.loaded and log is not None:
        log(f"resuming: {journal.loaded} objective evaluations already done are read from {path}")
    measured.eval_journal = journal
    try:
        yield journal
    finally:
        measured.eval_journal = None
    if not keep:
        journal.remove()


def _step_label(req: LabRequest, label: str | None, config, fit) -> str | None:
    if label:
        return label
    if fit is not None or req.model:
        names = ", ".join(config.names(enabled_only=True)) or "ideal"
        return f"{names} ({'fitted' if fit is not None else 'model ' + Path(req.model).name})"
    return None


@contextmanager
def _timed(timings: dict, key: str):
    """Store the wall time of the block in ``timings[key]`` (seconds)."""
    t = time.perf_counter()
    try:
        yield
    finally:
        timings[key] = time.perf_counter() - t


# --------------------------------------------------------------------------- simulate

@dataclass
class SimulateOutcome:
    """What :func:`simulate_sequence` did."""

    out: Path
    """The simulated sequence folder."""
    config: object
    """The SensorConfig used (fitted when the request asked for a fit)."""
    frames_written: int
    """Frames simulated now."""
    frames_kept: int
    """Frames already there from an interrupted run."""
    seconds: float
    """Wall time."""


def simulate_sequence(req: LabRequest, out: str | Path, *, overwrite: bool = False,
                      log: Callable[[str], None] | None = None) -> SimulateOutcome:
    """Simulate every kept frame of ``req.seq`` with its model into ``out`` (see
    :func:`write_simulated_sequence`), fitting the model first when ``req.fit``."""
    out = check_output_dir(out)
    t0 = time.perf_counter()
    measured, config = req.load(preload=False)  # streams; a fit reads only its own frames
    if req.fit:
        mark_incomplete(out, "realgap sensor simulate", 0, len(measured))
    config, _fit = _maybe_fit(req, measured, config, out, log)
    n_new, n_kept = write_simulated_sequence(measured, config, out, seed=req.seed, overwrite=overwrite,
                                             lab_config=req.describe("simulate", measured, config))
    if n_kept and log is not None:
        log(f"resumed: {n_kept} frames already simulated in {out} were kept")
    return SimulateOutcome(out, config, n_new, n_kept, time.perf_counter() - t0)


def _read_index_lines(path: Path) -> dict[str, str]:
    """Relative file -> its original line of an rgb.txt/depth.txt (timestamps kept verbatim)."""
    out = {}
    if not path.is_file():
        return out
    for line in path.read_text().splitlines():
        s = line.split("#", 1)[0].split()
        if len(s) >= 2:
            out[s[1]] = line.strip()
    return out


def write_simulated_sequence(measured, config, out_dir, *, seed: int = 0, overwrite: bool = False,
                             lab_config: dict | None = None, progress: bool = True) -> tuple[int, int]:
    """Simulate every kept frame of ``measured`` with ``config`` into ``out_dir`` (TUM layout).

    Output: ``depth/<same name as in SEQ>`` (16-bit PNG, SEQ's depth scale), ``depth.txt`` with
    SEQ's original lines (timestamps as written there) for the simulated frames,
    ``groundtruth.txt`` copied verbatim, ``camera.json`` (SEQ's), ``scene.json`` + meshes, and,
    when SEQ has colour, ``rgb.txt`` (original lines) + ``rgb/`` images hard-linked or copied
    (the model simulates depth only; colour stays the measured one so RGB-D tools can run on
    the output). ``sensor_config.json`` and ``lab_config.json`` record the model and options.

    Frames without a ground-truth pose (and, with a frame limit, those not picked) cannot be
    simulated and are left out of depth.txt/rgb.txt; every other line is SEQ's own.

    Resumable: images are written before their index line, so after an interruption the frames
    listed in depth.txt are complete; a re-run with the same configuration skips them (frame k
    is simulated with seed ``seed + frame index``, so the result is the same as an
    uninterrupted run). A different configuration in ``out_dir`` is an error unless ``overwrite``.
    Returns (frames written now, frames kept from before).
    """
    from data_tools.camera import write_camera_json
    from data_tools.scene_spec import write_scene_json
    from data_tools.sequence import SequenceReader, link_or_copy, write_depth_png

    out = check_output_dir(out_dir)
    src = Path(measured.seq_dir)
    if out.resolve() == src.resolve():
        raise RealgapError(f"{out}: the output (--out) must not be the measured sequence itself")
    reader = SequenceReader(src)
    signature = {"sensor_config": config.to_json(), "seed": int(seed), "frame_indices": list(measured.frame_indices),
                 "sequence": str(src.resolve())}
    sig_path = out / SIGNATURE_FILE
    if (out / "depth.txt").exists():
        if overwrite:
            for name in ("depth.txt", "rgb.txt", "groundtruth.txt", sig_path.name):
                (out / name).unlink(missing_ok=True)
            shutil.rmtree(out / "depth", ignore_errors=True)
            shutil.rmtree(out / "rgb", ignore_errors=True)
        else:
            try:
                old = json.loads(sig_path.read_text()) if sig_path.exists() else None
            except ValueError:
                old = None
            if old != json.loads(json.dumps(signature)):
                raise RealgapError(f"{out}: holds a different simulation (other model, seed, frames or source); "
                                   f"use --overwrite to replace it")
    out.mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    mark_incomplete(out, "realgap sensor simulate", 0, len(measured))
    atomic_write_json(sig_path, signature, indent=None)
    write_camera_json(out / "camera.json", reader.camera)
    if (src / "groundtruth.txt").is_file():
        shutil.copyfile(src / "groundtruth.txt", out / "groundtruth.txt")
    if not (out / "scene.json").exists():
        write_scene_json(out, measured.scene)
    config.save(out / "sensor_config.json")
    if lab_config is not None:
        atomic_write_json(out / LAB_CONFIG_FILE, lab_config)

    depth_lines = _read_index_lines(src / "depth.txt")
    rgb_lines = _read_index_lines(src / "rgb.txt")
    done = set(_read_index_lines(out / "depth.txt"))
    if not (out / "depth.txt").exists():
        (out / "depth.txt").write_text(f"# depth images simulated by realgap sensor simulate "
                                       f"({', '.join(config.names(enabled_only=True)) or 'ideal'}) from {src}\n"
                                       "# timestamp filename\n")
    has_rgb = any(r is not None for r in reader.rgb_files)
    if has_rgb and not (out / "rgb.txt").exists():
        (out / "rgb.txt").write_text("# colour images of the measured sequence (not simulated)\n# timestamp filename\n")
    done_rgb = set(_read_index_lines(out / "rgb.txt"))

    sim = measured.simulator(config)
    scale = reader.camera.depth_scale
    todo = [k for k in range(len(measured)) if reader.depth_files[measured.frame_indices[k]] not in done]
    kept = len(measured) - len(todo)
    done_count = kept
    mark_incomplete(out, "realgap sensor simulate", done_count, len(measured))
    bar = None
    if progress and todo:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=len(measured), initial=kept, desc="simulating", unit="frame", leave=False)
    for k in todo:
        i = measured.frame_indices[k]
        rel = reader.depth_files[i]
        res = sim.simulate(measured.poses[k], seed=int(seed) + i, prev_pose=measured.prev_poses[k], frame_index=i,
                           timestamp_s=float(measured.timestamps[k]))
        dst = out / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        write_depth_png(dst, res.depth, scale)
        rgb_rel = reader.rgb_files[i]
        if rgb_rel is not None and rgb_rel not in done_rgb:
            link_or_copy(src / rgb_rel, out / rgb_rel)
            with open(out / "rgb.txt", "a") as f:
                f.write(rgb_lines.get(rgb_rel, f"{reader.rgb_timestamps[i]:.6f} {rgb_rel}") + "\n")
            done_rgb.add(rgb_rel)
        with open(out / "depth.txt", "a") as f:
            f.write(depth_lines.get(rel, f"{reader.timestamps[i]:.6f} {rel}") + "\n")
        done_count += 1
        mark_incomplete(out, "realgap sensor simulate", done_count, len(measured))
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    clear_incomplete(out)
    return len(todo), kept


# --------------------------------------------------------------------------- compare

@dataclass
class CompareOutcome:
    """What :func:`compare_sequence` did."""

    result: object
    """The :class:`~synth.lab.compare.CompareResult` (gap, breakdowns)."""
    config: object
    """The SensorConfig compared (fitted when the request asked for a fit)."""
    frames: int
    """Frames compared."""
    report: Path
    """``report.html``."""
    history: list
    """The gap history after this step."""


def simulate_all(measured, config, seed: int, progress: bool = True) -> list:
    """Simulated depth of every kept frame of ``measured`` (progress bar on stderr)."""
    sim = measured.simulator(config)
    frames = range(len(measured))
    if progress:
        from data_tools.progress import progress_bar
        frames = progress_bar(frames, desc="simulating", unit="frame", leave=False)
    out = []
    for k in frames:
        out.extend(measured.simulate(config, seed=seed, frames=[k], simulator=sim))
    return out


def compare_sequence(req: LabRequest, out: str | Path, *, compare_against: str | None = None,
                     label: str | None = None, compare_preset: str = "default", report_frames: int = 4,
                     log: Callable[[str], None] | None = None) -> CompareOutcome:
    """Compare SEQ with its simulation: ``out/metrics.json``, ``out/report.html`` and one more step
    in ``out/history.json`` (continuing ``compare_against``'s history when given)."""
    from synth.lab.compare import compare_preset as get_compare_preset
    from synth.lab.history import load_history
    from synth.lab.report import run_lab
    out = check_output_dir(out)
    if compare_against is not None:
        check_input_dir(compare_against, "earlier lab folder", "--compare-against")
    timings = {}
    with _timed(timings, "load_s"):
        measured, config = req.load()
    with _timed(timings, "fit_s"):
        config, fit = _maybe_fit(req, measured, config, out, log)
    with _timed(timings, "simulate_s"):
        sims = simulate_all(measured, config, req.seed)
    with _timed(timings, "compare_report_s"):
        obs = measured.observations(sims)
        ccfg = get_compare_preset(compare_preset)
        ccfg.seed = int(req.seed)
        effects = config.names(enabled_only=True)
        result = run_lab(obs, out, effects=effects, label=_step_label(req, label, config, fit), config=ccfg,
                         compare_against=compare_against, report_frames=report_frames,
                         planar=measured.has_masks, fit=fit.to_json() if fit is not None else None)
    config.save(out / "sensor_config.json")
    extra = {"compare_preset": compare_preset, "compare_against": compare_against,
             "label": label, "gap": result.gap, "timings_s": {k: round(v, 3) for k, v in timings.items()}}
    if fit is not None:
        extra["fit"] = fit.to_json()
    atomic_write_json(out / LAB_CONFIG_FILE, req.describe("compare", measured, config, extra))
    metrics = {"gap": result.gap, "frames": len(obs), "spatial_term": result.spatial_term,
               **{f"term.{k}": v for k, v in result.feature_terms.items()}}
    result.save(out, header=req.header("lab.compare", config, timings, metrics,
                                       {"compare_preset": compare_preset, "compare_against": compare_against,
                                        "label": label, "report_frames": report_frames}))
    return CompareOutcome(result, config, len(obs), out / "report.html", load_history(out))


# --------------------------------------------------------------------------- diagnose

DIAGNOSE_JOURNAL_FILE = "diagnose_journal.jsonl"
"""Evaluations of an unfinished diagnosis inside its output folder (:mod:`synth.lab.journal`)."""


def diagnose_sequence(req: LabRequest, out: str | Path, *, candidates: Sequence[str] | None = None,
                      top: int = 3, report_frames: int = 3, diagnose_options: Sequence[str] = (),
                      overwrite: bool = False, log: Callable[[str], None] | None = None):
    """Rank the effects missing from the model by how much gap they remove: ``out/diagnosis.json``,
    ``out/diagnosis.html`` (signature figures of the ``top`` candidates), and model files of the
    refitted model and the top candidates (:func:`save_diagnosis_models`). Returns
    (Diagnosis, path of diagnosis.html).

    Resumable: every objective evaluation is journalled in ``out/diagnose_journal.jsonl``; a re-run
    after a kill replays them and computes only the rest (same result as an uninterrupted run).
    A finished diagnosis in ``out`` is replaced only with ``overwrite``."""
    from synth.lab.diagnose import DiagnoseConfig, diagnose
    from synth.lab.signatures import write_diagnosis_report
    out = check_output_dir(out, finished="diagnosis.json", overwrite=overwrite)
    dcfg = config_from_options(DiagnoseConfig, diagnose_options, "--diagnose-option")
    timings = {}
    with _timed(timings, "load_s"):
        measured, config = req.load()
    mark_incomplete(out, "realgap sensor diagnose", 0, None, unit="candidates")
    with _timed(timings, "diagnose_s"), evaluation_journal(measured, out / DIAGNOSE_JOURNAL_FILE, log, keep=True):
        diag = diagnose(measured, config, candidates=candidates, fit_config=req.fit_config(), progress=True,
                        diagnose_config=dcfg)
    diag.save(out)
    models = save_diagnosis_models(diag, out, top=top)
    with _timed(timings, "report_s"):
        figs = diagnosis_figure_data(measured, config, diag, top=top, n_frames=report_frames, seed=req.seed)
        path = write_diagnosis_report(diag.to_json(), figs["base"], figs["candidates"], out,
                                      measured_name=str(req.seq))
    config.save(out / "sensor_config.json")
    atomic_write_json(out / LAB_CONFIG_FILE, req.describe("diagnose", measured, config, {
        "candidates": candidates, "top": top, "gap": diag.gap,
        "models": {k: str(v) for k, v in models.items()},
        "timings_s": {k: round(v, 3) for k, v in timings.items()}}))
    metrics = {"gap": diag.gap, "candidates": len(diag.ranking),
               **{f"gain.{c.effect}": c.gain for c in diag.ranking}}
    diag.save(out, header=req.header("lab.diagnose", config, timings, metrics,
                                     {"candidates": list(candidates) if candidates else None, "top": top,
                                      "diagnose_options": list(diagnose_options)}))
    (out / DIAGNOSE_JOURNAL_FILE).unlink(missing_ok=True)
    clear_incomplete(out)
    return diag, path


def save_diagnosis_models(diag, out_dir: Path, top: int = 3) -> dict[str, Path]:
    """Reusable model files of a diagnosis: ``models/model_refit.json`` (the current model with
    its parameters refitted), ``models/<effect>.json`` for the ``top`` candidates (model +
    candidate, fitted) and ``best_model.json`` (the best candidate's), each with its gap in
    the ``fit`` record. Use them with ``--model``."""
    from synth.lab.model import save_model
    out = {}
    mc = getattr(diag, "model_config", None)
    if mc is not None:
        out["model_refit"] = save_model(mc, out_dir / "models" / "model_refit.json",
                                        fit_info={"gap": diag.gap, "params": dict(diag.model_params),
                                                  "source": "sensor diagnose (current model refitted)"})
    for r, c in enumerate(diag.ranking[:max(0, int(top))]):
        cfg = getattr(c, "config", None)
        if cfg is None:
            continue
        info = {"gap": c.gap_after, "gain": c.gain, "params": dict(c.params), "evidence": c.evidence,
                "source": f"sensor diagnose (candidate {c.effect}, rank {r + 1})"}
        out[c.effect] = save_model(cfg, out_dir / "models" / f"{c.effect}.json", fit_info=info)
        if r == 0:
            out["best_model"] = save_model(cfg, out_dir / "best_model.json", fit_info=info)
    return out


def diagnosis_figure_data(measured, config, diag, *, top: int = 3, n_frames: int = 3, seed: int = 0) -> dict:
    """Observations for the diagnosis figures: the base model and each of the ``top``
    candidates (fitted parameters) on ``n_frames`` evenly spread frames."""
    from data_tools.sequence import spread_indices
    n = len(measured)
    k = max(1, min(int(n_frames), n))
    picks = spread_indices(n, k)
    base_cfg = diag.model_config or config
    base = measured.observations(measured.simulate(base_cfg, seed=seed, frames=picks), frames=picks)
    cands = {}
    for c in diag.ranking[:max(0, int(top))]:
        cfg = c.config  # diagnose() sets every candidate's fitted config
        cands[c.effect] = measured.observations(measured.simulate(cfg, seed=seed, frames=picks), frames=picks)
    return {"base": base, "candidates": cands, "frames": picks}


# --------------------------------------------------------------------------- fit

def fit_sequence(req: LabRequest, out: str | Path, *, only: Sequence[str] | None = None, overwrite: bool = False,
                 log: Callable[[str], None] | None = None):
    """Fit the fittable parameters of the model's effects (``only``: of these effects) to SEQ and
    save the model with its fit record and the result header to ``out``. Returns (FitResult, path).

    An existing ``out`` is replaced only with ``overwrite``. Resumable: the evaluations are
    journalled in ``out`` + ``.journal.jsonl`` until the model is saved; a re-run after a kill
    replays them (same result as an uninterrupted run)."""
    from synth.lab.fit import fit_model
    from synth.lab.model import save_model
    out = check_output_file(out, what="model file", overwrite=overwrite)
    journal = out.with_name(out.name + ".journal.jsonl")
    timings = {}
    with _timed(timings, "load_s"):
        measured, config = req.load()
    require_fittable(config)
    if only:
        missing = [n for n in only if n not in config.names()]
        if missing:
            raise ConfigError(f"--only names effects that are not in the model: {', '.join(missing)}")
    with _timed(timings, "fit_s"), evaluation_journal(measured, journal, log, keep=True):
        res = fit_model(measured, config, names=list(only) if only else None, fit_config=req.fit_config(),
                        progress=True)
    info = res.to_json()
    info["lab_config"] = req.describe("fit", measured, res.config)
    metrics = {"gap_before": res.gap_before, "gap": res.gap, "evaluations": res.evaluations,
               **{f"param.{k}": v for k, v in res.params.items()}}
    header = req.header("lab.fit", res.config, timings, metrics, {"only": list(only) if only else None})
    path = save_model(res.config, out, fit_info=info, header=header)
    journal.unlink(missing_ok=True)
    if log is not None and res.frozen:
        log(f"{len(res.frozen)} of {len(res.params)} parameters frozen at their start (the data does not constrain "
            f"them; fit record 'frozen'): {', '.join(res.frozen)}")
    if log is not None and (hint := unheld_moves_hint(res)):
        log(hint)
    return res, path


def unheld_moves_hint(res) -> str | None:
    """A line for the user when the fit kept nothing although its search moved parameters: the moves
    that lowered the objective on the search's few frames (``FitResult.frames``) were put back on the
    evaluation frames (``reverted``, or the whole start kept), so the search saw the noise of its
    frames, not the sensor - seen with the physical pipeline on 24 real chess plane frames (4 search
    frames 0.436 -> 0.341, evaluation gap unchanged; 12 search frames: held-out gap -12 %). None when
    something was kept, nothing moved, or the search already used every evaluation frame."""
    n_search, n_eval = len(res.frames), len(res.eval_frames)
    if res.gap < res.gap_before or not (res.reverted or res.kept_start) or n_search >= n_eval:
        return None
    moved = ", ".join(res.reverted) if res.reverted else "every parameter"
    return (f"nothing kept: the search's moves on its {n_search} frames ({moved}) did not hold on the {n_eval} "
            f"evaluation frames and were put back; where the objective is rough (the physical pipeline on real "
            f"frames) search on more frames: --fit-option max_frames={min(3 * n_search, n_eval)}")
