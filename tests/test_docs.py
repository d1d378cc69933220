"""The user documentation stays short, linked and runnable: README.md within its line budget, every
relative link in README.md, docs/*.md and the model cards pointing at a file that exists, every
``realgap ...`` line of the README's code blocks accepted by the CLI's own argument parser, and the
cheap ones (no data, no output folder) run to exit code 0."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from app.cli import UsageError, build_parser, main

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
README_MAX_LINES = 300
"""The README says what realgap is and what to run first; deep dives live in docs/."""

DOC_FILES = [README, *sorted((REPO / "docs").glob("*.md")),
             *sorted((REPO / "slam" / "neural" / "weights").glob("*/MODEL_CARD.md")),
             REPO / "slam" / "neural" / "weights" / "README.md"]

_LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")
_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.M | re.S)

CHEAP_COMMANDS = [["--help"], ["synth", "scenes"], ["sensor", "effects"], ["sensor", "presets", "kinect_v1"]]
"""README commands that need no data and write nothing: they are run, not only parsed."""


def links(text: str) -> list[str]:
    """Targets of the markdown links and images in ``text``, code blocks and code spans left out."""
    text = _FENCE.sub("", text)
    text = re.sub(r"`[^`\n]*`", "", text)
    return [a or b for a, b in _LINK.findall(text)]


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def readme_commands(text: str) -> list[list[str]]:
    """The ``realgap`` command lines of ``text``'s fenced code blocks as argv lists (without the
    leading ``realgap``): backslash continuations joined, ``#`` comments dropped."""
    commands = []
    for block in _FENCE.findall(text):
        joined = re.sub(r"\\\n\s*", " ", block)
        for line in joined.splitlines():
            if line.strip().startswith("realgap "):
                commands.append(shlex.split(line, comments=True)[1:])
    return commands


def test_helpers_on_hand_made_text():
    text = ("see [a](docs/a.md) and ![pic](docs/p.png), [web](https://x.org), [top](#two-words)\n"
            "`[not](a link)`\n```bash\nrealgap x --a 1 \\\n   --b \"q r\"   # c [no](link)\nmake demo\n```\n")
    assert links(text) == ["docs/a.md", "docs/p.png", "https://x.org", "#two-words"]
    assert readme_commands(text) == [["x", "--a", "1", "--b", "q r"]]
    assert anchor("Two words!") == "two-words"


def test_readme_is_short():
    n = len(README.read_text().splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines (at most {README_MAX_LINES}): move detail to docs/"


@pytest.mark.parametrize("doc", DOC_FILES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_resolves(doc):
    assert doc.exists(), doc
    text = doc.read_text()
    headings = {anchor(h) for h in re.findall(r"^#+ (.*)$", _FENCE.sub("", text), re.M)}
    broken = []
    for target in links(text):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto: not checked offline
        path, _, frag = target.partition("#")
        if not path:
            if frag not in headings:
                broken.append(target)
        elif not (doc.parent / path).exists():
            broken.append(target)
    assert not broken, f"{doc.relative_to(REPO)}: links to nothing: {broken}"


def test_readme_commands_parse(capsys):
    commands = [c for c in readme_commands(README.read_text()) if "--help" not in c]  # --help: run below
    assert len(commands) >= 20, "the README's tour lost its commands"
    _assert_parse(commands, "README")


@pytest.mark.parametrize("doc", [d for d in DOC_FILES if d != README], ids=lambda p: p.relative_to(REPO).as_posix())
def test_docs_commands_parse(doc, capsys):
    """The command lines of the docs pages and model cards too (placeholders like SEQ parse as paths)."""
    _assert_parse([c for c in readme_commands(doc.read_text()) if "--help" not in c], doc.name)


def _assert_parse(commands, where):
    parser = build_parser()
    bad = []
    for argv in commands:
        try:
            args = parser.parse_args(argv)
        except (SystemExit, UsageError):
            bad.append(" ".join(argv))
            continue
        if getattr(args, "func", None) is None:
            bad.append(" ".join(argv) + "  (no subcommand)")
    assert not bad, f"{where}: command lines the CLI rejects:\n" + "\n".join(bad)


def test_parse_check_rejects_a_wrong_line():
    with pytest.raises(UsageError):
        build_parser().parse_args(["slam", "run", "x", "--out", "y", "--no-such-flag"])


@pytest.mark.parametrize("argv", CHEAP_COMMANDS, ids=" ".join)
def test_cheap_readme_commands_run(argv, capsys):
    assert argv in readme_commands(README.read_text()), f"realgap {' '.join(argv)} is not in the README"
    try:
        rc = main(argv)
    except SystemExit as e:  # --help exits through argparse
        rc = e.code
    assert rc == 0
    assert capsys.readouterr().out.strip()
