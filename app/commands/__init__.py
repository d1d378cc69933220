"""Command groups of the ``realgap`` CLI, one module per group (discovered by ``app.cli``).

A group module defines ``NAME``, ``HELP`` and ``register(parser)``; inside ``register`` use
:func:`add_group` to create sub-subcommands. Commands stay thin: parse -> call a library
function -> save the result.

One dialect: the same idea has the same flag in every command, added by :func:`add_shared`
with the help text of :data:`SHARED_FLAGS` (``tests/test_cli_dialect.py`` walks the parser and
checks it): ``--out``, ``--overwrite``, ``--max-frames``, ``--spread-frames``, ``--seed``,
``--workers``, ``--no-progress``, ``--json``. A configuration dataclass's options are not written here but generated from
its fields by :func:`app.commands.flags.add_config_flags`.
"""
from __future__ import annotations

import argparse

SHARED_FLAGS: dict[str, str] = {
    "--out": "output",
    "--overwrite": "replace a finished result already at --out (without it such an output is an error)",
    "--max-frames": "the first N frames (of those any other frame option selects)",
    "--spread-frames": "N frames evenly spread over the frames used (after --max-frames)",
    "--seed": "random seed: the same seed gives the same output",
    "--workers": "parallel worker processes",
    "--no-progress": "no progress display on stderr (also: REALGAP_NO_PROGRESS=1)",
    "--json": "print the result as JSON on stdout instead of text",
}
"""The shared flags and the start of their help text (each command appends its specifics)."""

EXIT_POOR_TRACKING = 3
"""Exit code of ``slam run`` when fewer than half its frames were registered
(:func:`slam.pipeline.poor_tracking`): the run is written, but it is a failed run. 1 stays the
code of an error (nothing usable written), 130 an interrupt, 141 a closed stdout."""

RESUMES = "re-run the same command to continue: finished steps are kept and skipped"
"""``on_interrupt`` note of a command that continues an interrupted run (see :mod:`app.cli`)."""

FORBIDDEN_SYNONYMS = ("--out-dir", "--output", "--force", "--jobs", "--num-workers", "--quiet", "--random-seed",
                      "--n-frames", "--num-frames", "--limit-frames", "--first-frames", "--even-frames")
"""Other names for the shared ideas, which no command may use."""


def add_group(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """Sub-subcommand container for a group; ``realgap GROUP`` alone prints the group help."""
    parser.set_defaults(func=None, _group_parser=parser)
    return parser.add_subparsers(dest="subcommand", metavar="SUBCOMMAND")


def add_shared(p: argparse.ArgumentParser, flag: str, detail: str = "", **kwargs) -> argparse.Action:
    """Add the shared ``flag`` (one of :data:`SHARED_FLAGS`) with its standard help + ``detail``."""
    base = SHARED_FLAGS[flag]
    help_text = f"{base}: {detail}" if detail else base
    if flag in ("--overwrite", "--no-progress", "--json"):
        kwargs.setdefault("action", "store_true")
    if flag in ("--max-frames", "--spread-frames"):
        kwargs.setdefault("type", positive_int(flag))
        kwargs.setdefault("metavar", "N")
    if flag == "--workers":
        kwargs.setdefault("type", positive_int("--workers"))
        kwargs.setdefault("metavar", "N")
    if flag == "--seed":
        kwargs.setdefault("type", int)
    return p.add_argument(flag, help=help_text.replace("%", "%%"), **kwargs)


def add_align(p: argparse.ArgumentParser, default: str | None = "auto", note: str = "") -> argparse.Action:
    """The ``--align`` option of every command that scores a trajectory (``eval``, ``batch``,
    ``demo``): the same choices (:data:`slam.metrics.ALIGNERS`) and help text everywhere."""
    from slam.metrics import ALIGN_HELP, ALIGNERS
    tail = f" ({note})" if note else f" (default: {default})"
    return p.add_argument("--align", dest="align", choices=list(ALIGNERS), default=default,
                          help=(ALIGN_HELP + tail).replace("%", "%%"))


def ranged(flag: str, kind: type = int, low: float | None = None, high: float | None = None,
           low_open: bool = False):
    """argparse ``type`` of a finite ``kind`` (int or float) in [low, high] (``low_open``: (low, high]):
    the bounds as a :class:`data_tools.config.Range`, parsed and checked by the one number parser of the
    command line (:func:`app.commands.flags.number_parser`, also the generated configuration flags'), so a
    bad value reads the same everywhere: one line naming ``flag`` (``must be >= 1, got 0``), exit 1."""
    from app.commands.flags import number_parser
    from data_tools.config import Range
    rng = None if low is None and high is None else Range(low, high, open_lo=low_open)
    parse = number_parser(kind, rng)
    parse.__name__ = flag
    return parse


def positive_float(flag: str):
    """argparse ``type`` of a finite number > 0 (``--fps 0`` or ``-30`` is one line naming ``flag``)."""
    return ranged(flag, float, 0, low_open=True)


def positive_int(flag: str):
    """argparse ``type`` of a whole number >= 1 (a bad value is one line naming ``flag``, exit 1)."""
    return ranged(flag, int, 1)


RERUN: dict[str, tuple[tuple[str, tuple[str, ...] | None], ...]] = {
    "batch": (("out", ("results.json",)),),
    "data convert-7scenes": (("dst", ("depth.txt",)), ("out", ("depth.txt",))),
    "data convert-kinect-raw": (("dst", ("convert.json",)), ("out", ("convert.json",))),
    "data make-reference": (("out", ("reference_config.json", "scene.json")), ("seq", ("reference_config.json",))),
    "demo": (("out", ("summary.json",)),),
    "eval ate": (("out", ("ate.json",)),),
    "eval rpe": (("out", ("rpe.json",)),),
    "eval run": (("out", ("ate.json",)), ("run", None)),
    "neural train": (("out", ("neural.json",)),),
    "neural refine-decoder": (("out", ("neural.json",)),),
    "neural refine-hallucination": (("out", ("neural.json",)),),
    "neural eval": (("out", ("neural_eval.json",)),),
    "recog train": (("out", ("recogniser.json",)),),
    "recog eval": (("out", ("eval.json",)),),
    "recog testset": (("out", ("labels.json",)),),
    "sensor simulate": (("out", ("depth.txt",)),),
    "sensor compare": (("out", ("metrics.json",)),),
    "sensor diagnose": (("out", ("diagnosis.json",)),),
    "sensor fit": (("out", None),),
    "slam run": (("out", ("stats.json", "trajectory.txt")),),
    "slam render": (("out", None),),
    "synda train": (("out", None),),
    "synda map": (("out", ("contact_sheet.png",)),),
    "synda augment": (("out", ("contact_sheet.png",)),),
    "synda testset": (("out", ("labels.json",)),),
    "synda reindex": (("out", ("recogniser.json",)),),
    "synth sequence": (("out", ("depth.txt",)),),
    "synth views": (("out", ("views.jsonl",)),),
    "view": (("screenshot", None), ("movie", None)),
}
"""The one re-run rule (:func:`data_tools.outputs.check_rerun`, docs/cli.md) over every command:
command -> its outputs as ``(dest, finished)``: the argument naming the output and the files that make
it a finished output folder (None: the output is a file, finished when it exists). The first given
output of an entry is checked; a later entry is the default output when the earlier ones are not given
(``eval run RUN`` writes ``RUN/eval``, ``data make-reference SEQ`` writes into SEQ). ``app.cli`` checks
it before any work; ``tests/test_rerun.py`` runs every entry."""


def check_rerun_args(args: argparse.Namespace) -> None:
    """Apply the re-run rule to the parsed command ``args`` (see :data:`RERUN`)."""
    from pathlib import Path

    from data_tools.outputs import check_rerun
    cmd = " ".join(x for x in (getattr(args, "command", None), getattr(args, "subcommand", None)) if x)
    # --resume (synth sequence/views) asks explicitly to add to a finished output (frames, views): let it through
    overwrite = bool(getattr(args, "overwrite", False) or getattr(args, "resume", False))
    for k, (dest, finished) in enumerate(RERUN.get(cmd, ())):
        value = getattr(args, dest, None)
        if not isinstance(value, str) or not value:
            continue
        if cmd == "eval run" and dest == "run":         # the default --out of eval run
            value, finished = str(Path(value) / "eval"), ("ate.json",)
        flag = "--" + dest if dest in ("out", "screenshot", "movie") else dest.upper()
        check_rerun(value, finished, overwrite=overwrite, flag=flag)
        if cmd != "view":
            return


OUTPUT_FLAGS = ("--out", "--screenshot", "--movie", "--json")
"""Options naming something a command writes (``--json`` only where it takes a file name)."""
OUTPUT_POSITIONALS = ("dst",)
"""Positional arguments naming something a command writes (``data convert-* SRC DST``)."""
INPUT_FLAGS = ("--model", "--gt", "--camera", "--config", "--compare-against", "--objects", "--worlds", "--planar",
               "--lab", "--recog", "--calib", "--synda", "--backgrounds", "--textures")
"""Options naming files or folders a command reads (besides its positional arguments)."""


HELD_INPUT_FLAGS = ("--model", "--camera", "--config", "--calib", "--compare-against")
"""Inputs (a model, a calibration, an earlier lab folder) that an output folder may hold: the lab
writes its models into its own folder and reads them back. The data a command works on (its
positional arguments, --gt, --objects, ...) is never inside its output."""


def io_arguments(p: argparse.ArgumentParser) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """``(inputs, outputs)`` of a command's parser as ``(label, dest)`` pairs.

    Inputs are the positional arguments (other than :data:`OUTPUT_POSITIONALS`) and the options
    of :data:`INPUT_FLAGS`; outputs are :data:`OUTPUT_FLAGS` and :data:`OUTPUT_POSITIONALS`.
    ``app.cli`` checks with these, before any work, that no output lands in an input
    (:func:`data_tools.outputs.check_output_not_input`), so every command gets the check by
    declaring its arguments, with nothing to call.
    """
    inputs, outputs = [], []
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction) or a.dest in (argparse.SUPPRESS, "help"):
            continue
        if not a.option_strings:
            label = a.metavar if isinstance(a.metavar, str) else a.dest.upper()
            (outputs if a.dest in OUTPUT_POSITIONALS else inputs).append((label, a.dest))
        elif any(s in OUTPUT_FLAGS for s in a.option_strings):
            outputs.append((a.option_strings[0], a.dest))
        elif any(s in INPUT_FLAGS for s in a.option_strings):
            inputs.append((a.option_strings[0], a.dest))
    return inputs, outputs


def check_io(args: argparse.Namespace) -> None:
    """Refuse an output in an input for the parsed command ``args`` (see :func:`io_arguments`)."""
    from data_tools.outputs import check_output_not_input
    spec = getattr(args, "_io", None)
    if not spec:
        return

    def values(pairs):
        out = []
        for label, dest in pairs:
            v = getattr(args, dest, None)
            for item in (v if isinstance(v, (list, tuple)) else [v]):
                if isinstance(item, str):
                    out.append((label, item))
        return out
    check_output_not_input(values(spec[1]), values(spec[0]), allow_inside=getattr(args, "_io_allow_inside", ()),
                           may_hold=HELD_INPUT_FLAGS)
