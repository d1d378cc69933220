"""The CLI rules of docs/cli.md over every command (issue 44 item 4, issue 46 section 3).

Range and type errors are one line and exit 1 naming the flag (never argparse's exit 2 and usage
dump); a value starting with a minus sign parses (``--bbox -50,-50,100,100``); a closed stdout
pipe is a quiet exit; a full disk names the file and keeps the incomplete marker; ``show``
prints a unit for every number.
"""
from __future__ import annotations

import errno
import subprocess
import sys
from pathlib import Path

import pytest

from app.cli import EXIT_BROKEN_PIPE, main
from tests.test_cli_dialect import leaf_parsers, options

REPO = Path(__file__).resolve().parents[1]

BAD_VALUES = {"--max-frames": "0", "--spread-frames": "-1", "--workers": "-2", "--fps": "0", "--frames": "0", "--seed": "x"}


def _required_args(cmd: str) -> list[str]:
    """Enough of a command line for argparse to reach the bad value (positionals and required flags)."""
    p = leaf_parsers()[cmd]
    argv = cmd.split()
    for a in p._actions:
        if not a.option_strings and a.dest not in ("help",) and a.nargs not in ("?", "*"):
            argv += ["X"] * (2 if a.nargs == 2 else 1)
        elif a.required and a.option_strings:      # a required choice gets a valid one (synda's --domain)
            argv += [a.option_strings[0], str(a.choices[0]) if a.choices else "X"]
    return argv


CASES = [(cmd, flag) for cmd, p in leaf_parsers().items() for flag in BAD_VALUES if flag in options(p)]


def test_every_flag_with_a_range_is_covered():
    assert len(CASES) >= 20 and {c for c, _ in CASES} >= {"slam run", "sensor fit", "batch", "synth sequence",
                                                          "data convert-7scenes", "recog eval"}


@pytest.mark.parametrize("cmd, flag", CASES, ids=[f"{c} {f}" for c, f in CASES])
def test_a_bad_value_is_one_line_exit_1_naming_the_flag(cmd, flag, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = main(_required_args(cmd) + [flag, BAD_VALUES[flag]])
    err = capsys.readouterr().err.strip()
    assert rc == 1, (rc, err)
    assert "\n" not in err and err.startswith("realgap: error:") and flag in err and "usage:" not in err, err
    assert sorted(tmp_path.iterdir()) == []


def test_unknown_option_and_missing_argument_are_one_line_exit_1(capsys):
    assert main(["slam", "run", "S", "--out", "R", "--nope"]) == 1
    assert main(["eval", "ate"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and "--nope" in lines[0] and "REF" in lines[1]


def test_a_negative_window_parses_without_equals(tmp_path, capsys):
    """``--bbox -50,-50,100,100`` reaches the command (which then says what is wrong with the files)."""
    assert main(["recog", "predict", str(tmp_path / "M"), str(tmp_path / "d.png"), "--bbox", "-50,-50,100,100"]) == 1
    err = capsys.readouterr().err
    assert "d.png" in err and "expected one argument" not in err


def test_a_window_mostly_outside_the_image_is_an_error():
    from data_tools.errors import RealgapError
    from recog.patches import check_bbox
    assert check_bbox([580, 400, 680, 470], 640, 480, min_inside=0.5) == (580, 400, 640, 470)   # 60 % in: kept
    with pytest.raises(RealgapError, match=r"only 4 % inside the 640x480 image"):
        check_bbox([600, 400, 900, 700], 640, 480, "--bbox", min_inside=0.5)


def test_a_closed_pipe_is_a_quiet_exit(monkeypatch, capsys):
    """``realgap sensor effects | head``: once the reader has gone, writing raises BrokenPipeError; that is a
    quiet exit (141, as a shell reports SIGPIPE), not "realgap: error: Broken pipe". In-process, because a
    subprocess whose whole output fits the pipe buffer finishes before the reader closes (a race)."""
    import app.commands.show as show

    def writes_to_a_closed_pipe(args):
        raise BrokenPipeError(32, "Broken pipe")
    monkeypatch.setattr(show, "run", writes_to_a_closed_pipe)
    assert main(["show", "x.json"]) == EXIT_BROKEN_PIPE
    err = capsys.readouterr().err
    assert "error" not in err.lower() and "Traceback" not in err, err


def test_disk_full_names_the_file_and_keeps_the_incomplete_marker(tmp_path, capsys, monkeypatch):
    import data_tools.results as R
    real_fdopen = R.os.fdopen
    calls = []

    class Full:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.f.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    def fdopen(fd, *a, **kw):
        calls.append(fd)
        f = real_fdopen(fd, *a, **kw)
        return Full(f) if len(calls) > 3 else f
    monkeypatch.setattr(R.os, "fdopen", fdopen)
    out = tmp_path / "S"
    rc = main(["synth", "sequence", "--out", str(out), "--frames", "3", "--width", "64", "--height", "48",
               "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1, err
    assert "No space left on device" in err[0] and str(out) in err[0] and ".tmp" not in err[0], err
    assert "incomplete marker" in err[0]
    assert (out / "incomplete.json").is_file() and not list(out.rglob("*.tmp"))


def test_show_gives_every_number_a_unit():
    from data_tools.results import metric_unit
    known = {"eval.ate": ["rmse", "pairs"], "eval.rpe": ["rmse", "rotation_rmse"],
             "eval.run": ["ate_rmse", "ape_rotation_rmse", "rpe_rmse", "rpe_rotation_max", "failed_frames"],
             "slam.run": ["frames", "frames_tracked", "frames_failed", "frames_relocalised", "frames_per_second"],
             "batch": ["seq/icp.ate_rmse_m", "seq/icp.frames_per_second", "seq/icp.frames_failed"],
             "lab.compare": ["gap", "frames", "spatial_term", "term.distance"],
             "lab.diagnose": ["gap", "candidates", "gain.shadow"], "lab.fit": ["gap_before", "gap", "evaluations"],
             "recog.eval": ["accuracy", "rot_err_deg_median", "trans_err_m_median"]}
    units = {(k, m): metric_unit(k, m) for k, ms in known.items() for m in ms}
    assert "?" not in units.values(), [k for k, u in units.items() if u == "?"]
    assert units[("eval.rpe", "rotation_rmse")] == "deg" and units[("eval.run", "ate_rmse")] == "m"
    assert units[("slam.run", "frames_per_second")] == "frames/s" and units[("lab.fit", "gap")] == "gap score"


def test_the_rules_are_documented():
    """docs/cli.md states each rule (``--max-frames``'s behaviour over every command: tests/test_max_frames.py)."""
    rules = (REPO / "docs" / "cli.md").read_text()
    for word in ("**`--json`**", "**`--max-frames N`**", "**`--spread-frames K`**",
                 "**Re-running onto an existing output: one rule.**", "exit code"):
        assert word in rules


def test_a_huge_sequence_is_refused_before_any_allocation(tmp_path, capsys):
    import time
    t0 = time.perf_counter()
    assert main(["synth", "sequence", "--out", str(tmp_path / "S"), "--frames", "100000000"]) == 1
    assert main(["synth", "sequence", "--out", str(tmp_path / "S"), "--frames", "900000", "--width", "4000",
                 "--height", "3000"]) == 1          # ~27 TB of images: more than any test disk has free
    err = capsys.readouterr().err.strip().splitlines()
    assert time.perf_counter() - t0 < 10 and not (tmp_path / "S").exists()
    assert "--frames 100000000" in err[0] and "at most" in err[0]
    assert "--frames 900000" in err[1] and "GB free" in err[1]
