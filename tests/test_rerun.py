"""One rule for running a command again onto an existing output, over every command (issue 44, item 4).

The rule (docs/cli.md, README): a finished output is replaced only with ``--overwrite`` - without
it the command stops before any work with one line naming ``--overwrite`` and the output - and an
unfinished one (``incomplete.json``) is continued by the same command. One table: every command
that writes an output is run onto a finished output of its own kind (a folder holding the file that
marks its finished result, or an existing output file); each must exit 1 with that one line, and
every file is byte-identical afterwards. The same outputs marked unfinished, or with
``--overwrite``, pass the rule (checked on the parsed command, without running it).
"""
from __future__ import annotations

from pathlib import Path

import pytest

from app.cli import build_parser, main
from app.commands import RERUN, check_rerun_args, io_arguments
from data_tools.errors import RealgapError
from data_tools.outputs import INCOMPLETE_FILE, check_rerun
from tests.test_bad_input import files_of as _snapshot

CASES = [
    # (name, argv with {OUT} the output, the file that makes {OUT} a finished output; None: {OUT} is that file)
    ("batch", ["batch", "S", "--out", "{OUT}"], "results.json"),
    ("data convert-7scenes", ["data", "convert-7scenes", "SRC", "{OUT}"], "depth.txt"),
    ("data convert-7scenes --out", ["data", "convert-7scenes", "SRC", "--out", "{OUT}"], "depth.txt"),
    ("data convert-kinect-raw", ["data", "convert-kinect-raw", "SRC", "--out", "{OUT}", "--calib", "c.yml"],
     "convert.json"),
    ("data make-reference", ["data", "make-reference", "S", "--out", "{OUT}"], "reference_config.json"),
    ("data make-reference into SEQ", ["data", "make-reference", "{OUT}"], "reference_config.json"),
    ("demo", ["demo", "--out", "{OUT}"], "summary.json"),
    ("eval ate", ["eval", "ate", "a.txt", "b.txt", "--out", "{OUT}"], "ate.json"),
    ("eval rpe", ["eval", "rpe", "a.txt", "b.txt", "--out", "{OUT}"], "rpe.json"),
    ("eval run", ["eval", "run", "R", "--gt", "S", "--out", "{OUT}"], "ate.json"),
    ("eval run into RUN/eval", ["eval", "run", "{OUT}", "--gt", "S"], "eval/ate.json"),
    ("neural train", ["neural", "train", "--out", "{OUT}"], "neural.json"),
    ("neural refine-decoder", ["neural", "refine-decoder", "M", "--out", "{OUT}"], "neural.json"),
    ("neural refine-hallucination", ["neural", "refine-hallucination", "M", "--out", "{OUT}"], "neural.json"),
    ("neural eval", ["neural", "eval", "M", "--out", "{OUT}"], "neural_eval.json"),
    ("recog train", ["recog", "train", "--objects", "chairs", "--out", "{OUT}"], "recogniser.json"),
    ("recog eval", ["recog", "eval", "M", "T", "--out", "{OUT}"], "eval.json"),
    ("recog testset", ["recog", "testset", "--objects", "chairs", "--out", "{OUT}"], "labels.json"),
    ("sensor simulate", ["sensor", "simulate", "S", "--effects", "none", "--out", "{OUT}"], "depth.txt"),
    ("sensor compare", ["sensor", "compare", "S", "--effects", "none", "--out", "{OUT}"], "metrics.json"),
    ("sensor diagnose", ["sensor", "diagnose", "S", "--effects", "none", "--out", "{OUT}"], "diagnosis.json"),
    ("sensor fit", ["sensor", "fit", "S", "--effects", "axial_noise", "--out", "{OUT}"], None),
    ("slam run", ["slam", "run", "S", "--out", "{OUT}"], "stats.json"),
    ("slam render", ["slam", "render", "R", "--frame", "0", "--out", "{OUT}"], None),
    ("synda train", ["synda", "train", "--objects", "chairs", "--domain", "depth", "--out", "{OUT}"], None),
    ("synda map", ["synda", "map", "G.pt", "x.png", "--out", "{OUT}"], "contact_sheet.png"),
    ("synda augment", ["synda", "augment", "--objects", "chairs", "--domain", "depth", "--out", "{OUT}"],
     "contact_sheet.png"),
    ("synda testset", ["synda", "testset", "--objects", "chairs", "--out", "{OUT}"], "labels.json"),
    ("synda reindex", ["synda", "reindex", "M", "--out", "{OUT}"], "recogniser.json"),
    ("synth sequence", ["synth", "sequence", "--out", "{OUT}"], "depth.txt"),
    ("synth views", ["synth", "views", "--model", "m.ply", "--out", "{OUT}"], "views.jsonl"),
    ("view --screenshot", ["view", "S", "--screenshot", "{OUT}"], None),
    ("view --movie", ["view", "S", "--movie", "{OUT}"], None),
]
NOT_IN_THE_TABLE: set[str] = set()
"""Commands with an output outside the rule (none)."""




def _finished(t: Path, marker: str | None) -> Path:
    """A finished output in ``t``: the folder O with ``marker`` in it, or the file O.png."""
    if marker is None:
        out = t / "O.png"
        out.write_bytes(b"finished output")
        return out
    out = t / "O"
    (out / marker).parent.mkdir(parents=True, exist_ok=True)
    (out / marker).write_text('{"finished": true}\n')
    return out


@pytest.mark.parametrize("name, argv, marker", CASES, ids=[c[0] for c in CASES])
def test_a_finished_output_is_refused_naming_overwrite(name, argv, marker, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    out = _finished(tmp_path, marker)
    before = _snapshot(tmp_path)
    rc = main([a.replace("{OUT}", str(out)) for a in argv])
    err = [ln for ln in capsys.readouterr().err.splitlines() if not ln.startswith("realgap: warning:")]
    assert rc == 1 and len(err) == 1, err
    assert err[0].startswith("realgap: error: ") and "--overwrite" in err[0] and "finished" in err[0], err
    shown = out / marker.split("/")[0] if marker and "/" in marker else out
    assert str(shown) in err[0], err
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("name, argv, marker", CASES, ids=[c[0] for c in CASES])
def test_an_unfinished_output_or_overwrite_passes_the_rule(name, argv, marker, tmp_path):
    """``incomplete.json`` (continue) and ``--overwrite`` (replace) are what the rule lets through."""
    out = _finished(tmp_path, marker)
    args = [a.replace("{OUT}", str(out)) for a in argv]
    check_rerun_args(build_parser().parse_args(args + ["--overwrite"]))
    if marker is not None:
        folder = out / marker.split("/")[0] if "/" in marker else out
        (folder / INCOMPLETE_FILE).write_text("{}")
        check_rerun_args(build_parser().parse_args(args))


def test_every_command_with_an_output_follows_the_rule():
    """Every command that writes a file or folder (not only JSON on stdout) has a row in RERUN and here,
    and --overwrite."""
    from tests.test_cli_dialect import leaf_parsers, options
    tested = {n.split(" --")[0].split(" into")[0] for n, _, _ in CASES}
    for cmd, p in leaf_parsers().items():
        actions = {a.dest: a for a in p._actions}
        files = [dest for _, dest in io_arguments(p)[1] if actions[dest].nargs != 0]   # not a switch like --json
        if not files or cmd in NOT_IN_THE_TABLE:
            continue
        assert cmd in RERUN and cmd in tested, cmd
        assert "--overwrite" in options(p), cmd


def test_the_rule_itself(tmp_path):
    assert check_rerun(tmp_path / "none", ("a.json",), overwrite=False) == "new"
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "other.txt").write_text("x")
    assert check_rerun(tmp_path / "d", ("a.json",), overwrite=False) == "new"        # nothing of ours
    (tmp_path / "d" / "a.json").write_text("{}")
    with pytest.raises(RealgapError, match=r"finished result \(a.json\); pass --overwrite"):
        check_rerun(tmp_path / "d", ("a.json",), overwrite=False)
    assert check_rerun(tmp_path / "d", ("a.json",), overwrite=True) == "replace"
    (tmp_path / "d" / INCOMPLETE_FILE).write_text("{}")
    assert check_rerun(tmp_path / "d", ("a.json",), overwrite=False) == "resume"
    with pytest.raises(RealgapError, match="--overwrite"):
        check_rerun(tmp_path / "d" / "a.json", None, overwrite=False, flag="--json")
