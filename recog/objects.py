"""Recognition objects: CAD models with their name, materials, size and symmetry.

An object is one or more triangle meshes in the model's own frame (metres) with a material
per mesh. Its *name* is the class label (the model file's stem: ``obj_05``; for the embedded
chairs ``chair_a``, ``chair_b``, ``chair_c``). Poses are object-to-camera 4x4 matrices in
that frame (OpenCV camera axes), as in ``labels.json``.

Units: a model file is read in metres unless it is more than 10 units across, which no
recognition object is in metres but every millimetre CAD model (T-LESS: 35-95 mm objects) is;
then it is scaled by 0.001 (:func:`guess_scale`, reported in the object's ``scale``). An
explicit scale overrides the guess.

    objs = load_objects("../shared/data/tless_cad/obj_01.ply,../shared/data/tless_cad/obj_02.ply")
    objs = load_objects("chairs")          # the three embedded office chairs
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError
from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material

__all__ = ["RecogObject", "load_objects", "guess_scale", "EMBEDDED_SETS", "MESH_SUFFIXES"]

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off")
EMBEDDED_SETS = ("chairs",)
"""Object sets that need no file: ``chairs`` = the three near-identical procedural office chairs
of the thesis' experiment (synth.scenes.builtin.CHAIR_VARIANTS)."""

MM_THRESHOLD = 10.0
"""A model more than this many file units across is read as millimetres (see the module docstring)."""


@dataclass
class RecogObject:
    """One class of the recogniser: its meshes (object frame, metres) and provenance."""

    name: str
    """Class label (file stem, or the embedded object's name)."""
    meshes: list[TriMesh]
    """The object's meshes in its own frame, metres; ``mesh.material`` keys :attr:`materials`."""
    materials: dict[str, Material]
    """Material of each mesh."""
    source: str = ""
    """The model file, or ``embedded:<set>``."""
    scale: float = 1.0
    """File units -> metres factor applied when loading."""
    symmetry: dict = field(default_factory=dict)
    """Symmetry of the shape (:mod:`recog.symmetry`: ``{"axis": [x, y, z] or None, "order": n}``),
    filled by :func:`recog.symmetry.detect_symmetry` or declared."""

    @property
    def vertices(self) -> np.ndarray:
        """(N, 3) all vertices, metres."""
        return np.concatenate([m.vertices for m in self.meshes])

    @property
    def bounds(self) -> np.ndarray:
        v = self.vertices
        return np.stack([v.min(0), v.max(0)])

    @property
    def diameter_m(self) -> float:
        """Bounding-box diagonal, metres."""
        lo, hi = self.bounds
        return float(np.linalg.norm(hi - lo))

    def merged(self) -> TriMesh:
        """All meshes as one (for sampling and ICP)."""
        v, t, off = [], [], 0
        for m in self.meshes:
            v.append(m.vertices)
            t.append(m.triangles + off)
            off += len(m.vertices)
        return TriMesh(np.concatenate(v), np.concatenate(t), self.name, self.meshes[0].material)

    def to_json(self) -> dict:
        return {"name": self.name, "source": self.source, "scale": self.scale, "symmetry": self.symmetry,
                "diameter_m": self.diameter_m}


def guess_scale(extent: float) -> float:
    """File units -> metres for a model ``extent`` units across: 0.001 above
    :data:`MM_THRESHOLD` (millimetres), else 1."""
    return 0.001 if extent > MM_THRESHOLD else 1.0


def _load_file(path: Path, scale: float | None) -> RecogObject:
    from data_tools.mesh import check_mesh, load_mesh
    raw = load_mesh(path, 1.0, validate=False)
    if len(raw.triangles) == 0:
        raise FormatError(path, "the mesh is empty (no triangles)")
    extent = float(np.linalg.norm(raw.bounds[1] - raw.bounds[0]))
    s = guess_scale(extent) if scale is None else float(scale)
    mesh = raw.scaled(s)
    mesh.name, mesh.material = path.stem, "object"
    check_mesh(mesh, path)
    from synth.sensor.views import check_model_size
    check_model_size(mesh, path, s)
    return RecogObject(path.stem, [mesh], {"object": Material(0.6, 0.05)}, str(path.resolve()), s)


def _chairs() -> list[RecogObject]:
    from synth.scenes.builtin import CHAIR_VARIANTS, MATERIALS, chair_meshes
    out = []
    for name in CHAIR_VARIANTS:
        meshes = chair_meshes(name, name=name)
        mats = {m.material: MATERIALS[m.material] for m in meshes}
        out.append(RecogObject(name, meshes, mats, "embedded:chairs", 1.0))
    return out


def load_objects(spec: str | os.PathLike | list, scale: float | None = None) -> list[RecogObject]:
    """Objects of ``spec``: a folder (every .ply/.obj/.stl/.off in it, sorted), a comma list of
    model files, a list of paths, or ``chairs`` (embedded). ``scale`` None = guess the units."""
    if isinstance(spec, (list, tuple)):
        items = [str(s) for s in spec]
    else:
        items = [s.strip() for s in str(spec).split(",") if s.strip()]
    if not items:
        raise ConfigError("--objects: give a folder, a comma list of model files, or 'chairs'")
    objs: list[RecogObject] = []
    for it in items:
        if it in EMBEDDED_SETS:
            objs += _chairs()
            continue
        p = Path(it)
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in MESH_SUFFIXES)
            if not files:
                raise FormatError(p, f"no model files ({', '.join(MESH_SUFFIXES)}) in this folder")
            objs += [_load_file(f, scale) for f in files]
        elif p.is_file():
            if p.suffix.lower() not in MESH_SUFFIXES:
                raise FormatError(p, f"not a model file (expected {', '.join(MESH_SUFFIXES)})")
            objs.append(_load_file(p, scale))
        else:
            raise FormatError(p, "model file or folder not found (or use the embedded set 'chairs')")
    names = [o.name for o in objs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"--objects: two models share the name {dup[0]!r} (names are the file stems)")
    return objs
