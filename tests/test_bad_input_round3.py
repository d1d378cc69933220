"""A third table of bad input of issue 44's kinds ("more cases of the same kinds, not listed here, will be
tried"), the contract of tests/test_bad_input.py: exit 1, ONE line naming the file or the flag and the
problem, every file that existed before byte-identical afterwards, nothing left behind.

The rows marked ``# was:`` failed before this table (what they did then); the others held already and
stay here so that they keep holding. Model headers are edited copies of the shipped models
(recog/weights/chairs, slam/neural/weights/front_2d): the header is read before any weight.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from app.cli import main
from tests.test_bad_input import check_one_line_error, good  # noqa: F401 (the fixture: S, a 4-frame 160x120 sequence, and traj.txt)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def base(good, tmp_path_factory):  # noqa: F811
    """``good`` plus RM: a finished run of S with a mesh."""
    root = tmp_path_factory.mktemp("round3")
    shutil.copytree(good, root, dirs_exist_ok=True)
    with pytest.MonkeyPatch.context() as mp:      # not os.environ: later test files read progress settings
        mp.setenv("REALGAP_NO_PROGRESS", "1")
        assert main(["slam", "run", str(root / "S"), "--out", str(root / "RM"), "--tsdf.voxel-size-m", "0.05",
                     "--tsdf.mesh-weight-threshold", "1"]) == 0
    assert (root / "RM" / "mesh.ply").is_file()
    return root


def _json(rel: str, fn):
    def edit(t: Path) -> None:
        d = json.loads((t / rel).read_text())
        fn(d)
        (t / rel).write_text(json.dumps(d))
    return edit


def _model(kind: str, fn=None):
    """A copy of a shipped model as t/RC (recogniser) or t/N2 (neural memory), its header edited by ``fn``."""
    src, name, header = {"recog": (REPO / "recog" / "weights" / "chairs", "RC", "recogniser.json"),
                         "neural": (REPO / "slam" / "neural" / "weights" / "front_2d", "N2", "neural.json")}[kind]

    def make(t: Path) -> None:
        shutil.copytree(src, t / name)
        if fn is not None:
            _json(f"{name}/{header}", fn)(t)
    return make


def _first_depth(t: Path) -> str:
    lines = [ln for ln in (t / "S" / "depth.txt").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return lines[0].split()[1]


def _unfinished_run(t: Path) -> None:
    (t / "RM" / "stats.json").unlink()
    (t / "RM" / "incomplete.json").write_text('{"command": "realgap slam run", "done": 2, "total": 4}')


PREDICT = ["recog", "predict", "{T}/RC", "{T}/S/{DEPTH0}", "--bbox", "10,10,100,100"]
FIT = ["sensor", "fit", "{S}", "--effects", "axial_noise", "--out", "{T}/m.json"]

CASES = [
    # an output inside an input it may live in (a screenshot into its folder) never replaces a file of it
    ("view: --screenshot onto an input image", ["view", "{S}", "--screenshot", "{S}/{DEPTH0}", "--overwrite"],
     None, ["--screenshot", "would replace", "a file of the input"]),    # was: exit 0, the depth image overwritten
    ("slam render: --out onto the run's mesh", ["slam", "render", "{T}/RM", "--frame", "0", "--out", "{T}/RM/mesh.ply",
                                                "--overwrite"], None, ["mesh.ply", "would replace"]),  # was: replaced
    ("slam render: --out onto the run's trajectory", ["slam", "render", "{T}/RM", "--frame", "0", "--out",
                                                      "{T}/RM/trajectory.txt", "--overwrite"], None, ["trajectory.txt"]),
    ("slam run: --out S/../S/r", ["slam", "run", "{S}", "--out", "{S}/../S/r"], None, ["--out", "inside the input"]),
    ("sensor fit: MODEL.json inside the sequence", ["sensor", "fit", "{S}", "--effects", "axial_noise", "--out",
                                                    "{S}/m.json"], None, ["--out", "inside the input"]),
    ("slam run: the output holds the input", ["slam", "run", "{S}", "--out", "{T}"], None, ["contains the input"]),
    ("neural eval: --out inside the model", ["neural", "eval", "{T}/N2", "--out", "{T}/N2/e"], _model("neural"),
     ["--out", "inside the input MODEL"]),
    # option values of the lab's KEY=VALUE options: converted to the field's type, named
    ("fit: --fit-option max_evaluations=abc", FIT + ["--fit-option", "max_evaluations=abc"], None,
     ["--fit-option max_evaluations", "expected an integer"]),     # was: "bad value (invalid literal for int() ...)"
    ("fit: --fit-option max_evaluations=NaN", FIT + ["--fit-option", "max_evaluations=NaN"], None,
     ["--fit-option max_evaluations"]),                  # was: "bad value (cannot convert float NaN to integer)"
    ("fit: --fit-option max_pixels_per_frame=1e400", FIT + ["--fit-option", "max_pixels_per_frame=1e400"], None,
     ["--fit-option max_pixels_per_frame"]),             # was: unexpected OverflowError (a bug)
    ("fit: --fit-option intervals=maybe", FIT + ["--fit-option", "intervals=maybe"], None,
     ["--fit-option intervals", "true/false"]),         # was: exit 0 after a whole fit, 'maybe' taken as true
    ("diagnose: --diagnose-option candidate_evaluations=0", ["sensor", "diagnose", "{S}", "--effects", "none",
                                                            "--out", "{T}/D", "--diagnose-option",
                                                            "candidate_evaluations=0"], None, ["candidate_evaluations"]),
    # model headers with their JSON types
    ("recog: recogniser.json patch.size a string", PREDICT, _model("recog", lambda d: d["patch"].update(size="64")),
     ["recogniser.json", "patch.size", "string"]),       # was: converted silently
    ("recog: recogniser.json objects an object", PREDICT, _model("recog", lambda d: d.update(objects={"a": 1})),
     ["recogniser.json", "objects"]),                    # was: unexpected TypeError (a bug)
    ("recog: recogniser.json object name a number", PREDICT,
     _model("recog", lambda d: d["objects"][0].update(name=5)), ["recogniser.json", "objects[0].name"]),  # was: TypeError
    ("recog: recogniser.json symmetry order a string", PREDICT,
     _model("recog", lambda d: d["objects"][0]["symmetry"].update(order="1")),
     ["recogniser.json", "symmetry.order"]),             # was: exit 0, the symmetry read as a string
    ("recog: recogniser.json train a list", PREDICT, _model("recog", lambda d: d.update(train=[1])),
     ["recogniser.json", "train", "object"]),           # was: the message did not name the key
    ("neural: neural.json iterations a string", ["neural", "eval", "{T}/N2", "--out", "{T}/E"],
     _model("neural", lambda d: d["train"].update(iterations="2200")),
     ["neural.json", "iterations", "string"]),           # was: converted silently
    ("neural: neural.json image a fraction", ["neural", "eval", "{T}/N2", "--out", "{T}/E"],
     _model("neural", lambda d: d["train"].update(image=43.5)), ["neural.json", "image", "integer"]),
    ("slam run --config: loop_closure.enabled 'no'", ["slam", "run", "{S}", "--config", "{T}/c.json", "--out",
                                                      "{T}/R2"],
     lambda t: (t / "c.json").write_text('{"config": {"loop_closure": {"enabled": "no"}}}'), ["c.json", "enabled"]),
    ("slam render: the run's camera.json fx a string", ["slam", "render", "{T}/RM", "--frame", "0", "--out",
                                                        "{T}/v.png"], _json("RM/camera.json", lambda d: d.update(fx="1")),
     ["camera.json", "fx"]),
    ("make-reference: --camera file with fx a string", ["data", "make-reference", "{S}", "--out", "{T}/O",
                                                        "--camera", "{T}/cam.json"],
     lambda t: (t / "cam.json").write_text(json.dumps({**json.loads((t / "S" / "camera.json").read_text()), "fx": "1"})),
     ["cam.json", "fx"]),
    # numbers and frame ranges
    ("simulate: --spread-frames 0", ["sensor", "simulate", "{S}", "--effects", "none", "--out", "{T}/Q",
                                     "--spread-frames", "0"], None, ["--spread-frames", "must be >= 1, got 0"]),
    ("compare: --frame-slice that selects nothing, with --max-frames", ["sensor", "compare", "{S}", "--effects",
                                                                         "none", "--out", "{T}/L", "--frame-slice",
                                                                         "10:20", "--max-frames", "2"], None,
     ["--frame-slice 10:20:", "selects none"]),
    ("eval ate: --max-dt nan", ["eval", "ate", "{S}/groundtruth.txt", "{T}/traj.txt", "--max-dt", "nan"], None,
     ["--max-dt", "finite"]),
    ("slam render: --frame 99", ["slam", "render", "{T}/RM", "--frame", "99", "--out", "{T}/v.png"], None,
     ["--frame 99"]),
    ("view: --size 0x0", ["view", "{S}", "--size", "0x0", "--screenshot", "{T}/v.png"], None, ["--size"]),
    ("make-reference --plane: --roi inverted", ["data", "make-reference", "{S}", "--out", "{T}/O", "--plane",
                                                "--roi", "100,100,10,10"], None, ["--roi"]),
    # partial folders
    ("slam render: trajectory.txt missing", ["slam", "render", "{T}/RM", "--frame", "0", "--out", "{T}/v.png"],
     lambda t: (t / "RM" / "trajectory.txt").unlink(), ["trajectory.txt"]),
    ("slam run: resume a run whose config.json is cut", ["slam", "run", "{S}", "--out", "{T}/RM"],
     lambda t: (_unfinished_run(t), (t / "RM" / "config.json").write_text('{"config": ')), ["config.json", "JSON"]),
]


def test_the_table_covers_the_groups():
    assert len(CASES) >= 25
    assert {argv[0] for _, argv, _, _ in CASES} >= {"data", "sensor", "slam", "eval", "recog", "neural", "view"}


@pytest.mark.parametrize("name, argv, breaks, words", CASES, ids=[c[0] for c in CASES])
def test_round3_bad_input_is_one_line_exit_1_and_changes_nothing(name, argv, breaks, words, base, tmp_path, capsys,
                                                                 monkeypatch):
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    shutil.copytree(base, tmp_path, dirs_exist_ok=True)
    if breaks is not None:
        breaks(tmp_path)
    check_one_line_error(tmp_path, argv, words, capsys, subst={"{DEPTH0}": _first_depth(tmp_path)}, exact=True)


def test_eval_of_an_unfinished_run_says_so(base, tmp_path, capsys, monkeypatch):
    """``eval run`` on a run a kill left (incomplete.json): the numbers come with one warning line naming the
    run as unfinished, and ate.json records it (was: nothing said)."""
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    shutil.copytree(base, tmp_path, dirs_exist_ok=True)
    _unfinished_run(tmp_path)
    assert main(["eval", "run", str(tmp_path / "RM"), "--gt", str(tmp_path / "S"), "--out", str(tmp_path / "E")]) == 0
    warns = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("realgap: warning:")]
    assert any("unfinished run" in w and "RM" in w for w in warns), warns
    assert "run_complete" in (tmp_path / "E" / "ate.json").read_text()
