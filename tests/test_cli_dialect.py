"""One dialect: the argparse tree is walked and the shared flags are checked in every command.

The same idea has the same flag everywhere (``--out``, ``--overwrite``, ``--max-frames``,
``--seed``, ``--workers``, ``--no-progress``, ``--json``) with the standard help text of
:data:`app.commands.SHARED_FLAGS`; no command uses another name for them; every command that
shows progress can switch it off; errors about a value name the flag.
"""
from __future__ import annotations

import argparse

import pytest

from app.cli import build_parser, main
from app.commands import FORBIDDEN_SYNONYMS, SHARED_FLAGS

LONG_COMMANDS = ("sensor simulate", "sensor compare", "sensor diagnose", "sensor fit", "slam run", "batch",
                 "data make-reference", "data convert-7scenes", "data info", "synth sequence", "synth views", "demo")
"""Commands with a progress display: each has --no-progress."""
WRITERS_WITHOUT_OVERWRITE = ()
"""Commands with --out and no --overwrite: none (the one re-run rule, tests/test_rerun.py)."""


def leaf_parsers() -> dict[str, argparse.ArgumentParser]:
    """'group sub' -> parser of every command of the CLI."""
    out = {}

    def walk(p, path):
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            out[" ".join(path)] = p
        for a in subs:
            for name, sp in a.choices.items():
                walk(sp, path + [name])
    walk(build_parser(), [])
    return out


def options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in p._actions for s in a.option_strings}


def test_every_command_is_walked():
    cmds = leaf_parsers()
    assert {"sensor fit", "slam run", "eval ate", "data info", "synth views", "show", "batch"} <= set(cmds)
    assert len(cmds) >= 18


def test_shared_flags_have_the_standard_name_and_help():
    for cmd, p in leaf_parsers().items():
        for flag, action in options(p).items():
            if flag in SHARED_FLAGS:
                assert action.help.startswith(SHARED_FLAGS[flag].replace("%", "%%")), (cmd, flag, action.help)
            assert flag not in FORBIDDEN_SYNONYMS, (cmd, flag)


def test_frames_only_means_frames_to_generate():
    """``--frames`` is the length of a generated sequence; a limit on frames read is --max-frames."""
    for cmd, p in leaf_parsers().items():
        opts = options(p)
        if "--frames" in opts:
            assert "generate" in opts["--frames"].help, (cmd, opts["--frames"].help)
            assert "--max-frames" not in opts, cmd


def test_long_commands_can_switch_progress_off():
    cmds = leaf_parsers()
    for cmd in LONG_COMMANDS:
        assert "--no-progress" in options(cmds[cmd]), cmd


def test_every_writer_has_overwrite():
    for cmd, p in leaf_parsers().items():
        opts = options(p)
        if "--out" in opts and cmd not in WRITERS_WITHOUT_OVERWRITE:
            assert "--overwrite" in opts, cmd


def test_json_is_a_flag_that_prints():
    """``--json`` is a switch that prints JSON on stdout on every command (files are written by --out)."""
    for cmd, p in leaf_parsers().items():
        opts = options(p)
        if "--json" in opts:
            assert opts["--json"].nargs == 0, cmd  # a switch, never a file name


@pytest.mark.parametrize("argv, flag", [
    (["sensor", "fit", "S", "--effects", "axial_noise", "--out", "m.json", "--max-frames", "0"], "--max-frames"),
    (["data", "make-reference", "S", "--max-frames", "-1"], "--max-frames"),
    (["synth", "sequence", "--out", "o", "--workers", "0"], "--workers"),
    (["sensor", "compare", "S", "--effects", "none", "--out", "o", "--seed", "x"], "--seed"),
])
def test_usage_errors_are_one_line_exit_1_naming_the_flag(argv, flag, capsys):
    """Range and type errors argparse finds are one line and exit 1, like every realgap error."""
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert flag in err and "\n" not in err and err.startswith("realgap: error:"), err


@pytest.mark.parametrize("argv, words", [
    (["slam", "run", "S", "--out", "R", "--max-frames", "0"], ["--max-frames", "must be >= 1, got 0"]),
    (["slam", "run", "S", "--out", "R", "--tsdf.voxel-size-m", "-1"], ["--tsdf.voxel-size-m", "> 0"]),
    (["slam", "run", "S", "--out", "R", "--icp.iterations", "x"], ["--icp.iterations", "integer"]),
    (["slam", "run", "S", "--out", "R", "--frame-step", "0"], ["--frame-step"]),
])
def test_config_errors_name_the_flag_not_the_field(argv, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "S").mkdir()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Config." not in err and "config." not in err, err
    for w in words:
        assert w in err, (w, err)
    assert not (tmp_path / "R").exists()


def test_align_is_one_option_with_one_meaning():
    """``--align`` of eval, batch and demo: the same choices and help text (issue 44 item 3); the default
    of every command that scores absolute errors is auto (eval rpe keeps evo's none)."""
    from slam.metrics import ALIGN_HELP, ALIGNERS, PRESETS
    cmds = leaf_parsers()
    found = {}
    for cmd in ("eval ate", "eval rpe", "eval run", "batch", "demo"):
        a = options(cmds[cmd])["--align"]
        assert list(a.choices) == list(ALIGNERS) and a.help.startswith(ALIGN_HELP), (cmd, a.help)
        found[cmd] = a.default
    assert found["batch"] == "auto" and PRESETS["tum"].align == "auto" and "default: auto" in options(
        cmds["demo"])["--align"].help
    from app.commands.demo import demo_config
    args = build_parser().parse_args(["demo", "--align", "origin"])
    assert demo_config(args).align == "origin"
