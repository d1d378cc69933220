"""``realgap eval``: outputs, their agreement with the library, and one-line errors on bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from data_tools.geometry import quat_to_matrix
from data_tools.trajectory import Trajectory, read_tum, write_tum
from slam import metrics as M

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _pair(n=40, seed=0, t_shift=0.0):
    """A seeded curve as reference and a noisy, moved copy as estimate (timestamps jittered)."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = quat_to_matrix(np.c_[np.zeros((n, 2)), np.sin(0.02 * k), np.cos(0.02 * k)])
    T[:, :3, 3] = np.c_[np.cos(0.15 * k), 0.5 * np.sin(0.15 * k), 0.01 * k]
    T[:, 3, 3] = 1
    ref = Trajectory(100.0 + 0.05 * k, T)
    E = T.copy()
    E[:, :3, 3] += rng.normal(scale=0.01, size=(n, 3))
    E[:, :3, 3] += [1.0, -2.0, 0.3]
    est = Trajectory(ref.timestamps + t_shift + rng.uniform(-0.003, 0.003, n), E)
    return ref, est


@pytest.fixture
def files(tmp_path):
    ref, est = _pair()
    write_tum(tmp_path / "gt.txt", ref)
    write_tum(tmp_path / "est.txt", est)
    return tmp_path, tmp_path / "gt.txt", tmp_path / "est.txt"


def _one_line_error(capsys, *names):
    err = capsys.readouterr().err.strip()
    assert err.startswith("realgap: error:") and "\n" not in err, err
    for n in names:
        assert n in err, (n, err)
    return err


def test_ate_outputs(files, capsys):
    d, gt, est = files
    out = d / "res" / "ate.json"
    assert main(["eval", "ate", str(gt), str(est), "--out", str(d / "res")]) == 0
    data = json.loads(out.read_text())
    for k in ("rmse", "mean", "median", "std", "min", "max", "pairs", "align", "alignment", "info", "config"):
        assert k in data
    assert data["align"] == "se3" and data["pairs"] == 40
    lib = M.ate(read_tum(gt), read_tum(est), "se3", 0.02)
    assert data["rmse"] == pytest.approx(lib.rmse, abs=1e-12)
    aligned = read_tum(d / "res" / "ate_aligned.txt")
    assert len(aligned) == data["pairs"]
    # the written aligned estimate reproduces the rmse without further alignment
    assert M.ate(read_tum(gt), aligned, "none").rmse == pytest.approx(data["rmse"], abs=1e-6)
    png = d / "res" / "ate_top.png"
    assert png.read_bytes()[:8] == PNG_MAGIC
    printed = capsys.readouterr().out
    assert "ATE (align auto: se3): rmse" in printed and "40 associated pairs" in printed


def test_ate_out_options_overwrite_and_json(files, capsys):
    d, gt, est = files
    out = d / "extra" / "ate.json"
    assert main(["eval", "ate", str(gt), str(est), "--out", str(d / "extra"), "--align", "sim3",
                 "--max-dt", "0.01"]) == 0
    data = json.loads(out.read_text())
    assert data["align"] == "sim3" and data["config"]["max_dt"] == 0.01
    assert data["rmse"] == pytest.approx(M.ate(read_tum(gt), read_tum(est), "sim3", 0.01).rmse, abs=1e-12)
    assert (d / "extra" / "ate_aligned.txt").is_file() and (d / "extra" / "ate_top.png").is_file()
    # a finished result is not replaced without --overwrite (and stays byte-identical)
    before = out.read_bytes()
    capsys.readouterr()
    assert main(["eval", "ate", str(gt), str(est), "--out", str(d / "extra")]) == 1
    _one_line_error(capsys, "extra", "--overwrite")
    assert out.read_bytes() == before
    assert main(["eval", "ate", str(gt), str(est), "--out", str(d / "extra"), "--overwrite", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["rmse"] == pytest.approx(M.ate(read_tum(gt), read_tum(est), "se3", 0.02).rmse, abs=1e-12)
    assert printed["unit"] == "m" and printed["pairs"] == 40
    # one shape for one result: --json prints what ate.json holds, with --out or without
    assert printed == json.loads((d / "extra" / "ate.json").read_text())
    assert main(["eval", "ate", str(gt), str(est), "--json"]) == 0
    alone = json.loads(capsys.readouterr().out)
    assert set(alone) == set(printed) - {"files"} and alone["rmse"] == printed["rmse"]


def test_rpe_outputs(files):
    d, gt, est = files
    o = d / "rpe_out"          # not d itself: it holds the inputs, and an output never contains an input
    out = o / "rpe.json"
    assert main(["eval", "rpe", str(gt), str(est), "--out", str(o), "--delta", "0.2", "--delta-unit", "m"]) == 0
    data = json.loads(out.read_text())
    for k in ("rmse", "mean", "median", "std", "min", "max", "pairs", "align", "rotation"):
        assert k in data
    assert data["unit"] == "m" and data["align"] == "none" and data["info"]["delta_unit"] == "m"
    assert data["rotation"]["unit"] == "deg"
    lib = M.rpe(read_tum(gt), read_tum(est), 0.2, "m")
    assert data["rmse"] == pytest.approx(lib.rmse, abs=1e-12)
    assert data["n_errors"] == len(lib.errors)
    lib_rot = M.rpe(read_tum(gt), read_tum(est), 0.2, "m", relation="rotation_angle_deg")
    assert data["rotation"]["rmse"] == pytest.approx(lib_rot.rmse, abs=1e-12)
    # RPE does not align (align none): the written estimate is the associated estimate, unchanged
    aligned, e = read_tum(o / "rpe_aligned.txt"), read_tum(est)
    assert len(aligned) == data["pairs"] == 40
    np.testing.assert_array_equal(aligned.timestamps, e.timestamps)
    np.testing.assert_allclose(aligned.poses, e.poses, atol=1e-9)
    assert (o / "rpe_errors.png").read_bytes()[:8] == PNG_MAGIC


def _slam_run(d, failed=(101.0, 101.5)):
    ref, est = _pair()
    seq = d / "seq"
    seq.mkdir()
    write_tum(seq / "groundtruth.txt", ref)
    run = d / "run"
    run.mkdir()
    write_tum(run / "trajectory.txt", est)
    (run / "stats.json").write_text(json.dumps({"failed_timestamps": list(failed), "frames": 40}))
    return seq, run


def test_run_with_sequence_folder(tmp_path, capsys):
    seq, run = _slam_run(tmp_path)
    assert main(["eval", "run", str(run), "--gt", str(seq)]) == 0
    out = run / "eval"
    for name in ("ate.json", "ape_rotation.json", "rpe.json", "config.json", "estimate_aligned.txt"):
        assert (out / name).is_file(), name
    for name in ("top_view.png", "errors_over_time.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    ate = json.loads((out / "ate.json").read_text())
    assert ate["run"]["failed_frames"] == 2 and ate["unit"] == "m"
    rot = json.loads((out / "ape_rotation.json").read_text())
    assert rot["unit"] == "deg" and rot["relation"] == "rotation_angle_deg"
    rpe = json.loads((out / "rpe.json").read_text())
    assert "rotation" in rpe and rpe["info"]["delta"] == 1.0
    ref, est = read_tum(seq / "groundtruth.txt"), read_tum(run / "trajectory.txt")
    assert ate["rmse"] == pytest.approx(M.ate(ref, est).rmse, abs=1e-12)
    back = M.MetricResult.load(out / "ate")
    assert back.stats["rmse"] == ate["rmse"]
    printed = capsys.readouterr().out
    assert "2 failed frames" in printed and "ATE (align auto: se3)" in printed
    assert "APE rotation (align auto: se3)" in printed and "RPE translation (delta 1 frames, align auto: se3)" in printed


def test_run_with_tum_file_and_out(tmp_path):
    seq, run = _slam_run(tmp_path, failed=())
    (run / "stats.json").unlink()                       # stats.json is optional
    out = tmp_path / "ev"
    assert main(["eval", "run", str(run), "--gt", str(seq / "groundtruth.txt"), "--out", str(out),
                 "--align", "origin", "--delta", "2"]) == 0
    assert json.loads((out / "ate.json").read_text())["align"] == "origin"
    assert json.loads((out / "rpe.json").read_text())["info"]["delta"] == 2.0


def test_duplicate_timestamps_hint_and_flag(files, capsys):
    d, gt, est = files
    lines = gt.read_text().splitlines()
    lines.insert(5, lines[4])                           # repeat one pose
    gt.write_text("\n".join(lines) + "\n")
    out = d / "o"
    assert main(["eval", "ate", str(gt), str(est), "--out", str(out), "--strict-timestamps"]) == 1
    _one_line_error(capsys, "gt.txt", "duplicated timestamp", "--strict-timestamps")
    assert main(["eval", "ate", str(gt), str(est), "--out", str(out)]) == 0     # as evo: keep the first, warn
    err = capsys.readouterr().err
    assert "gt.txt: line" in err and "repeats the previous pose's" in err


@pytest.mark.parametrize("case", ["missing", "malformed", "no_pairs", "two_pairs", "bad_align"])
def test_ate_bad_input_is_one_line(tmp_path, capsys, case):
    ref, est = _pair()
    gt, e = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum(gt, ref)
    names = ["est.txt"]
    extra = []
    if case == "missing":
        names.append("file not found")
    elif case == "malformed":
        e.write_text("100.0 0 0 0 0 0 0 1\n100.1 0 0 0 0 0 1\n")
        names.append("line 2")
    elif case == "no_pairs":
        write_tum(e, _pair(t_shift=50.0)[1])
        names += ["gt.txt", "no associated poses"]
    elif case == "two_pairs":
        write_tum(e, est.subset(np.arange(2)))
        extra = ["--align", "se3"]                 # auto would compare 2 poses from the first one
        names = ["gt.txt", "est.txt", "at least 3"]
    elif case == "bad_align":
        write_tum(e, est)
        extra = ["--align", "none", "--max-dt", "-1"]
        names = ["--max-dt"]
    rc = main(["eval", "ate", str(gt), str(e), "--out", str(tmp_path / "o"), *extra])
    assert rc == 1
    _one_line_error(capsys, *names)
    assert not (tmp_path / "o" / "ate.json").exists()


@pytest.mark.parametrize("case", ["no_run", "no_trajectory", "no_groundtruth", "bad_stats"])
def test_run_bad_input_is_one_line(tmp_path, capsys, case):
    seq, run = _slam_run(tmp_path)
    args = ["eval", "run", str(run), "--gt", str(seq)]
    if case == "no_run":
        args[2], names = str(tmp_path / "nope"), ["nope", "not found"]
    elif case == "no_trajectory":
        (run / "trajectory.txt").unlink()
        names = ["run", "trajectory.txt"]
    elif case == "no_groundtruth":
        (seq / "groundtruth.txt").unlink()
        names = ["seq", "groundtruth.txt"]
    else:
        (run / "stats.json").write_text('{"failed_timestamps": ["a"]}')
        names = ["stats.json", "failed_timestamps"]
    assert main(args) == 1
    _one_line_error(capsys, *names)


def test_ate_and_rpe_print_without_writing(files, capsys, monkeypatch):
    d, gt, est = files
    monkeypatch.chdir(d)
    before = sorted(p.name for p in d.iterdir())
    assert main(["eval", "ate", str(gt), str(est)]) == 0
    out = capsys.readouterr().out
    lib = M.ate(read_tum(gt), read_tum(est), "se3", 0.02)
    assert f"rmse {lib.rmse:.6g} m" in out and "wrote" not in out
    assert main(["eval", "rpe", str(gt), str(est)]) == 0
    assert "RPE rotation" in capsys.readouterr().out
    assert sorted(p.name for p in d.iterdir()) == before
    assert main(["eval", "ate", str(gt), str(est), "--out", str(d / "o")]) == 0
    assert json.loads((d / "o" / "ate.json").read_text())["rmse"] == pytest.approx(lib.rmse, abs=1e-12)
