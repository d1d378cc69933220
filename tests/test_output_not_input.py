"""An output never lands in an input, over every command (issue 44, item 1).

One table: each command that reads a file or folder and writes an output is run with its output
(a) equal to the input, (b) inside an input folder, (c) holding the input, (d) equal to the input
through a symlink. Each must exit 1 with one line naming the output flag, before any work, and
every file that existed before is byte-identical afterwards, with nothing new written.
``IN`` is a folder holding a file ``f.txt`` (a trajectory) so that commands reading a file get
one; ``{IN}`` in a template is replaced by the input path of the case.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from app.cli import main
from data_tools.errors import RealgapError
from data_tools.outputs import check_output_not_input
from tests.test_bad_input import files_of as _snapshot

ALL = ("same", "inside", "contains", "symlink")
CMDS = [
    # (command, argv template: {IN} the input, {OUT} the output, relations refused)
    ("batch", ["batch", "{IN}", "--out", "{OUT}", "--backends", "icp"], ALL),
    ("data convert-7scenes DST", ["data", "convert-7scenes", "{IN}", "{OUT}"], ALL),
    ("data convert-7scenes", ["data", "convert-7scenes", "{IN}", "--out", "{OUT}"], ALL),
    ("data convert-kinect-raw", ["data", "convert-kinect-raw", "{IN}", "--out", "{OUT}", "--calib", "c.yml"], ALL),
    ("data make-reference", ["data", "make-reference", "{IN}", "--out", "{OUT}"], ALL),
    ("eval ate", ["eval", "ate", "{IN}/f.txt", "{IN}/f.txt", "--out", "{OUT}"], ("contains", "symlink")),
    ("eval rpe", ["eval", "rpe", "{IN}/f.txt", "{IN}/f.txt", "--out", "{OUT}"], ("contains", "symlink")),
    ("eval run --gt", ["eval", "run", "R", "--gt", "{IN}", "--out", "{OUT}"], ALL),
    ("eval run", ["eval", "run", "{IN}", "--gt", "R", "--out", "{OUT}"], ("same", "contains", "symlink")),
    ("neural train", ["neural", "train", "--worlds", "{IN}", "--out", "{OUT}"], ALL),
    ("neural refine-decoder", ["neural", "refine-decoder", "{IN}", "--out", "{OUT}"], ALL),
    ("neural refine-hallucination", ["neural", "refine-hallucination", "{IN}", "--out", "{OUT}"], ALL),
    ("neural eval", ["neural", "eval", "{IN}", "--out", "{OUT}"], ALL),
    ("recog train", ["recog", "train", "--objects", "{IN}", "--out", "{OUT}"], ALL),
    ("recog eval", ["recog", "eval", "M", "{IN}", "--out", "{OUT}"], ALL),
    ("recog eval MODEL", ["recog", "eval", "{IN}", "T", "--out", "{OUT}"], ALL),
    ("recog testset", ["recog", "testset", "--objects", "{IN}", "--out", "{OUT}"], ALL),
    ("sensor simulate", ["sensor", "simulate", "{IN}", "--effects", "none", "--out", "{OUT}"], ALL),
    ("sensor compare", ["sensor", "compare", "{IN}", "--effects", "none", "--out", "{OUT}"], ALL),
    ("sensor compare --model", ["sensor", "compare", "S", "--model", "{IN}/f.txt", "--out", "{OUT}"], ("same",)),
    ("sensor diagnose", ["sensor", "diagnose", "{IN}", "--effects", "none", "--out", "{OUT}"], ALL),
    ("sensor fit", ["sensor", "fit", "{IN}", "--effects", "none", "--out", "{OUT}"], ALL),
    ("slam run", ["slam", "run", "{IN}", "--out", "{OUT}"], ALL),
    ("slam render", ["slam", "render", "{IN}", "--frame", "0", "--out", "{OUT}"], ("same", "contains", "symlink")),
    ("synda train", ["synda", "train", "--objects", "{IN}", "--domain", "depth", "--out", "{OUT}"], ALL),
    ("synda map", ["synda", "map", "G.pt", "{IN}", "--out", "{OUT}"], ALL),
    ("synda map GEN", ["synda", "map", "{IN}", "x.png", "--out", "{OUT}"], ALL),
    ("synda augment", ["synda", "augment", "--objects", "{IN}", "--domain", "depth", "--out", "{OUT}"], ALL),
    ("synda testset", ["synda", "testset", "--objects", "{IN}", "--out", "{OUT}"], ALL),
    ("synda testset --backgrounds", ["synda", "testset", "--objects", "chairs", "--backgrounds", "{IN}", "--out", "{OUT}"], ALL),
    ("synda reindex", ["synda", "reindex", "{IN}", "--out", "{OUT}"], ALL),
    ("synda testset --textures", ["synda", "testset", "--objects", "chairs", "--textures", "{IN}", "--out", "{OUT}"], ALL),
    ("synth views", ["synth", "views", "--model", "{IN}/f.txt", "--out", "{OUT}"], ("same",)),
    ("view", ["view", "{IN}", "--screenshot", "{OUT}"], ("same", "contains", "symlink")),
]
CASES = [(name, argv, rel) for name, argv, rels in CMDS for rel in rels]




def _layout(t: Path, rel: str) -> tuple[str, str]:
    """Make the input folder (and the folder around it) for relation ``rel``; (input, output)."""
    outer = t / "outer"
    seq = outer / "IN" if rel == "contains" else t / "IN"
    seq.mkdir(parents=True)
    (seq / "f.txt").write_text("0 0 0 0 0 0 0 1\n")
    for d in ("R", "S", "M", "T"):
        (t / d).mkdir()
    if rel == "same":
        return str(seq), str(seq)
    if rel == "inside":
        return str(seq), str(seq / "sub")
    if rel == "contains":
        return str(seq), str(outer)
    os.symlink(seq, t / "link")
    return str(seq), str(t / "link")


@pytest.mark.parametrize("name, argv, rel", CASES, ids=[f"{c[0]}: {c[2]}" for c in CASES])
def test_output_in_input_is_refused_before_any_work(name, argv, rel, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    src, out = _layout(tmp_path, rel)
    # "same" for a command whose input is a file: the output is that file
    if rel == "same" and any("{IN}/f.txt" in a for a in argv):
        out = f"{src}/f.txt"
    before = _snapshot(tmp_path)
    args = [a.replace("{IN}", src).replace("{OUT}", out) for a in argv]
    rc = main(args)
    err = [ln for ln in capsys.readouterr().err.splitlines() if not ln.startswith("realgap: warning:")]
    assert rc == 1 and len(err) == 1, err
    before_out = argv[argv.index("{OUT}") - 1]
    flag = before_out if before_out.startswith("--") else "DST"
    assert err[0].startswith("realgap: error: ") and "input" in err[0], err
    assert f"output ({flag})" in err[0], (flag, err)
    assert _snapshot(tmp_path) == before


def test_every_command_with_an_input_and_an_output_is_in_the_table():
    from app.commands import io_arguments
    from tests.test_cli_dialect import leaf_parsers
    tested = {name.split(" --")[0].removesuffix(" DST") for name, _, _ in CMDS}
    need = set()
    for cmd, p in leaf_parsers().items():
        inputs, outputs = io_arguments(p)
        if inputs and outputs and not all(lab == "NAME" or lab == "RESULT" for lab, _ in inputs):
            if not (cmd == "recog predict"):      # its only output is --json to stdout
                need.add(cmd)
    need.discard("neural train-topview")           # writes into MODEL by design (no output flag)
    assert need <= tested, need - tested


def test_outputs_beside_inputs_and_expected_containers_pass(tmp_path):
    seq = tmp_path / "S"
    seq.mkdir()
    (seq / "f.txt").write_text("x")
    check_output_not_input([("--out", str(tmp_path / "O"))], [("SEQ", str(seq))])
    check_output_not_input([("--out", str(tmp_path / "S2"))], [("SEQ", str(seq))])      # a name prefix is not inside
    check_output_not_input([("--out", str(seq / "eval"))], [("RUN", str(seq))], allow_inside=("RUN",))
    check_output_not_input([("--out", str(seq))], [("SEQ", str(tmp_path / "missing"))])  # no input to protect
    # the lab's own models may live in the folder it writes (--model LAB/diagnosis/best_model.json --out LAB)
    check_output_not_input([("--out", str(seq))], [("--model", str(seq / "f.txt"))], may_hold=("--model",))
    with pytest.raises(RealgapError, match="is the input"):
        check_output_not_input([("--out", str(seq))], [("RUN", str(seq))], allow_inside=("RUN",))
    # a symlinked parent on the output side is resolved too
    os.symlink(tmp_path, tmp_path / "up")
    with pytest.raises(RealgapError, match="inside the input"):
        check_output_not_input([("--out", str(tmp_path / "up" / "S" / "x"))], [("SEQ", str(seq))])
