"""Bad input, over every command: each case exits 1 with ONE line on stderr that names the file or
the flag and the problem, never a traceback, and every file that existed before the command is
byte-identical after it (nothing finished is lost).

A case is (id, argv with ``{S}`` = a valid small sequence copied into the case's folder, ``{T}``
= the case's folder, a function that breaks something in ``{T}``, words the message must hold).
The commands run in-process through :func:`app.cli.main`, the same entry point as the console
script.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from app.cli import main


# --------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    """A valid 4-frame 160x120 ideal sequence (camera.json, scene.json, ground truth) and a valid
    trajectory, lab folder and model, made once."""
    from dataclasses import replace

    from synth.sequence import SEQUENCE_PRESETS, generate_sequence
    root = tmp_path_factory.mktemp("good")
    cfg = replace(SEQUENCE_PRESETS["kinect_v1"], frames=4, seed=0).with_resolution(160, 120)
    generate_sequence(cfg, root / "S", progress=False)
    gt = (root / "S" / "groundtruth.txt").read_text()
    (root / "traj.txt").write_text(gt)
    return root


def _write(path: Path, text: str | bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)


def _depth_files(seq: Path) -> list[Path]:
    return [seq / ln.split()[1] for ln in (seq / "depth.txt").read_text().splitlines()
            if ln.strip() and not ln.startswith("#")]


def _edit_lines(path: Path, fn) -> None:
    """Apply ``fn`` to the data lines (not the # comments) of a text file."""
    lines = path.read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    data = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    path.write_text("\n".join(head + fn(data)) + "\n")


def _png8(t: Path) -> None:
    import cv2
    f = _depth_files(t / "S")[1]
    cv2.imwrite(str(f), np.full((120, 160), 100, np.uint8))


def _png_size(t: Path) -> None:
    import cv2
    f = _depth_files(t / "S")[2]
    cv2.imwrite(str(f), np.full((60, 80), 1000, np.uint16))


def _png_truncated(t: Path) -> None:
    f = _depth_files(t / "S")[1]
    f.write_bytes(f.read_bytes()[: 200])


def _depth_scale_wrong(t: Path) -> None:
    """camera.json says 1 unit = 1 m (scale 1): the median depth becomes ~1000 m."""
    p = t / "S" / "camera.json"
    d = json.loads(p.read_text())
    d["depth_scale"] = 1.0
    p.write_text(json.dumps(d))


def _camera_no_fx(t: Path) -> None:
    p = t / "S" / "camera.json"
    d = json.loads(p.read_text())
    d.pop("fx", None)
    if "intrinsics" in d:
        d["intrinsics"].pop("fx", None)
    p.write_text(json.dumps(d))


def _unsorted_depth(t: Path) -> None:
    _edit_lines(t / "S" / "depth.txt", lambda d: [d[1], d[0], *d[2:]])


def _duplicate_depth(t: Path) -> None:
    _edit_lines(t / "S" / "depth.txt", lambda d: [d[0], d[0].split()[0] + " " + d[1].split()[1], *d[2:]])


def _nan_pose(t: Path) -> None:
    _edit_lines(t / "S" / "groundtruth.txt", lambda d: [d[0], " ".join(d[1].split()[:2] + ["nan"] + d[1].split()[3:]),
                                                           *d[2:]])


def _non_unit_quat(t: Path) -> None:
    def f(d):
        v = d[1].split()
        v[4:8] = ["0.5", "0.5", "0.5", "3.0"]
        return [d[0], " ".join(v), *d[2:]]
    _edit_lines(t / "S" / "groundtruth.txt", f)


def _traj(t: Path, fn) -> None:
    _edit_lines(t / "traj.txt", fn)


def _no_scene(t: Path) -> None:
    (t / "S" / "scene.json").unlink()


def _no_groundtruth(t: Path) -> None:
    (t / "S" / "groundtruth.txt").unlink()


def _empty_mesh(t: Path) -> None:
    _write(t / "empty.ply", "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                            "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")


def _model(t: Path, params: dict | None = None, text: str | None = None) -> None:
    if text is not None:
        _write(t / "model.json", text)
        return
    from synth.sensor.config import SensorConfig
    cfg = SensorConfig.build("kinect_v1", ["axial_noise"])
    d = cfg.to_json()
    for e in d["effects"]:
        if e["name"] == "axial_noise":
            e["params"].update(params or {})
    _write(t / "model.json", json.dumps(d))


def _finished_model(t: Path) -> None:
    _model(t)
    shutil.copy(t / "model.json", t / "fitted.json")


def _run_folder_without_trajectory(t: Path) -> None:
    (t / "R").mkdir()
    _write(t / "R" / "config.json", "{}")


def _nothing(t: Path) -> None:
    pass


CASES = [
    # data info
    ("info: sequence is a file", ["data", "info", "{T}/traj.txt"], _nothing, ["traj.txt", "file"]),
    ("info: missing folder", ["data", "info", "{T}/nope"], _nothing, ["nope", "not found"]),
    ("info: 8-bit depth", ["data", "info", "{S}", "--deep"], _png8, ["16-bit"]),
    ("info: wrong image size", ["data", "info", "{S}", "--deep"], _png_size, ["80x60"]),
    ("info: truncated png", ["data", "info", "{S}", "--deep"], _png_truncated, [".png"]),
    ("info: wrong depth scale", ["data", "info", "{S}", "--deep"], _depth_scale_wrong, ["depth_scale"]),
    ("info: unsorted timestamps", ["data", "info", "{S}"], _unsorted_depth, ["depth.txt", "sorted"]),
    ("info: duplicate timestamps", ["data", "info", "{S}"], _duplicate_depth, ["depth.txt", "duplicate"]),
    ("info: NaN pose", ["data", "info", "{S}"], _nan_pose, ["groundtruth.txt", "NaN"]),
    ("info: non-unit quaternion", ["data", "info", "{S}"], _non_unit_quat, ["groundtruth.txt", "quaternion"]),
    ("info: empty depth.txt", ["data", "info", "{S}"], lambda t: _write(t / "S" / "depth.txt", "# depth\n"),
     ["depth.txt", "no depth frames"]),
    ("info: camera.json corrupt", ["data", "info", "{S}"], lambda t: _write(t / "S" / "camera.json", "{fx: 5"),
     ["camera.json", "JSON"]),
    ("info: camera.json without fx", ["data", "info", "{S}"], _camera_no_fx, ["camera.json", "fx"]),
    # data convert-7scenes / make-reference
    ("7scenes: not a 7-Scenes folder", ["data", "convert-7scenes", "{T}/S", "--out", "{T}/O"], _nothing,
     ["frame-"]),
    ("7scenes: --out is a file", ["data", "convert-7scenes", "{T}/S", "--out", "{T}/traj.txt"], _nothing,
     ["traj.txt", "--out"]),
    ("make-reference: no ground truth", ["data", "make-reference", "{S}", "--out", "{T}/O"], _no_groundtruth,
     ["groundtruth.txt"]),
    ("make-reference: --out under a file", ["data", "make-reference", "{S}", "--out", "{T}/traj.txt/x"], _nothing,
     ["traj.txt", "is a file"]),
    # synth
    ("synth sequence: unknown scene", ["synth", "sequence", "--scene", "castle", "--out", "{T}/O"], _nothing,
     ["castle"]),
    ("synth sequence: existing sequence", ["synth", "sequence", "--preset", "small", "--out", "{S}"], _nothing,
     ["already holds a finished result", "--overwrite"]),
    ("synth views: missing model", ["synth", "views", "--model", "{T}/none.ply", "--out", "{T}/O"], _nothing,
     ["none.ply"]),
    ("synth views: empty mesh", ["synth", "views", "--model", "{T}/empty.ply", "--out", "{T}/O"], _empty_mesh,
     ["empty.ply", "empty"]),
    ("synth views: model is a folder", ["synth", "views", "--model", "{S}", "--out", "{T}/O"], _nothing,
     ["folder"]),
    # sensor
    ("compare: unknown effect", ["sensor", "compare", "{S}", "--effects", "axial_nois", "--out", "{T}/L"],
     _nothing, ["axial_nois"]),
    ("compare: unknown preset", ["sensor", "compare", "{S}", "--preset", "kinect_v9", "--effects", "none",
                                 "--out", "{T}/L"], _nothing, ["--preset", "kinect_v9"]),
    ("compare: missing scene.json", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/L"], _no_scene,
     ["scene.json"]),
    ("compare: --out is a file", ["sensor", "compare", "{S}", "--effects", "none", "--out", "{T}/traj.txt"],
     _nothing, ["traj.txt", "--out"]),
    ("compare: --model is a folder", ["sensor", "compare", "{S}", "--model", "{S}", "--out", "{T}/L"], _nothing,
     ["--model", "folder"]),
    ("compare: --model corrupt", ["sensor", "compare", "{S}", "--model", "{T}/model.json", "--out", "{T}/L"],
     lambda t: _model(t, text='{"preset": '), ["model.json"]),
    ("compare: parameter out of bounds", ["sensor", "compare", "{S}", "--model", "{T}/model.json", "--out", "{T}/L"],
     lambda t: _model(t, {"sigma2": -1.0}), ["sigma2"]),
    ("fit: finished model without --overwrite", ["sensor", "fit", "{S}", "--effects", "axial_noise", "--out",
                                                 "{T}/fitted.json"], _finished_model, ["fitted.json", "--overwrite"]),
    ("fit: unknown --fit-option", ["sensor", "fit", "{S}", "--effects", "axial_noise", "--out", "{T}/m.json",
                                   "--fit-option", "max_evals=3"], _nothing, ["max_evals"]),
    ("simulate: --out is the input", ["sensor", "simulate", "{S}", "--effects", "none", "--out", "{S}"], _nothing,
     ["--out"]),
    ("diagnose: unknown candidate", ["sensor", "diagnose", "{S}", "--effects", "none", "--candidates", "bogus",
                                     "--out", "{T}/D"], _nothing, ["bogus"]),
    ("effects: unknown name", ["sensor", "effects", "bogus_effect"], _nothing, ["bogus_effect"]),
    ("presets: unknown name", ["sensor", "presets", "kinect_v9"], _nothing, ["kinect_v9"]),
    # slam
    ("slam run: sequence is a file", ["slam", "run", "{T}/traj.txt", "--out", "{T}/R"], _nothing, ["traj.txt"]),
    ("slam run: --out is a file", ["slam", "run", "{S}", "--out", "{T}/traj.txt"], _nothing, ["traj.txt", "--out"]),
    ("slam run: --camera is a folder", ["slam", "run", "{S}", "--camera", "{S}", "--out", "{T}/R"], _nothing,
     ["--camera", "folder"]),
    ("slam run: --config missing", ["slam", "run", "{S}", "--config", "{T}/none.json", "--out", "{T}/R"], _nothing,
     ["none.json"]),
    ("slam run: --config corrupt", ["slam", "run", "{S}", "--config", "{T}/c.json", "--out", "{T}/R"],
     lambda t: _write(t / "c.json", "{\"config\": [1,"), ["c.json"]),
    ("slam run: corrupt frame", ["slam", "run", "{S}", "--out", "{T}/R"], _png_truncated,
     [".png", "--skip-unreadable"]),
    ("slam render: run without mesh", ["slam", "render", "{T}/R", "--pose", "0 0 0 0 0 0 1", "--out", "{T}/v.png"],
     _run_folder_without_trajectory, ["R"]),
    ("batch: unknown backend", ["batch", "{S}", "--backends", "icp,bogus", "--out", "{T}/B"], _nothing, ["bogus"]),
    ("batch: sequence missing", ["batch", "{T}/nope", "--backends", "icp", "--out", "{T}/B"], _nothing, ["nope"]),
    # eval
    ("ate: reference is a folder", ["eval", "ate", "{S}", "{T}/traj.txt"], _nothing, ["folder"]),
    ("ate: NaN pose", ["eval", "ate", "{S}/groundtruth.txt", "{T}/traj.txt"],
     lambda t: _traj(t, lambda d: [d[0], d[1].replace(d[1].split()[3], "nan", 1), *d[2:]]), ["traj.txt"]),
    ("ate: unsorted timestamps", ["eval", "ate", "{S}/groundtruth.txt", "{T}/traj.txt"],
     lambda t: _traj(t, lambda d: [d[2], *d[:2], *d[3:]]), ["traj.txt", "sorted"]),
    ("ate: empty trajectory", ["eval", "ate", "{S}/groundtruth.txt", "{T}/traj.txt"],
     lambda t: _write(t / "traj.txt", ""), ["traj.txt"]),
    ("ate: --out is a file", ["eval", "ate", "{S}/groundtruth.txt", "{T}/traj.txt", "--out", "{S}/depth.txt"],
     _nothing, ["depth.txt", "--out"]),
    ("ate: unknown --format", ["eval", "ate", "{S}/groundtruth.txt", "{T}/traj.txt", "--format", "tum"],
     lambda t: _write(t / "traj.txt", "1 2 3\n"), ["traj.txt"]),
    ("eval run: not a run folder", ["eval", "run", "{S}", "--gt", "{S}"], _nothing, ["trajectory.txt"]),
    # recog / view
    ("recog train: model file missing", ["recog", "train", "--objects", "{T}/none.ply", "--out", "{T}/M"], _nothing,
     ["none.ply"]),
    ("recog train: empty mesh", ["recog", "train", "--objects", "{T}/empty.ply", "--out", "{T}/M"], _empty_mesh,
     ["empty.ply", "empty"]),
    ("recog eval: model is a file", ["recog", "eval", "{T}/traj.txt", "{S}"], _nothing, ["traj.txt", "folder"]),
    ("recog testset: --out is a file", ["recog", "testset", "--objects", "chairs", "--out", "{T}/traj.txt"], _nothing,
     ["traj.txt", "--out"]),
    ("view: not a lab folder", ["view", "--lab", "{S}", "--screenshot", "{T}/v.png"], _nothing, ["lab_config.json"]),
    ("view: existing screenshot", ["view", "{S}", "--screenshot", "{T}/traj.txt"], _nothing,
     ["traj.txt", "--overwrite"]),
    ("neural eval: not a model", ["neural", "eval", "{S}"], _nothing, ["neural.json"]),
    ("neural train: no iterations", ["neural", "train", "--mode", "3d", "--iterations", "0", "--out", "{T}/N3"],
     _nothing, ["iterations", ">= 1"]),
    ("neural train: existing model", ["neural", "train", "--out", "{T}/N"],
     lambda t: (t / "N").mkdir() or _write(t / "N" / "neural.json", "{}"), ["--overwrite"]),
    ("synda map: not a generator", ["synda", "map", "{T}/traj.txt", "{T}/traj.txt", "--out", "{T}/MAP"], _nothing,
     ["traj.txt", "not a SynDA generator"]),
    ("synda train: model file missing", ["synda", "train", "--objects", "{T}/none.ply", "--domain", "depth",
                                         "--out", "{T}/G.pt"], _nothing, ["none.ply", "not found"]),
    # show / demo
    ("show: not a result", ["show", "{S}/camera.json"], _nothing, ["camera.json"]),
    ("show: corrupt JSON", ["show", "{T}/r.json"], lambda t: _write(t / "r.json", "{\"header\": "), ["r.json"]),
    ("demo: --out is a file", ["demo", "--out", "{T}/traj.txt"], _nothing, ["traj.txt"]),
]


def test_at_least_forty_cases_over_every_command():
    from tests.test_cli_dialect import leaf_parsers
    assert len(CASES) >= 40
    covered = {" ".join(a for a in argv[:2] if not a.startswith("{")) for _, argv, _, _ in CASES}
    groups = {c.split()[0] for c in leaf_parsers()}
    assert groups <= {c.split()[0] for c in covered}, groups - {c.split()[0] for c in covered}


def files_of(root: Path) -> dict[str, bytes | None]:
    """Every path under ``root`` -> its bytes (None for a folder): equal before and after = nothing changed,
    removed or left behind."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def check_one_line_error(root: Path, argv: list[str], words, capsys, subst: dict | None = None,
                         exact: bool = False) -> None:
    """Run the CLI on ``argv`` ({S} = root/S, {T} = root, plus ``subst``): exit 1, one line starting
    'realgap: error: ' holding every one of ``words``, no traceback or usage dump, and no file under ``root``
    changed or removed (``exact``: nor anything left behind). The one check of every bad-input table."""
    subst = {"{S}": str(root / "S"), "{T}": str(root), **(subst or {})}
    before = files_of(root)
    args = []
    for a in argv:
        for k, v in subst.items():
            a = a.replace(k, v)
        args.append(a)
    rc = main(args)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("realgap: warning:")]
    assert rc == 1, (rc, err)
    assert len(lines) == 1 and lines[0].startswith("realgap: error: "), err
    assert "Traceback" not in err and "unexpected" not in err and "usage:" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    after = files_of(root)
    if exact:
        assert after == before, "files changed, removed or left behind"
    else:
        changed = [f for f, b in before.items() if after.get(f, b"") != b]
        assert not changed, f"files changed or removed: {changed}"


@pytest.mark.parametrize("name, argv, breaks, words", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_1_and_loses_nothing(name, argv, breaks, words, good, tmp_path, capsys,
                                                         monkeypatch):
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    shutil.copytree(good, tmp_path, dirs_exist_ok=True)
    breaks(tmp_path)
    check_one_line_error(tmp_path, argv, words, capsys)
