"""The one result format (data_tools.results): write -> read round trips, atomic writes, content
hashes, reading files without a header, and ``realgap show`` on real command outputs."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from app.cli import main
from data_tools.errors import FormatError
from data_tools.results import (FORMAT, atomic_write_json, atomic_write_text, content_hash, find_result,
                                format_table, json_safe, make_header, read_result, results_table,
                                write_result)


def test_write_read_round_trip(tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "depth.txt").write_text("0.0 depth/0.png\n")
    h = make_header("lab.compare", inputs={"sequence": seq}, parameters={"effects": ["axial_noise"], "k": 3},
                    seed=7, timings_s={"total": 1.23456}, metrics={"gap": 0.5, "n": 3, "flag": True,
                                                                   "bad": float("nan"), "name": "x"},
                    command=["realgap", "sensor", "compare", str(seq)])
    body = {"gap": 0.5, "breakdowns": {"distance": [1, 2]}}
    path = write_result(tmp_path / "out" / "metrics.json", h, body)
    r = read_result(tmp_path / "out")   # found in the folder by its kind's file name
    assert r.path == path and r.kind == "lab.compare" and r.body == body
    assert r.header == json.loads(json.dumps(h))
    assert r.header["format"] == FORMAT and r.header["seed"] == 7
    assert r.metrics == {"gap": 0.5, "n": 3, "flag": 1}     # numbers only, NaN and strings dropped
    assert r.header["timings_s"] == {"total": 1.235}
    (inp,) = r.header["inputs"]
    assert inp["role"] == "sequence" and inp["hashed"] == ["depth.txt"] and len(inp["sha256"]) == 64


def test_folder_hash_follows_index_and_calibration_not_images(tmp_path):
    (tmp_path / "depth").mkdir()
    (tmp_path / "depth.txt").write_text("0.0 depth/0.png\n")
    (tmp_path / "depth" / "0.png").write_bytes(b"a")
    h0, files = content_hash(tmp_path)
    assert files == ["depth.txt"]
    (tmp_path / "depth" / "0.png").write_bytes(b"b")
    assert content_hash(tmp_path)[0] == h0
    (tmp_path / "camera.json").write_text("{}")
    h1 = content_hash(tmp_path)[0]
    assert h1 != h0
    (tmp_path / "depth.txt").write_text("0.1 depth/0.png\n")
    assert content_hash(tmp_path)[0] not in (h0, h1)


def test_an_interrupted_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = atomic_write_text(tmp_path / "a.json", '{"old": 1}\n')

    def boom(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_json(path, {"new": 2})
    assert json.loads(path.read_text()) == {"old": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]   # no temporary file left


def test_json_safe_makes_strict_json():
    d = json_safe({"a": np.float32(1.5), "b": [np.nan, np.inf, 2], "c": np.arange(3), 4: (np.int64(5),)})
    assert d == {"a": 1.5, "b": [None, None, 2], "c": [0, 1, 2], "4": [5]}
    json.dumps(d, allow_nan=False)


def test_legacy_file_without_header_and_bad_files(tmp_path):
    (tmp_path / "stats.json").write_text(json.dumps({"frames": 40, "stats": {"rmse": 0.1}, "name": "x"}))
    r = read_result(tmp_path / "stats.json")
    assert r.header == {} and r.kind == "unknown" and r.metrics == {"frames": 40, "rmse": 0.1}
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(FormatError, match="bad.json"):
        read_result(tmp_path / "bad.json")
    (tmp_path / "new.json").write_text(json.dumps({"header": {"format": FORMAT, "format_version": 99}}))
    with pytest.raises(FormatError, match="newer"):
        read_result(tmp_path / "new.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match="no result file"):
        find_result(tmp_path / "empty")


def test_table_lines_results_up():
    from data_tools.results import Result
    a = Result(None, {"kind": "eval.ate", "seed": 1, "metrics": {"rmse": 0.1234567, "pairs": 40}})
    b = Result(None, {"kind": "eval.ate", "metrics": {"rmse": 0.2, "extra": 3}})
    cols, rows = results_table([a, b], ["a", "b"])
    assert cols == ["", "unit", "a", "b"]
    assert rows[0] == ["kind", "", "eval.ate", "eval.ate"] and rows[1] == ["seed", "", "1", ""]
    assert rows[3:] == [["rmse", "m", "0.123457", "0.2"], ["pairs", "count", "40", "-"], ["extra", "?", "-", "3"]]
    lines = format_table(cols, rows).splitlines()
    assert len({len(ln) for ln in lines}) == 1      # aligned columns


def test_show_lines_up_eval_outputs(tmp_path, capsys):
    from test_eval_cli import _pair
    from data_tools.trajectory import write_tum
    ref, est = _pair()
    write_tum(tmp_path / "gt.txt", ref)
    write_tum(tmp_path / "est.txt", est)
    gt, est = str(tmp_path / "gt.txt"), str(tmp_path / "est.txt")
    out = tmp_path / "o"                      # an output never holds an input: not tmp_path itself
    assert main(["eval", "ate", gt, est, "--out", str(out)]) == 0
    assert main(["eval", "rpe", gt, est, "--out", str(out), "--overwrite"]) == 0
    tmp_path = out
    ate, rpe = json.loads((tmp_path / "ate.json").read_text()), json.loads((tmp_path / "rpe.json").read_text())
    capsys.readouterr()
    assert main(["show", str(tmp_path / "ate.json"), str(tmp_path / "rpe.json")]) == 0
    rows = {ln.split()[0]: ln.split()[1:] for ln in capsys.readouterr().out.splitlines()[2:]}
    assert rows["kind"] == ["eval.ate", "eval.rpe"]
    assert rows["rmse"] == ["m", f"{ate['rmse']:.6g}", f"{rpe['rmse']:.6g}"]          # every number has its unit
    assert rows["rotation_rmse"][0] == "deg" and rows["pairs"][0] == "count"
    for r in (read_result(tmp_path / "ate.json"), read_result(tmp_path / "rpe.json")):
        assert [i["role"] for i in r.header["inputs"]] == ["reference", "estimate"]
        assert r.header["command"].startswith("realgap eval")
    assert main(["show", str(tmp_path / "ate.json"), "--json"]) == 0
    (shown,) = json.loads(capsys.readouterr().out)
    assert shown["metrics"]["rmse"] == ate["rmse"]
    assert main(["show", str(tmp_path / "missing.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "missing.json" in err


def test_written_files_follow_the_umask(tmp_path):
    from synth.lab.history import append_history
    old = os.umask(0o022)
    try:
        append_history(tmp_path, ["axial_noise"], 0.5)
        p = atomic_write_json(tmp_path / "r.json", {"a": 1})
    finally:
        os.umask(old)
    for f in (tmp_path / "history.json", p):
        assert (f.stat().st_mode & 0o777) == 0o644, f
