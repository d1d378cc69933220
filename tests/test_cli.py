"""The CLI: help for every group, one-line errors with exit code 1 through the real entry point."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from app.cli import build_parser, main

REPO = Path(__file__).resolve().parents[1]


def _run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True,
                          cwd=cwd or REPO, timeout=120)


def test_help_lists_subcommands_and_each_has_help(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert {"data"} <= set(sub.choices)
    for name, p in sub.choices.items():
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0
    out = capsys.readouterr().out
    assert "convert-7scenes" in out


def test_bad_input_is_one_line_exit_1(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    r = _run("data", "convert-7scenes", str(src), "--out", str(tmp_path / "dst"))
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(src) in lines[0] and "Traceback" not in r.stderr


def test_corrupt_sequence_is_one_line(tmp_path):
    seq = tmp_path / "seq"
    (seq / "depth").mkdir(parents=True)
    (seq / "depth.txt").write_text("1.0 depth/a.png\n0.5 depth/b.png\n")
    r = _run("data", "info", str(seq))
    assert r.returncode == 1 and "not sorted" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_demo_refuses_a_bad_option_before_writing(tmp_path, capsys):
    from app.cli import main
    assert main(["demo", "--room-frames", "10", "--out", str(tmp_path / "d")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "room_frames must be at least 30" in err[0]
    assert not (tmp_path / "d").exists()


def test_unexpected_errors_are_one_line_unless_debug(monkeypatch, capsys):
    import app.commands.show as show

    def bug(args):
        raise ValueError("bad\nthing")
    monkeypatch.setattr(show, "run", bug)
    monkeypatch.delenv("REALGAP_DEBUG", raising=False)
    assert main(["show", "x.json"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "realgap: error: unexpected ValueError: bad thing (a bug: re-run with --debug for the traceback)"
    with pytest.raises(ValueError):
        main(["--debug", "show", "x.json"])
    monkeypatch.setenv("REALGAP_DEBUG", "1")
    with pytest.raises(ValueError):
        main(["show", "x.json"])


def test_os_errors_name_the_file(monkeypatch, capsys, tmp_path):
    import app.commands.show as show

    def write_under_a_file(args):
        (tmp_path / "f").write_text("x")
        (tmp_path / "f" / "out.json").write_text("{}")
    monkeypatch.setattr(show, "run", write_under_a_file)
    monkeypatch.delenv("REALGAP_DEBUG", raising=False)
    assert main(["show", "x.json"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("realgap: error: ") and str(tmp_path / "f" / "out.json") in err and "\n" not in err
