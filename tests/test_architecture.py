"""Architecture rules of DEVELOPERS.md, checked on the source: dependency direction and lazy
plotting imports."""
from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ["data_tools", "synth", "slam", "recog", "app"]
# what each package may import from the project (dependencies point one way)
ALLOWED = {
    "data_tools": {"data_tools"},
    "synth": {"data_tools", "synth"},
    "slam": {"data_tools", "slam"},
    "recog": {"data_tools", "synth", "recog"},
    "app": set(PACKAGES),
}
HEAVY_GUI = ("matplotlib", "pyvista")


def _imports(path: Path):
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node, a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node, node.module.split(".")[0]


@pytest.mark.parametrize("pkg", PACKAGES)
def test_dependencies_point_one_way(pkg):
    bad = []
    for f in sorted((REPO / pkg).rglob("*.py")):
        for node, top in _imports(f):
            if top in PACKAGES and top not in ALLOWED[pkg]:
                bad.append(f"{f.relative_to(REPO)}:{node.lineno} imports {top}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("pkg", ["data_tools", "synth", "slam", "recog"])
def test_no_plotting_import_at_module_level(pkg):
    """Library modules may import matplotlib/pyvista only inside functions."""
    bad = []
    for f in sorted((REPO / pkg).rglob("*.py")):
        tree = ast.parse(f.read_text(), str(f))
        for node in tree.body:  # module level only
            stmts = [node] + (list(ast.walk(node)) if isinstance(node, (ast.If, ast.Try)) else [])
            for s in stmts:
                names = []
                if isinstance(s, ast.Import):
                    names = [a.name for a in s.names]
                elif isinstance(s, ast.ImportFrom) and s.module:
                    names = [s.module]
                if any(n.split(".")[0] in HEAVY_GUI for n in names):
                    bad.append(f"{f.relative_to(REPO)}:{s.lineno}")
    assert not bad, "module-level plotting imports: " + ", ".join(bad)


def test_importing_every_library_module_loads_no_plotting():
    mods = []
    for pkg in ["data_tools", "synth", "slam", "recog"]:
        for f in sorted((REPO / pkg).rglob("*.py")):
            mods.append(".".join(f.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__"))
    code = ("import sys, importlib\n"
            f"for m in {mods!r}: importlib.import_module(m)\n"
            f"bad = [m for m in {HEAVY_GUI!r} if m in sys.modules]\n"
            "print(','.join(bad))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "", f"plotting libraries loaded at import: {r.stdout.strip()}"


# ------------------------------------------------------------------------------------------
# app/commands is thin: parse -> call one library function -> print
# ------------------------------------------------------------------------------------------

COMMAND_MAX_LINES = 40
"""Longest function allowed in app/commands (argparse declarations, ``register`` and ``_add_*``,
are exempt: they only declare options)."""
COMPUTATION_MODULES = {"numpy", "scipy", "cv2", "open3d", "trimesh", "torch", "numba", "PIL", "sklearn",
                       "skimage", "kornia", "matplotlib", "pyvista", "tqdm"}


def _command_files():
    return sorted((REPO / "app" / "commands").glob("*.py"))


def test_command_functions_are_short():
    long_ = []
    for f in _command_files():
        tree = ast.parse(f.read_text(), str(f))
        for node in ast.walk(tree):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if node.name == "register" or node.name.startswith(("_add", "add_")):
                continue
            n = node.end_lineno - node.lineno + 1
            if n > COMMAND_MAX_LINES:
                long_.append(f"{f.relative_to(REPO)}:{node.lineno} {node.name} ({n} lines)")
    assert not long_, "command functions must parse, call one library function and print:\n" + "\n".join(long_)


def test_commands_import_no_computation_library():
    bad = [f"{f.relative_to(REPO)}:{node.lineno} imports {top}"
           for f in _command_files() for node, top in _imports(f) if top in COMPUTATION_MODULES]
    assert not bad, "app/commands may import only the library entry points:\n" + "\n".join(bad)


def test_architecture_checks_catch_a_fat_command(tmp_path, monkeypatch):
    """The two checks above fail on a command that computes (so they can fail)."""
    fat = tmp_path / "app" / "commands"
    fat.mkdir(parents=True)
    (fat / "fat.py").write_text("import numpy as np\n\ndef _cmd(args):\n" + "    x = 1\n" * 45)
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    with pytest.raises(AssertionError, match="fat.py:3 _cmd"):
        test_command_functions_are_short()
    with pytest.raises(AssertionError, match="imports numpy"):
        test_commands_import_no_computation_library()


# ------------------------------------------------------------------------------------------
# heavy optional libraries stay where they belong; no import cycles
# ------------------------------------------------------------------------------------------

RESTRICTED = {"torch": ("recog", "slam/neural", "data_tools/training.py"), "pyvista": ("app",)}
"""Library -> the only folders (or files) that may import it. ``data_tools/training.py``: the training loop and
checkpoint file shared by the trainers of ``recog`` and ``slam/neural``, which may not import each other; it imports
torch inside its checkpoint methods only (importing data_tools does not load torch)."""


def test_torch_and_pyvista_only_where_they_belong():
    bad = []
    for pkg in PACKAGES:
        for f in sorted((REPO / pkg).rglob("*.py")):
            rel = f.relative_to(REPO).as_posix()
            for node, top in _imports(f):
                allowed = RESTRICTED.get(top)
                if allowed is not None and not any(rel == a or rel.startswith(a + "/") for a in allowed):
                    bad.append(f"{rel}:{node.lineno} imports {top} (allowed only under {', '.join(allowed)})")
    assert not bad, "\n".join(bad)


def _module_name(f: Path) -> str:
    return ".".join(f.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")


def _module_graph() -> dict[str, set[str]]:
    """Project module -> project modules it imports (anywhere in the file: a function-level
    import is a dependency too)."""
    mods = {_module_name(f): f for pkg in PACKAGES for f in (REPO / pkg).rglob("*.py")}
    graph = {}
    for m, f in mods.items():
        deps = set()
        tree = ast.parse(f.read_text(), str(f))
        pkg_parts = m.split(".") if f.name == "__init__.py" else m.split(".")[:-1]
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(pkg_parts[:len(pkg_parts) - node.level + 1] + ([base] if base else []))
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            for n in names:
                while n and n not in mods:
                    n = n.rpartition(".")[0]
                if n and n != m and not m.startswith(n + "."):  # a package's own __init__ is not a cycle
                    deps.add(n)
        graph[m] = deps
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_between_modules():
    cycles = _cycles(_module_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


# ------------------------------------------------------------------------------------------
# docs/architecture.md's "How the code is organised" matches the code
# ------------------------------------------------------------------------------------------

_PATH_TOKEN = re.compile(r"(?<![\w./-])([A-Za-z_][\w]*(?:\.py|/))(?=[\s,)]|$)")
DESCRIBED_AS_A_GROUP = {"synth/sensor/effects", "slam/backends", "app/commands"}
"""Folders docs/architecture.md describes as a whole ("one file per effect") instead of file by file."""


def readme_tree(text: str) -> set[str]:
    """Paths named in the code block of the "How the code is organised" section of
    docs/architecture.md (the README links to it): the
    first path on a line is placed by its indentation (2 spaces per level); the other paths on
    the line are inside it when it is a folder, else beside it; lines that start with prose
    continue the line before."""
    sec = text.split("## How the code is organised", 1)[1]
    block = sec.split("```", 2)[1]
    paths: set[str] = set()
    stack: list[str] = []  # folder at each depth
    context = None
    for line in block.splitlines():
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        m = _PATH_TOKEN.match(line.strip())
        tokens = _PATH_TOKEN.findall(line)
        if m and indent % 2 == 0 and indent // 2 <= len(stack):
            depth = indent // 2
            del stack[depth:]
            first = "/".join(stack + [m.group(1).rstrip("/")])
            paths.add(first)
            if m.group(1).endswith("/"):
                stack.append(m.group(1).rstrip("/"))
                context = first
            else:
                context = "/".join(stack)
            tokens = tokens[1:]
        for t in tokens:
            paths.add((context + "/" if context else "") + t.rstrip("/"))
    return paths


def test_readme_tree_parser_places_paths():
    text = ("## How the code is organised\n```\na/   x.py (one), sub/ two\n  y.py  b.py also z.py\n"
            "       prose continues w.py\n  c/   d.py\nb/\n```\n")
    assert readme_tree(text) == {"a", "a/x.py", "a/sub", "a/y.py", "a/b.py", "a/z.py", "a/w.py", "a/c",
                                 "a/c/d.py", "b"}


def test_readme_describes_every_package_and_module():
    named = readme_tree((REPO / "docs" / "architecture.md").read_text())
    missing_on_disk = sorted(p for p in named if not (REPO / p).exists())
    assert not missing_on_disk, f"docs/architecture.md names paths that do not exist: {missing_on_disk}"
    unnamed = []
    for pkg in ["app", "data_tools", "synth", "slam", "recog"]:
        for f in sorted((REPO / pkg).rglob("*.py")):
            rel = f.relative_to(REPO)
            folder = rel.parent.as_posix()
            if f.name == "__init__.py":
                if folder not in named:
                    unnamed.append(folder + "/")
                continue
            if f.name.startswith("_") or any(folder == g or folder.startswith(g + "/") for g in DESCRIBED_AS_A_GROUP):
                continue
            if rel.as_posix() not in named:
                unnamed.append(rel.as_posix())
    assert not unnamed, f"docs/architecture.md's 'How the code is organised' does not name: {unnamed}"


MAX_MODULE_LINES = 700
"""A library module longer than this usually holds two ideas (split it: see docs/architecture.md)."""


def test_library_modules_hold_one_idea_each():
    long = []
    for pkg in ["app", "data_tools", "synth", "slam", "recog"]:
        for f in sorted((REPO / pkg).rglob("*.py")):
            n = len(f.read_text().splitlines())
            if n > MAX_MODULE_LINES:
                long.append(f"{f.relative_to(REPO)} ({n} lines)")
    assert not long, f"modules longer than {MAX_MODULE_LINES} lines: {long}"


def test_progress_goes_through_one_module():
    """tqdm redraws with carriage returns, which fill log files: every long job uses
    data_tools.progress (a bar on a terminal, whole lines otherwise)."""
    bad = []
    for pkg in ["app", "data_tools", "synth", "slam", "recog"]:
        for f in sorted((REPO / pkg).rglob("*.py")):
            if f.relative_to(REPO).as_posix() == "data_tools/progress.py":
                continue
            for node in ast.walk(ast.parse(f.read_text(), str(f))):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else []
                if any(n.split(".")[0] == "tqdm" for n in names):
                    bad.append(f"{f.relative_to(REPO)}:{node.lineno}")
    assert not bad, f"tqdm imported outside data_tools/progress.py: {bad}"
