"""Architecture rules of DEVELOPERS.md, checked on the source: dependency direction and lazy
plotting imports."""
from __future__ import annotations

import ast
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
