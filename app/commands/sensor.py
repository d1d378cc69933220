"""``realgap sensor``: the sensor lab on a measured sequence (simulate, compare, diagnose, fit).

A measured sequence SEQ is a TUM-layout folder with ``camera.json`` (intrinsics + sensor block),
``groundtruth.txt`` and ``scene.json`` (the reference geometry; ``realgap data make-reference``
fuses one from the sequence itself). Every subcommand simulates SEQ's frames at their
ground-truth poses with a sensor model (a device preset derived from camera.json plus the
effects named by ``--effects`` and/or loaded from ``--model``) and works with the result:

* ``sensor simulate SEQ --effects E1,E2 [--fit] [--model M] --out OUTSEQ``: a simulated copy of
  SEQ in the TUM layout, same timestamps and file names (see :func:`write_simulated_sequence`);
* ``sensor compare SEQ --effects ... --out DIR``: DIR/metrics.json (``gap`` + breakdowns),
  DIR/report.html, and one more step in DIR/history.json;
* ``sensor diagnose SEQ --effects ... --out DIR``: DIR/diagnosis.json (candidate effects ranked
  by how much of the gap they remove) and DIR/diagnosis.html with their signature figures;
* ``sensor fit SEQ --effects ... --out MODEL.json``: the fitted model, reusable with ``--model``.

``--effects`` takes a comma list of effect names, ``none`` (the ideal model: ideal depth, no
effect), ``physical`` or ``direct`` (the preset's pipelines). With ``--model`` the model's
effects and parameters are used on SEQ's geometry, and names in ``--effects`` that the model
lacks are added with the preset's defaults. The effective configuration is saved next to every
output (``lab_config.json``, ``sensor_config.json``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from data_tools.errors import ConfigError, RealgapError

NAME = "sensor"
HELP = "sensor lab on a measured sequence: simulate it, compare, diagnose the gap, fit a model"
DESCRIPTION = ("Simulate a measured RGB-D sequence (camera.json + groundtruth.txt + scene.json) with a "
               "depth-sensor model, measure the realism gap, rank missing effects and fit parameters.")

IDEAL_WORDS = ("none", "ideal")
"""``--effects`` values meaning 'no effect at all' (the ideal depth)."""
PIPELINE_WORDS = ("physical", "direct")
"""``--effects`` values naming a preset pipeline."""
LAB_CONFIG_FILE = "lab_config.json"
"""Effective command configuration written next to every output."""
DEFAULT_FRAMES = {"simulate": None, "compare": 24, "diagnose": 12, "fit": 12}
"""Default ``--frames`` per subcommand (None = every frame with a pose)."""


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands import add_group
    sub = add_group(parser)
    _add_simulate(sub)
    _add_compare(sub)
    _add_diagnose(sub)
    _add_fit(sub)


# --------------------------------------------------------------------------- shared options

def _common(p: argparse.ArgumentParser, cmd: str, fit_flag: bool = True) -> None:
    p.add_argument("seq", help="measured sequence (TUM layout + camera.json + groundtruth.txt + scene.json)")
    p.add_argument("--effects", metavar="E1,E2,...",
                   help="sensor effects of the model: comma list of names, 'none' (ideal depth), "
                        "'physical' or 'direct' (the preset's pipelines)")
    p.add_argument("--model", metavar="MODEL.json", help="a model saved by 'realgap sensor fit' (or any "
                   "sensor_config.json); --effects adds effects it lacks")
    if fit_flag:
        p.add_argument("--fit", action="store_true", help="fit the model's parameters to SEQ first")
    n = DEFAULT_FRAMES[cmd]
    p.add_argument("--frames", type=int, default=n, metavar="N",
                   help=f"use at most N frames, evenly spread (default {'all' if n is None else n})")
    p.add_argument("--preset", help="sensor preset to start from (default from camera.json's sensor type: "
                                    "kinect_v1, realsense_d435, kinect_v2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulation and of the pixel samples (default 0)")
    if fit_flag or cmd == "fit" or cmd == "diagnose":
        p.add_argument("--fit-option", action="append", default=[], metavar="KEY=VALUE",
                       help="FitConfig option, repeatable (e.g. max_evaluations=40)")


def _add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="simulate every frame of SEQ at its ground-truth pose (TUM output)",
                       description="Write OUTSEQ: the depth SEQ would have had under the sensor model, in "
                                   "the TUM layout with the same timestamps and depth file names (depth.txt, "
                                   "depth/, groundtruth.txt, camera.json, scene.json; rgb.txt and rgb/ are "
                                   "linked from SEQ when it has colour, since the model simulates depth only). "
                                   "Interrupted runs continue when re-run with the same options.")
    _common(p, "simulate")
    p.add_argument("--out", required=True, metavar="OUTSEQ", help="output sequence folder")
    p.add_argument("--overwrite", action="store_true", help="replace a simulation already in OUTSEQ")
    p.set_defaults(func=_cmd_simulate)


def _add_compare(sub) -> None:
    from synth.lab.compare import PRESETS
    p = sub.add_parser("compare", help="measure the gap between SEQ and its simulation; report + history",
                       description="Compare SEQ with its simulation: DIR/metrics.json (gap, breakdowns by "
                                   "distance, incidence, radial distance, material, edge distance), "
                                   "DIR/report.html (error maps, binned curves, worst regions, gap history). "
                                   "Every run appends one step to DIR/history.json.")
    _common(p, "compare")
    p.add_argument("--out", required=True, metavar="DIR", help="lab folder (report, metrics, history)")
    p.add_argument("--compare-against", metavar="PREVDIR",
                   help="continue the gap history of an earlier lab folder")
    p.add_argument("--label", help="label of this step in the history (default: the effects)")
    p.add_argument("--compare-preset", default="default", choices=sorted(PRESETS),
                   help="sampling of the comparison (default 20k pixels/frame, fast 5k, exact all)")
    p.add_argument("--report-frames", type=int, default=4, metavar="K",
                   help="frames with error-map figures in the report (default 4)")
    p.set_defaults(func=_cmd_compare)


def _add_diagnose(sub) -> None:
    p = sub.add_parser("diagnose", help="rank the effects missing from a model by how much gap they remove",
                       description="Try every candidate effect not in the model (each fitted to SEQ), rank "
                                   "them by gain = (gap - gap_after) / gap and write DIR/diagnosis.json and "
                                   "DIR/diagnosis.html (signature figures of the top candidates).")
    _common(p, "diagnose", fit_flag=False)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--candidates", metavar="E1,E2,...", help="candidate effects (default: every effect that "
                                                             "applies to the sensor type and is not in the model)")
    p.add_argument("--top", type=int, default=3, metavar="K", help="candidates explained with figures (default 3)")
    p.add_argument("--report-frames", type=int, default=3, metavar="K",
                   help="frames simulated per top candidate for the figures (default 3)")
    p.add_argument("--diagnose-option", action="append", default=[], metavar="KEY=VALUE",
                   help="DiagnoseConfig option, repeatable (e.g. candidate_evaluations=20, refit_model=false)")
    p.set_defaults(func=_cmd_diagnose)


def _add_fit(sub) -> None:
    p = sub.add_parser("fit", help="fit the parameters of a sensor model to SEQ; save MODEL.json",
                       description="Fit the fittable parameters of the model's effects to SEQ (minimising "
                                   "the gap) and save the model with its fit record.")
    _common(p, "fit", fit_flag=False)
    p.add_argument("--out", required=True, metavar="MODEL.json", help="where to save the fitted model")
    p.add_argument("--only", metavar="E1,E2,...", help="fit only these effects' parameters (default: all)")
    p.set_defaults(func=_cmd_fit)


# --------------------------------------------------------------------------- helpers

def parse_effects(text: str | None) -> list[str] | str | None:
    """``--effects`` value -> list of names ([] = ideal), a pipeline word, or None (not given).
    Unknown names raise ConfigError listing the known ones."""
    if text is None:
        return None
    t = text.strip()
    if t.lower() in IDEAL_WORDS or t == "":
        return []
    if t.lower() in PIPELINE_WORDS:
        return t.lower()
    from synth.sensor.registry import effect_class
    names = [x.strip() for x in t.split(",") if x.strip()]
    seen = set()
    for n in names:
        effect_class(n)  # ConfigError: unknown sensor effect 'x'; known effects: ...
        if n in seen:
            raise ConfigError(f"--effects lists {n!r} twice")
        seen.add(n)
    return names


def _check_model_args(args) -> None:
    if args.effects is None and not args.model:
        raise ConfigError("give the sensor model: --effects E1,E2,... (or 'none' for the ideal model) "
                          "and/or --model MODEL.json")
    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be >= 1, got {args.frames}")
    args.effect_list = parse_effects(args.effects)
    if args.model and not Path(args.model).is_file():
        from data_tools.errors import FormatError
        raise FormatError(args.model, "model file not found")


def _quiet_opencv() -> None:
    """OpenCV prints its own multi-line warnings for corrupt images before realgap's one-line
    FormatError; silence them (this process only)."""
    try:
        import cv2.utils.logging as cvlog
        cvlog.setLogLevel(cvlog.LOG_LEVEL_SILENT)
    except Exception:  # pragma: no cover - other OpenCV builds
        pass


def _load_measured(args, preload: bool = True):
    """MeasuredSequence of SEQ; with ``preload`` every kept frame's measured depth is decoded
    now, so a corrupt image fails with one line before any progress bar starts."""
    from synth.lab.measured import MeasuredSequence
    _quiet_opencv()
    m = MeasuredSequence.load(args.seq, max_frames=args.frames, preset=args.preset)
    if preload:
        for k in range(len(m)):
            m.measured_depth(k)
    return m


def build_config(measured, effects, model_path=None):
    """The sensor model of a command: the model file's effects (with their parameters) on the
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
    if isinstance(effects, str):  # a pipeline word
        effects = list(getattr(pre, f"{effects}_effects"))
    for n in effects or []:
        if n not in have:
            effs.append(make_effect(n, pre.effect_params.get(n)))
    return dataclasses.replace(model, preset=pre, effects=effs)  # keeps the model's other fields (motion)


def _options(cls, items, flag: str, base: dict | None = None):
    """``cls`` (a config dataclass) with KEY=VALUE overrides (values parsed as JSON when possible)."""
    from dataclasses import fields, replace
    known = {f.name for f in fields(cls) if f.init}
    over = dict(base or {})
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"{flag} expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        k = k.strip()
        if k not in known:
            raise ConfigError(f"{flag}: unknown option {k!r}; known: {', '.join(sorted(known))}")
        try:
            over[k] = json.loads(v)
        except json.JSONDecodeError:
            over[k] = v
    try:
        obj = replace(cls(), **{k: v for k, v in over.items() if k in known})
        v = getattr(obj, "validate", None)
        if callable(v):
            v()
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{flag}: bad value ({e})") from None
    return obj


def _fit_config(args):
    from synth.lab.fit import FitConfig
    return _options(FitConfig, getattr(args, "fit_option", []), "--fit-option", {"seed": args.seed})


def _diagnose_config(args):
    from synth.lab.diagnose import DiagnoseConfig
    return _options(DiagnoseConfig, getattr(args, "diagnose_option", []), "--diagnose-option")


def _jsonable(x):
    try:
        json.dumps(x)
        return x
    except TypeError:
        if hasattr(x, "to_json"):
            return x.to_json()
        if hasattr(x, "to_dict"):
            return x.to_dict()
        import dataclasses
        if dataclasses.is_dataclass(x):
            return {k: _jsonable(v) for k, v in dataclasses.asdict(x).items()}
        return repr(x)


def _write_json(path: Path, data: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, default=_jsonable) + "\n")
    return path


def _lab_config(args, cmd: str, measured, config, extra: dict | None = None) -> dict:
    d = {"command": f"sensor {cmd}", "sequence": str(Path(args.seq).resolve()),
         "effects": args.effects, "model": args.model, "fit": bool(getattr(args, "fit", False)),
         "frames": args.frames, "preset": args.preset, "seed": args.seed,
         "fit_options": list(getattr(args, "fit_option", []) or []),
         "measured": measured.describe(), "effects_used": config.names(enabled_only=True)}
    d.update(extra or {})
    return d


def _require_fittable(config, prefix: str = "") -> None:
    """Raise when the fit would have nothing to search: the lab's parameter space
    (:func:`synth.lab.fit.param_specs`: the effects' FITTABLE plus the lab-side extras such as
    the lens distortion coefficients), not the effects' FITTABLE alone."""
    from synth.lab.fit import param_specs
    if not param_specs(config):
        raise ConfigError(f"{prefix}the model has no fittable parameter (add effects with --effects)")


def _maybe_fit(args, measured, config, out_dir: Path | None):
    """Fit the parameters when --fit was given; saves out_dir/model.json and returns (config, FitResult|None)."""
    if not getattr(args, "fit", False):
        return config, None
    _require_fittable(config, "--fit: ")
    from synth.lab.fit import fit_model
    from synth.lab.model import save_model
    res = fit_model(measured, config, fit_config=_fit_config(args), progress=True)
    if out_dir is not None:
        save_model(res.config, out_dir / "model.json", fit_info=res.to_json())
    print(f"fitted {len(res.params)} parameters in {res.evaluations} evaluations ({res.seconds:.1f} s): "
          f"gap {res.gap_before:.4f} -> {res.gap:.4f}", file=sys.stderr)
    return res.config, res


def _step_label(args, config, fit) -> str | None:
    if getattr(args, "label", None):
        return args.label
    if fit is not None or args.model:
        names = ", ".join(config.names(enabled_only=True)) or "ideal"
        return f"{names} ({'fitted' if fit is not None else 'model ' + Path(args.model).name})"
    return None


def _measured_and_model(args, preload: bool = True):
    """(measured sequence of ``args.seq``, sensor model from ``--effects`` / ``--model``)."""
    measured = _load_measured(args, preload=preload)
    return measured, build_config(measured, args.effect_list, args.model)


def _effect_names_option(text: str, flag: str) -> list[str]:
    """A non-empty comma list of effect names given to ``flag``."""
    names = parse_effects(text)
    if not isinstance(names, list) or not names:
        raise ConfigError(f"{flag} needs a comma list of effect names")
    return names


@contextmanager
def _timed(timings: dict, key: str):
    """Store the wall time of the block in ``timings[key]`` (seconds)."""
    t = time.perf_counter()
    try:
        yield
    finally:
        timings[key] = time.perf_counter() - t


# --------------------------------------------------------------------------- simulate

def _cmd_simulate(args) -> int:
    _check_model_args(args)
    out = Path(args.out)
    t0 = time.perf_counter()
    measured, config = _measured_and_model(args, preload=False)  # streams; a fit reads only its own frames
    config, fit = _maybe_fit(args, measured, config, out)
    n_new, n_kept = write_simulated_sequence(measured, config, out, seed=args.seed, overwrite=args.overwrite,
                                             lab_config=_lab_config(args, "simulate", measured, config))
    print(f"{out}: simulated {n_new} frames (kept {n_kept} already there) with "
          f"{', '.join(config.names(enabled_only=True)) or 'no effect (ideal depth)'} in "
          f"{time.perf_counter() - t0:.1f} s")
    return 0




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

    Frames without a ground-truth pose (and, with ``--frames``, those not picked) cannot be
    simulated and are left out of depth.txt/rgb.txt; every other line is SEQ's own.

    Resumable: images are written before their index line, so after an interruption the frames
    listed in depth.txt are complete; a re-run with the same configuration skips them (frame k
    is simulated with seed ``seed + frame index``, so the result is the same as an
    uninterrupted run). A different configuration in ``out_dir`` is an error unless ``overwrite``.
    Returns (frames written now, frames kept from before).
    """
    import shutil

    from data_tools.camera import write_camera_json
    from data_tools.scene_spec import write_scene_json
    from data_tools.sequence import SequenceReader, link_or_copy, write_depth_png

    out = Path(out_dir)
    src = Path(measured.seq_dir)
    if out.resolve() == src.resolve():
        raise RealgapError(f"{out}: the output must not be the measured sequence itself")
    reader = SequenceReader(src)
    signature = {"sensor_config": config.to_json(), "seed": int(seed), "frame_indices": list(measured.frame_indices),
                 "sequence": str(src.resolve())}
    sig_path = out / ".simulate_signature.json"
    if (out / "depth.txt").exists():
        if overwrite:
            for name in ("depth.txt", "rgb.txt", "groundtruth.txt", sig_path.name):
                (out / name).unlink(missing_ok=True)
            shutil.rmtree(out / "depth", ignore_errors=True)
            shutil.rmtree(out / "rgb", ignore_errors=True)
        else:
            old = json.loads(sig_path.read_text()) if sig_path.exists() else None
            if old != json.loads(json.dumps(signature)):
                raise RealgapError(f"{out}: holds a different simulation (other model, seed, frames or source); "
                                   f"use --overwrite to replace it")
    out.mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    sig_path.write_text(json.dumps(signature) + "\n")
    write_camera_json(out / "camera.json", reader.camera)
    if (src / "groundtruth.txt").is_file():
        shutil.copyfile(src / "groundtruth.txt", out / "groundtruth.txt")
    if not (out / "scene.json").exists():
        write_scene_json(out, measured.scene)
    config.save(out / "sensor_config.json")
    if lab_config is not None:
        _write_json(out / LAB_CONFIG_FILE, lab_config)

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
    bar = None
    if progress and todo:
        from tqdm import tqdm
        bar = tqdm(total=len(measured), initial=kept, desc="simulating", unit="frame", file=sys.stderr, leave=False)
    for k in todo:
        i = measured.frame_indices[k]
        rel = reader.depth_files[i]
        res = sim.simulate(measured.poses[k], seed=int(seed) + i, prev_pose=measured.prev_poses[k])
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
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return len(todo), kept


# --------------------------------------------------------------------------- compare

def _cmd_compare(args) -> int:
    from synth.lab.compare import compare_preset
    from synth.lab.report import run_lab
    _check_model_args(args)
    out = Path(args.out)
    timings = {}
    with _timed(timings, "load_s"):
        measured, config = _measured_and_model(args)
    with _timed(timings, "fit_s"):
        config, fit = _maybe_fit(args, measured, config, out)
    with _timed(timings, "simulate_s"):
        sims = _simulate_all(measured, config, args.seed)
    with _timed(timings, "compare_report_s"):
        obs = measured.observations(sims)
        ccfg = compare_preset(args.compare_preset)
        ccfg.seed = int(args.seed)
        effects = config.names(enabled_only=True)
        result = run_lab(obs, out, effects=effects, label=_step_label(args, config, fit), config=ccfg,
                         compare_against=args.compare_against, report_frames=args.report_frames)
    config.save(out / "sensor_config.json")
    extra = {"compare_preset": args.compare_preset, "compare_against": args.compare_against,
             "label": args.label, "gap": result.gap, "timings_s": {k: round(v, 3) for k, v in timings.items()}}
    if fit is not None:
        extra["fit"] = fit.to_json()
    _write_json(out / LAB_CONFIG_FILE, _lab_config(args, "compare", measured, config, extra))
    from synth.lab.history import load_history
    hist = load_history(out)
    trail = " -> ".join(f"{e['gap']:.4f}" for e in hist[-6:])
    print(f"{out / 'report.html'}: gap {result.gap:.4f} with {', '.join(effects) or 'the ideal model'} on "
          f"{len(obs)} frames (history: {trail})")
    return 0


def _simulate_all(measured, config, seed: int) -> list:
    """Simulated depth of every kept frame, with a progress bar on stderr."""
    from tqdm import tqdm
    sim = measured.simulator(config)
    out = []
    for k in tqdm(range(len(measured)), desc="simulating", unit="frame", file=sys.stderr, leave=False):
        out.extend(measured.simulate(config, seed=seed, frames=[k], simulator=sim))
    return out


# --------------------------------------------------------------------------- diagnose

def _cmd_diagnose(args) -> int:
    from synth.lab.diagnose import diagnose
    from synth.lab.report import write_diagnosis_report
    _check_model_args(args)
    out = Path(args.out)
    candidates = _effect_names_option(args.candidates, "--candidates") if args.candidates else None
    timings = {}
    with _timed(timings, "load_s"):
        measured, config = _measured_and_model(args)
    with _timed(timings, "diagnose_s"):
        diag = diagnose(measured, config, candidates=candidates, fit_config=_fit_config(args), progress=True,
                        diagnose_config=_diagnose_config(args))
    diag.save(out)
    models = save_diagnosis_models(diag, out, top=args.top)
    with _timed(timings, "report_s"):
        figs = diagnosis_figure_data(measured, config, diag, top=args.top, n_frames=args.report_frames,
                                     seed=args.seed)
        path = write_diagnosis_report(diag.to_json(), figs["base"], figs["candidates"], out,
                                      measured_name=str(args.seq))
    config.save(out / "sensor_config.json")
    _write_json(out / LAB_CONFIG_FILE, _lab_config(args, "diagnose", measured, config, {
        "candidates": candidates, "top": args.top, "gap": diag.gap,
        "models": {k: str(v) for k, v in models.items()},
        "timings_s": {k: round(v, 3) for k, v in timings.items()}}))
    top = ", ".join(f"{c.effect} ({100 * c.gain:.0f} %)" for c in diag.ranking[:3])
    print(f"{path}: gap {diag.gap:.4f}; best candidates: {top or 'none'}")
    return 0


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

def _cmd_fit(args) -> int:
    from synth.lab.fit import fit_model
    from synth.lab.model import save_model
    _check_model_args(args)
    out = Path(args.out)
    measured, config = _measured_and_model(args)
    _require_fittable(config)
    names = None
    if args.only:
        names = _effect_names_option(args.only, "--only")
        missing = [n for n in names if n not in config.names()]
        if missing:
            raise ConfigError(f"--only names effects that are not in the model: {', '.join(missing)}")
    res = fit_model(measured, config, names=names, fit_config=_fit_config(args), progress=True)
    info = res.to_json()
    info["lab_config"] = _lab_config(args, "fit", measured, res.config)
    path = save_model(res.config, out, fit_info=info)
    params = ", ".join(f"{k}={v:.4g}" for k, v in res.params.items())
    print(f"{path}: gap {res.gap_before:.4f} -> {res.gap:.4f} after {res.evaluations} evaluations "
          f"({res.seconds:.1f} s); {params}")
    return 0
