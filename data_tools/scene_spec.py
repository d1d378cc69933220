"""``scene.json``: the reference geometry (meshes + materials) a sequence was captured in.

See ../shared/FORMATS.md. Mesh files are relative to the sequence folder and lie in the world
frame of groundtruth.txt, in metres.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from data_tools.errors import FormatError
from data_tools.mesh import TriMesh, load_mesh, save_mesh


@dataclass(frozen=True)
class Material:
    """Optical properties of a surface (shared by IR and the shaded RGB)."""

    albedo: float = 0.5
    """Diffuse reflectance in [0, 1]."""
    specular: float = 0.0
    """Weight of the mirror lobe in [0, 1] (shiny surfaces send the pattern away)."""
    extra: dict = field(default_factory=dict, compare=False)
    """Unknown keys found in the file, kept verbatim and ignored."""

    def to_json(self) -> dict:
        d = dict(self.extra)
        d.update({"albedo": self.albedo, "specular": self.specular})
        return d


DEFAULT_MATERIAL = Material()


@dataclass
class SceneSpec:
    """Content of scene.json plus the loaded meshes."""

    meshes: list[TriMesh]
    """Meshes in the world frame, metres; ``mesh.material`` keys into ``materials``."""
    materials: dict[str, Material]
    """Material table."""

    def material_of(self, mesh: TriMesh) -> Material:
        return self.materials.get(mesh.material, DEFAULT_MATERIAL)


def _material_from(d, path, name) -> Material:
    if not isinstance(d, dict):
        raise FormatError(path, f"material {name!r} must be an object")
    extra = {k: v for k, v in d.items() if k not in ("albedo", "specular")}
    try:
        albedo = float(d.get("albedo", DEFAULT_MATERIAL.albedo))
        spec = float(d.get("specular", DEFAULT_MATERIAL.specular))
    except (TypeError, ValueError):
        raise FormatError(path, f"material {name!r}: albedo/specular must be numbers") from None
    for k, v in (("albedo", albedo), ("specular", spec)):
        if not (math.isfinite(v) and 0.0 <= v <= 1.0):
            raise FormatError(path, f"material {name!r}: {k} must be in [0, 1], got {v}")
    return Material(albedo, spec, extra)


def read_scene_json(path: str | os.PathLike, validate_meshes: bool = True) -> SceneSpec:
    """Read scene.json and load its meshes (validated: non-empty, finite, edge-manifold)."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except json.JSONDecodeError as e:
        raise FormatError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(d, dict) or "meshes" not in d:
        raise FormatError(path, "scene.json needs a 'meshes' list")
    units = d.get("units", "m")
    scale = {"m": 1.0, "cm": 0.01, "mm": 0.001}.get(units)
    if scale is None:
        raise FormatError(path, f"units must be 'm', 'cm' or 'mm', got {units!r}")
    materials = {k: _material_from(v, path, k) for k, v in (d.get("materials") or {}).items()}
    if not isinstance(d["meshes"], list) or not d["meshes"]:
        raise FormatError(path, "scene.json 'meshes' must be a non-empty list")
    meshes = []
    for i, m in enumerate(d["meshes"]):
        if not isinstance(m, dict) or "file" not in m:
            raise FormatError(path, f"meshes[{i}] needs a 'file' key")
        mat = m.get("material", "default")
        if mat != "default" and mat not in materials:
            raise FormatError(path, f"meshes[{i}] uses material {mat!r} which is not in 'materials'")
        mpath = path.parent / m["file"]
        if not mpath.is_file():
            raise FormatError(path, f"meshes[{i}]: mesh file {m['file']!r} not found")
        mesh = load_mesh(mpath, scale, name=m.get("name", Path(m["file"]).stem), material=mat,
                         validate=validate_meshes)
        meshes.append(mesh)
    return SceneSpec(meshes, materials)


def write_scene_json(seq_dir: str | os.PathLike, scene: SceneSpec, mesh_dir: str = "meshes") -> Path:
    """Write every mesh as ``SEQ/meshes/NAME.ply`` and ``SEQ/scene.json``; returns its path."""
    seq_dir = Path(seq_dir)
    entries = []
    seen = set()
    for m in scene.meshes:
        if m.name in seen:
            raise FormatError(seq_dir / "scene.json", f"two meshes are named {m.name!r}")
        seen.add(m.name)
        rel = f"{mesh_dir}/{m.name}.ply"
        save_mesh(seq_dir / rel, m)
        entries.append({"file": rel, "name": m.name, "material": m.material})
    used = {m.material for m in scene.meshes}
    mats = {k: v.to_json() for k, v in scene.materials.items() if k in used}
    if "default" in used and "default" not in mats:
        mats["default"] = DEFAULT_MATERIAL.to_json()
    out = seq_dir / "scene.json"
    from data_tools.results import atomic_write_json
    atomic_write_json(out, {"units": "m", "meshes": entries, "materials": mats})
    return out
