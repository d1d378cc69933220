"""Triangle meshes as plain arrays, with loading, saving and validation.

Meshes are kept as numpy arrays (not library objects) so every package can use them; the
conversion to Open3D/trimesh happens at the boundary.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError


@dataclass
class TriMesh:
    """An indexed triangle mesh."""

    vertices: np.ndarray
    """(V, 3) float64 vertex positions, metres."""
    triangles: np.ndarray
    """(F, 3) int32 vertex indices, counter-clockwise seen from outside."""
    name: str = "mesh"
    """Object name (unique within a scene; used for instance ids and file names)."""
    material: str = "default"
    """Key into the scene's material table."""
    vertex_colors: np.ndarray | None = None
    """Optional (V, 3) float in [0, 1], used for the shaded RGB."""

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32).reshape(-1, 3)

    def transformed(self, T: np.ndarray) -> "TriMesh":
        T = np.asarray(T, dtype=np.float64)
        return TriMesh(self.vertices @ T[:3, :3].T + T[:3, 3], self.triangles.copy(), self.name,
                       self.material, None if self.vertex_colors is None else self.vertex_colors.copy())

    def scaled(self, s: float) -> "TriMesh":
        return TriMesh(self.vertices * s, self.triangles.copy(), self.name, self.material,
                       None if self.vertex_colors is None else self.vertex_colors.copy())

    def canonical(self) -> "TriMesh":
        """The same surface with vertices in lexicographic (x, y, z) order and triangles sorted
        (each rotated to start at its smallest index, winding kept): meshes extracted by parallel
        code, whose order follows the thread schedule, become byte-identical files. Vertices at
        exactly the same position (Open3D's marching cubes emits some twice where blocks meet;
        their order would follow the schedule) are merged into one, with the smallest colour."""
        v = np.asarray(self.vertices)
        keys = [v[:, 2], v[:, 1], v[:, 0]]
        if self.vertex_colors is not None:
            c = np.asarray(self.vertex_colors)
            keys = [c[:, k] for k in range(c.shape[1] - 1, -1, -1)] + keys
        order = np.lexsort(keys)
        vs = v[order]
        first = np.ones(len(vs), bool)
        first[1:] = np.any(vs[1:] != vs[:-1], axis=1)
        rank = np.empty(len(order), np.int64)
        rank[order] = np.cumsum(first) - 1
        tri = rank[self.triangles].astype(np.int32)
        if len(tri):
            shift = np.argmin(tri, axis=1)
            tri = np.take_along_axis(tri, (shift[:, None] + np.arange(3)[None]) % 3, axis=1)
            tri = tri[np.lexsort(tri.T[::-1])]
        colors = None if self.vertex_colors is None else np.asarray(self.vertex_colors)[order][first]
        return TriMesh(vs[first], tri, self.name, self.material, colors)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned min/max corners, metres."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    def area(self) -> float:
        v = self.vertices[self.triangles]
        return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())

    def to_open3d(self):
        """Legacy ``open3d.geometry.TriangleMesh`` (imported lazily)."""
        import open3d as o3d
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                      o3d.utility.Vector3iVector(self.triangles))
        if self.vertex_colors is not None:
            m.vertex_colors = o3d.utility.Vector3dVector(np.asarray(self.vertex_colors, np.float64))
        return m


def check_mesh(mesh: TriMesh, path: str | os.PathLike | None = None) -> None:
    """Raise a FormatError for an empty, non-finite, out-of-range or non-manifold mesh.

    Non-manifold here means an edge shared by more than two triangles (edge-manifoldness):
    such meshes make inside/outside, normals and TSDF fusion ill-defined. Open boundaries
    (edges used once) are allowed: floors and walls are open surfaces.
    """
    where = path if path is not None else f"mesh {mesh.name!r}"
    if len(mesh.vertices) == 0 or len(mesh.triangles) == 0:
        raise FormatError(where, "mesh is empty (no triangles)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise FormatError(where, "mesh has NaN or infinite vertex coordinates")
    if mesh.triangles.min() < 0 or mesh.triangles.max() >= len(mesh.vertices):
        raise FormatError(where, "mesh has triangle indices out of range")
    tri = mesh.triangles
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    if len(edges):
        _, counts = np.unique(edges, axis=0, return_counts=True)
        n_bad = int((counts > 2).sum())
        if n_bad:
            raise FormatError(where, f"mesh is non-manifold ({n_bad} edges shared by more than two triangles)")


def load_mesh(path: str | os.PathLike, scale: float = 1.0, name: str | None = None,
              material: str = "default", validate: bool = True) -> TriMesh:
    """Load a PLY/OBJ/STL/OFF file as one TriMesh (multiple parts are concatenated).

    ``scale`` converts file units to metres (e.g. 0.001 for millimetre CAD models).
    """
    import trimesh
    path = Path(path)
    if path.is_dir():
        raise FormatError(path, "is a folder, expected a mesh file (.ply, .obj, .stl, .off)")
    if not path.is_file():
        raise FormatError(path, "mesh file not found")
    try:
        obj = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for corrupt files
        raise FormatError(path, f"cannot read mesh ({type(e).__name__}: {e})") from None
    if isinstance(obj, trimesh.Scene):  # force="mesh" on an empty scene
        obj = obj.to_geometry() if obj.geometry else trimesh.Trimesh()
    colors = None
    try:
        vc = getattr(obj.visual, "vertex_colors", None)
        if vc is not None and len(vc) == len(obj.vertices) and obj.visual.kind == "vertex":
            colors = np.asarray(vc)[:, :3] / 255.0
    except Exception:
        colors = None
    mesh = TriMesh(np.asarray(obj.vertices) * scale, np.asarray(obj.faces), name or path.stem,
                   material, colors)
    if validate:
        check_mesh(mesh, path)
    return mesh


def save_mesh(path: str | os.PathLike, mesh: TriMesh) -> None:
    """Write a mesh (binary PLY unless the suffix says otherwise)."""
    import trimesh
    colors = None if mesh.vertex_colors is None else (np.clip(mesh.vertex_colors, 0, 1) * 255).astype(np.uint8)
    tm = trimesh.Trimesh(mesh.vertices, mesh.triangles, vertex_colors=colors, process=False)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    tm.export(str(path))
