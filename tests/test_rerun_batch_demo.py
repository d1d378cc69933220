"""The re-run rule (docs/cli.md) in action for ``batch`` and ``demo``: run, re-run without
``--overwrite`` (one line naming ``--overwrite``, exit 1, every file byte-identical), re-run an
interrupted output (continues: finished parts kept), re-run with ``--overwrite`` (done again).

``batch`` runs for real on a 6-frame 64x48 sequence. ``demo``'s three parts take minutes even on
its quick preset, so here they are stand-ins that write one file and count their calls: what is
tested is the command around them (the rule, what ``--overwrite`` removes, the summary);
tests/test_demo.py runs the real parts (slow).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from app.cli import main
from data_tools.outputs import INCOMPLETE_FILE
from tests.test_bad_input import files_of as _snapshot




def _one_error_line(capsys) -> str:
    err = [ln for ln in capsys.readouterr().err.splitlines() if not ln.startswith("realgap: warning:")]
    assert len(err) == 1, err
    return err[0]


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    from synth.sequence import SEQUENCE_PRESETS, generate_sequence
    root = tmp_path_factory.mktemp("rb") / "S"
    generate_sequence(replace(SEQUENCE_PRESETS["kinect_v1"], frames=6, seed=0).with_resolution(64, 48), root,
                      progress=False)
    return root


def test_batch_rerun_overwrite_and_resume(seq, tmp_path, capfd, monkeypatch):
    capsys = capfd                       # the worker processes' stderr too
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    out = tmp_path / "B"
    argv = ["batch", str(seq), "--backends", "icp", "--out", str(out), "--workers", "1", "--tsdf.voxel-size-m", "0.05"]
    assert main(argv) in (0, 1)          # 1 would be a failed run, which still finishes the report
    assert (out / "results.json").is_file() and not (out / INCOMPLETE_FILE).exists()
    stats = out / "runs" / "S" / "icp" / "stats.json"
    assert stats.is_file()
    raw = [ln for ln in capsys.readouterr().err.splitlines() if "Warning" in ln or "warnings.warn" in ln]
    assert not raw, raw                  # no raw Python warning from a worker (numba's TBB note)
    # finished: refused before any work, nothing touched
    before = _snapshot(tmp_path)
    assert main(argv) == 1
    line = _one_error_line(capsys)
    assert line.startswith("realgap: error: ") and "--overwrite" in line and str(out) in line
    assert _snapshot(tmp_path) == before
    # interrupted (no results.json yet, incomplete.json): continues; the finished run is read, not redone
    (out / "results.json").unlink()
    (out / INCOMPLETE_FILE).write_text('{"command": "realgap batch"}\n')
    run_files = _snapshot(out / "runs")
    main(argv)
    assert (out / "results.json").is_file() and not (out / INCOMPLETE_FILE).exists()
    assert _snapshot(out / "runs") == run_files
    # --overwrite: every run is done again
    mtime = stats.stat().st_mtime_ns
    main(argv + ["--overwrite"])
    assert (out / "results.json").is_file() and stats.stat().st_mtime_ns != mtime


def _stand_in_parts(monkeypatch, calls: dict):
    """Replace the demo's three parts by quick ones that write ``part.txt`` and return the facts the page
    and the summary need (tests/test_demo.py's hand-made facts)."""
    from tests.test_demo import _facts

    def part(key):
        def run(out: Path, *a, **k):
            calls[key] = calls.get(key, 0) + 1
            out.mkdir(parents=True, exist_ok=True)
            (out / "part.txt").write_text(f"{key} run {calls[key]}\n")
            return _facts(out.parent)[key]
        return run
    import app.demo.explore
    import app.demo.lab
    import app.demo.recognise
    monkeypatch.setattr(app.demo.lab, "run_lab_part", part("lab"))
    monkeypatch.setattr(app.demo.explore, "run_explore_part", part("explore"))
    monkeypatch.setattr(app.demo.recognise, "run_recog_part", part("recog"))


def test_demo_rerun_overwrite_and_resume(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    calls: dict = {}
    _stand_in_parts(monkeypatch, calls)
    out = tmp_path / "D"
    argv = ["demo", "--preset", "quick", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    assert calls == {"lab": 1, "explore": 1, "recog": 1}
    assert (out / "summary.json").is_file() and (out / "index.html").is_file()
    (out / "mine.txt").write_text("not the demo's")
    capsys.readouterr()
    # finished: refused before any work, nothing touched
    before = _snapshot(tmp_path)
    assert main(argv) == 1
    line = _one_error_line(capsys)
    assert line.startswith("realgap: error: ") and "--overwrite" in line and str(out) in line
    assert _snapshot(tmp_path) == before and calls == {"lab": 1, "explore": 1, "recog": 1}
    # interrupted: the same command continues (each real part keeps what it finished)
    (out / "summary.json").unlink()
    (out / INCOMPLETE_FILE).write_text('{"command": "realgap demo"}\n')
    assert main(argv) == 0
    assert (out / "summary.json").is_file() and not (out / INCOMPLETE_FILE).exists()
    assert (out / "lab" / "part.txt").read_text() == "lab run 2\n"
    # --overwrite: the demo's own outputs are removed and made again; anything else in the folder stays
    (out / "lab" / "stale.png").write_bytes(b"from an earlier demo")
    assert main(argv + ["--overwrite"]) == 0
    assert calls == {"lab": 3, "explore": 3, "recog": 3}
    assert not (out / "lab" / "stale.png").exists() and (out / "lab" / "part.txt").read_text() == "lab run 3\n"
    assert (out / "mine.txt").read_text() == "not the demo's" and (out / "summary.json").is_file()
