"""``realgap sensor``: the sensor lab on a measured sequence (simulate, compare, diagnose, fit).

A measured sequence SEQ is a TUM-layout folder with ``camera.json`` (intrinsics + sensor block),
``groundtruth.txt`` and ``scene.json`` (the reference geometry; ``realgap data make-reference``
fuses one from the sequence itself). Every subcommand simulates SEQ's frames at their
ground-truth poses with a sensor model (a device preset derived from camera.json plus the
effects named by ``--effects`` and/or loaded from ``--model``) and works with the result:

* ``sensor simulate SEQ --effects E1,E2 [--fit] [--model M] --out OUTSEQ``: a simulated copy of
  SEQ in the TUM layout, same timestamps and file names;
* ``sensor compare SEQ --effects ... --out DIR``: DIR/metrics.json (``gap`` + breakdowns),
  DIR/report.html, and one more step in DIR/history.json;
* ``sensor diagnose SEQ --effects ... --out DIR``: DIR/diagnosis.json (candidate effects ranked
  by how much of the gap they remove) and DIR/diagnosis.html with their signature figures;
* ``sensor fit SEQ --effects ... --out MODEL.json``: the fitted model, reusable with ``--model``;
* ``sensor effects [NAME]`` and ``sensor presets [NAME]``: what the model knows (every effect with
  its physics and parameters: units, defaults per preset, plausible range, fit range; every device),
  generated from the registry (:mod:`synth.sensor.catalog`).

``--effects`` takes a comma list of effect names, ``none`` (the ideal model: ideal depth, no
effect), ``physical`` or ``direct`` (the preset's pipelines). With ``--model`` the model's
effects and parameters are used on SEQ's geometry, and names in ``--effects`` that the model
lacks are added with the preset's defaults. The effective configuration is saved next to every
output (``lab_config.json``, ``sensor_config.json``). The work is done by :mod:`synth.lab.runs`;
this module parses the options and prints one line.
"""
from __future__ import annotations

import argparse
import sys

from app.commands import RESUMES, add_shared, ranged
from synth.lab.runs import LabRequest, effect_names_option

NAME = "sensor"
HELP = "sensor lab on a measured sequence: simulate it, compare, diagnose the gap, fit a model"
DESCRIPTION = ("Simulate a measured RGB-D sequence (camera.json + groundtruth.txt + scene.json) with a "
               "depth-sensor model, measure the realism gap, rank missing effects and fit parameters.")

DEFAULT_SPREAD = {"simulate": None, "compare": 24, "diagnose": 12, "fit": 12}
"""Default ``--spread-frames`` per subcommand (None = every frame used): the lab measures on a sample
spread over the sequence, which represents it better than its first frames."""


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands import add_group
    sub = add_group(parser)
    _add_simulate(sub)
    _add_compare(sub)
    _add_diagnose(sub)
    _add_fit(sub)
    _add_catalog(sub)


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
    n = DEFAULT_SPREAD[cmd]
    add_shared(p, "--max-frames", "of the frames with a pose in --frame-slice (default: all)")
    add_shared(p, "--spread-frames", f"(default {'all' if n is None else n})", default=n)
    p.add_argument("--frame-slice", metavar="START:STOP:STEP",
                   help="only these frames (Python slice over the frames with a pose, before --max-frames), "
                        "e.g. fit on 0::2 and compare on 1::2 to test on frames held out from the fit")
    p.add_argument("--preset", help="sensor preset to start from (default from camera.json's sensor type: "
                                    "kinect_v1, realsense_d435, kinect_v2; 'realgap sensor presets' lists them)")
    add_shared(p, "--seed", "of the simulation and of the pixel samples (default 0)", default=0)
    add_shared(p, "--no-progress")
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
    add_shared(p, "--out", "the simulated sequence folder", required=True, metavar="OUTSEQ")
    add_shared(p, "--overwrite", "a different simulation in OUTSEQ (the same one is continued)")
    p.set_defaults(func=_cmd_simulate, on_interrupt=RESUMES)


def _add_compare(sub) -> None:
    from synth.lab.compare import PRESETS
    p = sub.add_parser("compare", help="measure the gap between SEQ and its simulation; report + history",
                       description="Compare SEQ with its simulation: DIR/metrics.json (gap, breakdowns by "
                                   "distance, incidence, radial distance, material, edge distance), "
                                   "DIR/report.html (error maps, binned curves, worst regions, gap history). "
                                   "Every run appends one step to DIR/history.json; a finished DIR is replaced "
                                   "only with --overwrite (or continue its history in a new folder with "
                                   "--compare-against DIR).")
    _common(p, "compare")
    add_shared(p, "--out", "lab folder (report, metrics; each run adds a step to its history)", required=True,
               metavar="DIR")
    add_shared(p, "--overwrite", "a finished comparison in DIR: report and metrics are replaced, the folder's gap "
                                 "history keeps its steps and gets this one")
    p.add_argument("--compare-against", metavar="PREVDIR",
                   help="continue the gap history of an earlier lab folder")
    p.add_argument("--label", help="label of this step in the history (default: the effects)")
    p.add_argument("--compare-preset", default="default", choices=sorted(PRESETS),
                   help="sampling of the comparison (default 20k pixels/frame, fast 5k, exact all)")
    p.add_argument("--report-frames", type=ranged("--report-frames", int, 0), default=4, metavar="K",
                   help="frames with error-map figures in the report (default 4)")
    p.set_defaults(func=_cmd_compare)


def _add_diagnose(sub) -> None:
    p = sub.add_parser("diagnose", help="rank the effects missing from a model by how much gap they remove",
                       description="Try every candidate effect not in the model (each fitted to SEQ), rank "
                                   "them by gain = (gap - gap_after) / gap and write DIR/diagnosis.json and "
                                   "DIR/diagnosis.html (signature figures of the top candidates).")
    _common(p, "diagnose", fit_flag=False)
    add_shared(p, "--out", "folder for diagnosis.json/.html and the candidates' models", required=True,
               metavar="DIR")
    add_shared(p, "--overwrite", "a finished diagnosis in DIR (an interrupted one is continued)")
    p.add_argument("--candidates", metavar="E1,E2,...", help="candidate effects (default: every effect that "
                                                             "applies to the sensor type and is not in the model)")
    p.add_argument("--top", type=ranged("--top", int, 0), default=3, metavar="K",
                   help="candidates explained with figures (default 3)")
    p.add_argument("--report-frames", type=ranged("--report-frames", int, 0), default=3, metavar="K",
                   help="frames simulated per top candidate for the figures (default 3)")
    p.add_argument("--diagnose-option", action="append", default=[], metavar="KEY=VALUE",
                   help="DiagnoseConfig option, repeatable (e.g. candidate_evaluations=20, refit_model=false)")
    p.set_defaults(func=_cmd_diagnose, on_interrupt=RESUMES)


def _add_fit(sub) -> None:
    p = sub.add_parser("fit", help="fit the parameters of a sensor model to SEQ; save MODEL.json",
                       description="Fit the fittable parameters of the model's effects to SEQ (minimising "
                                   "the gap) and save the model with its fit record.")
    _common(p, "fit", fit_flag=False)
    add_shared(p, "--out", "the fitted model file", required=True, metavar="MODEL.json")
    add_shared(p, "--overwrite", "an existing MODEL.json (an interrupted fit is continued)")
    p.add_argument("--only", metavar="E1,E2,...", help="fit only these effects' parameters (default: all)")
    p.set_defaults(func=_cmd_fit, on_interrupt=RESUMES)


def _add_catalog(sub) -> None:
    p = sub.add_parser("effects", help="list the sensor effects: physics, parameters, units, defaults, ranges",
                       description="Every registered sensor effect (built-in and from $REALGAP_EFFECT_PATH) with "
                                   "its one-line physics; with NAME its parameters: unit, default, the value each "
                                   "preset sets, plausible range, and the range a fit may search.")
    p.add_argument("name", nargs="?", help="one effect, in detail")
    add_shared(p, "--json")
    p.set_defaults(func=_cmd_catalog, catalog="effects")
    p = sub.add_parser("presets", help="list the sensor presets (devices) and their numbers",
                       description="Every device preset; with NAME every field with its meaning, the effects "
                                   "of its physical and direct models and the parameter values it sets.")
    p.add_argument("name", nargs="?", help="one preset, in detail")
    add_shared(p, "--json")
    p.set_defaults(func=_cmd_catalog, catalog="presets")


# --------------------------------------------------------------------------- commands

def first_frames_slice(frame_slice: str | None, first: int | None, count) -> str | None:
    """The ``--frame-slice`` text selecting the first ``first`` frames of ``frame_slice`` (``--max-frames``
    after ``--frame-slice``), for :class:`synth.lab.runs.LabRequest`, whose own ``max_frames`` is the
    evenly spread sample (``--spread-frames``). ``0::2`` and 5 -> ``0:10:2``. ``count()``: the number of
    frames with a pose, called when a slice is given (to resolve a negative START or STOP, and to refuse
    a slice that selects nothing in the user's words; 0 when unknown: the lab's own check follows)."""
    if first is None:
        return frame_slice
    from data_tools.errors import ConfigError
    from synth.lab.measured import parse_frame_slice
    sl = parse_frame_slice(frame_slice) if frame_slice else slice(None)
    start, stop, step = sl.start, sl.stop, sl.step or 1
    if frame_slice:          # the error of a slice that selects nothing names the slice as the user wrote it
        n = int(count())
        if n and not len(range(*sl.indices(n))):
            raise ConfigError(f"--frame-slice {frame_slice}: selects none of the {n} frames with a pose")
        start, stop, step = sl.indices(n) if (start or 0) < 0 or (stop or 0) < 0 else (start, stop, step)
    start = start or 0
    end = start + first * step
    return f"{start}:{end if stop is None else min(stop, end)}:{step}"


def _frames_with_pose(seq: str) -> int:
    """Frames of ``seq`` with a ground-truth pose (as :meth:`synth.lab.measured.MeasuredSequence.load` counts)."""
    import math

    from data_tools.sequence import SequenceReader
    from data_tools.errors import RealgapError
    try:
        reader = SequenceReader(seq)
        if not reader.has_groundtruth:
            return 0
        return sum(all(math.isfinite(float(x)) for x in pose.flat) for pose in reader.poses)
    except RealgapError:       # a bad sequence: the lab names the problem when it opens it
        return 0


def _request(args) -> LabRequest:
    return LabRequest(seq=args.seq, effects=args.effects, model=args.model, fit=bool(getattr(args, "fit", False)),
                      max_frames=args.spread_frames, preset=args.preset, seed=args.seed,
                      frame_slice=first_frames_slice(getattr(args, "frame_slice", None), args.max_frames,
                                                      lambda: _frames_with_pose(args.seq)),
                      fit_options=list(getattr(args, "fit_option", []) or []))


def _log(msg: str) -> None:
    print(msg, file=sys.stderr)


def _effects_text(config) -> str:
    return ", ".join(config.names(enabled_only=True))


def _cmd_simulate(args) -> int:
    from synth.lab.runs import simulate_sequence
    r = simulate_sequence(_request(args), args.out, overwrite=args.overwrite, log=_log)
    print(f"{r.out}: simulated {r.frames_written} frames (kept {r.frames_kept} already there) with "
          f"{_effects_text(r.config) or 'no effect (ideal depth)'} in {r.seconds:.1f} s")
    return 0


def _cmd_compare(args) -> int:
    from synth.lab.runs import compare_sequence
    r = compare_sequence(_request(args), args.out, compare_against=args.compare_against, label=args.label,
                         compare_preset=args.compare_preset, report_frames=args.report_frames, log=_log)
    trail = " -> ".join(f"{e['gap']:.4f}" for e in r.history[-6:])
    print(f"{r.report}: gap {r.result.gap:.4f} with {_effects_text(r.config) or 'the ideal model'} on "
          f"{r.frames} frames (history: {trail})")
    return 0


def _cmd_diagnose(args) -> int:
    from synth.lab.runs import diagnose_sequence
    candidates = effect_names_option(args.candidates, "--candidates") if args.candidates else None
    req = _request(args)
    diag, path = diagnose_sequence(req, args.out, candidates=candidates, top=args.top,
                                   report_frames=args.report_frames, diagnose_options=args.diagnose_option,
                                   overwrite=args.overwrite, log=_log)
    top = ", ".join(f"{c.effect} ({100 * c.gain:.0f} %)" for c in diag.ranking[:3])
    print(f"{path}: gap {diag.gap:.4f}; best candidates: {top or 'none'}")
    return 0


def _cmd_fit(args) -> int:
    from synth.lab.runs import fit_sequence
    req = _request(args)
    only = effect_names_option(args.only, "--only") if args.only else None
    res, path = fit_sequence(req, args.out, only=only, overwrite=args.overwrite, log=_log)
    iv = res.intervals
    params = ", ".join(f"{k}={v:.4g}" + (f" [{iv[k][0]:.4g}, {iv[k][1]:.4g}]" if k in iv else "")
                       for k, v in res.params.items())
    bound = "".join(f"; AT BOUND {k}={res.params[k]:.4g} ({note.split(': ', 1)[1]})"
                    for k, note in res.at_bound.items())
    corr = "".join(f"; trade-off {k.replace('|', ' vs ')} r={r:+.2f}" for k, r in res.correlations.items() if r <= -0.7)
    from synth.lab.report import evaluations_text
    counted = evaluations_text(res.stages, res.evaluations, int(req.fit_config().max_evaluations))
    print(f"{path}: gap {res.gap_before:.4f} -> {res.gap:.4f} after {counted} "
          f"({res.seconds:.1f} s); {params}{bound}{corr}")
    return 0


def _cmd_catalog(args) -> int:
    import json
    from synth.sensor import catalog
    if args.catalog == "effects":
        entries, text = catalog.effect_catalog(args.name), catalog.format_effects
    else:
        entries, text = catalog.preset_catalog(args.name), catalog.format_presets
    print(json.dumps(entries, indent=2) if args.json else text(entries, detail=args.name is not None))
    return 0
