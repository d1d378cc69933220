"""Loaders for external scene data: SceneNet v1.0 rooms (OBJ + pose file) and T-LESS CAD models.

SceneNet v1.0 (``room_89_simple.obj`` and ``trajectory_random_poses_SE3_3x4.txt``)
------------------------------------------------------------------------------------
* Units are metres. The world is **y-up** (floor at y = -0.105, ceiling at y = 2.79,
  chairs and tables stand on the floor and extend towards +y). We convert it to realgap's
  z-up world with the rotation :data:`SCENENET_TO_WORLD` = R_x(+90 deg):
  (x, y, z)_scenenet -> (x, -z, y)_realgap. No translation: the floor stays at z = -0.105.
* The OBJ holds named objects (``o NAME``), one ``usemtl`` each, but the shared copy has
  no MTL file (its ``mtllib`` line is commented out). :func:`load_scenenet_room` reads an MTL
  when there is one (``Kd`` -> albedo as Rec.709 luminance, ``Ks``/``Ns`` -> specular) and
  otherwise derives materials from object-name keywords (:data:`SCENENET_NAME_MATERIALS`).
  Objects without faces (``floor_enclose``, ``ceiling`` in room 89) are skipped.
* The pose file holds 3x4 matrices [R | t] (3 rows each, blank line between poses; 500 in
  room 89). They are **camera-to-world** T_wc: t is the camera centre (1.65-1.85 m above
  the floor, inside the room; read as world-to-camera the centres would lie below the floor).
  SceneNet v1.0's renderer (``main_depth_and_labels.cpp``) inverts T_wc into the OpenGL
  model-view matrix and uses Pangolin's ``ProjectionMatrixRDF_BottomLeft``, i.e. the camera
  looks along **+z** of T_wc. In the file, however, the camera's y column points to world
  *up* (y component 0.52..1.0, x column always horizontal), so in an x-right / y-down camera
  the view would be upside down (SceneNet flips its images when saving them). We keep the
  viewing direction and position and rotate the camera frame by 180 deg about its optical
  axis to get an upright OpenCV camera: T_realgap = SCENENET_TO_WORLD @ T_wc @
  diag(-1, -1, 1, 1). (Our images are therefore the physically correct, upright views; the
  images SceneNet itself rendered are vertically flipped versions of them.)

T-LESS
------
CAD models are binary PLY in millimetres with the object centred at the origin;
:func:`load_tless_model` scales them to metres. Two of the 30 models (obj_07, obj_11) are not
edge-manifold (obj_07 has 4 back-to-back duplicate triangles, obj_11 thin fins touching
along edges); :func:`repair_nonmanifold` fixes such meshes without moving any vertex.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError
from data_tools.mesh import TriMesh, check_mesh, load_mesh
from data_tools.scene_spec import DEFAULT_MATERIAL, Material, SceneSpec
from data_tools.trajectory import Trajectory
from synth.scenes.builtin import _ground, pose_matrix
from synth.scenes.registry import register_scene

SCENENET_TO_WORLD = np.array([[1.0, 0.0, 0.0, 0.0],
                              [0.0, 0.0, -1.0, 0.0],
                              [0.0, 1.0, 0.0, 0.0],
                              [0.0, 0.0, 0.0, 1.0]])
"""Rotation R_x(+90 deg) taking SceneNet's y-up world to realgap's z-up world."""

SCENENET_CAM_TO_OPENCV = np.diag([-1.0, -1.0, 1.0, 1.0])
"""Right-multiplied on a SceneNet T_wc: 180 deg about the optical axis (see module docstring)."""

SCENENET_NAME_MATERIALS: list[tuple[str, str, Material, tuple[float, float, float]]] = [
    ("painting", "scenenet_painting", Material(0.50, 0.20), (0.55, 0.45, 0.35)),
    ("chair", "scenenet_chair", Material(0.30, 0.05), (0.40, 0.28, 0.20)),
    ("table", "scenenet_table", Material(0.45, 0.10), (0.62, 0.46, 0.30)),
    ("floor", "scenenet_floor", Material(0.45, 0.10), (0.55, 0.40, 0.26)),
    ("ceiling", "scenenet_ceiling", Material(0.85, 0.00), (0.92, 0.92, 0.90)),
    ("skeleton", "scenenet_wall", Material(0.80, 0.00), (0.88, 0.87, 0.83)),
    ("wall", "scenenet_wall", Material(0.80, 0.00), (0.88, 0.87, 0.83)),
]
"""Fallback materials when no MTL is available: (lower-case name keyword, material key,
material, RGB colour); the first keyword found in the object name wins. Plausible values for
the named surfaces, not measurements."""

TLESS_MATERIAL = Material(0.60, 0.15)
"""T-LESS objects are texture-less light-grey/white industrial plastic."""


# --------------------------------------------------------------------------- OBJ / MTL parsing

def _parse_obj(path: Path) -> tuple[np.ndarray, list[tuple[str, str | None, np.ndarray]], list[str]]:
    """Minimal OBJ reader: (vertices (V, 3), [(object name, usemtl, faces (F, 3) global 0-based)],
    mtllib names). Polygons are fan-triangulated; ``o`` (or ``g`` when a file has no ``o``)
    starts an object; vt/vn are ignored."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except UnicodeDecodeError:
        raise FormatError(path, "not a text OBJ file") from None
    has_o = any(line.startswith("o ") for line in text.splitlines())
    verts: list[list[float]] = []
    objects: list[list] = []
    mtllibs: list[str] = []
    cur = None
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.split()
        if not s or s[0].startswith("#"):
            continue
        key = s[0]
        if key == "v":
            try:
                verts.append([float(x) for x in s[1:4]])
            except ValueError:
                raise FormatError(path, f"line {lineno}: bad vertex {line.strip()!r}") from None
            if len(verts[-1]) != 3:
                raise FormatError(path, f"line {lineno}: a vertex needs 3 coordinates")
        elif key == "o" or (key == "g" and not has_o):
            cur = [" ".join(s[1:]) or f"object_{len(objects)}", None, []]
            objects.append(cur)
        elif key == "usemtl":
            if cur is None:
                cur = ["object_0", None, []]
                objects.append(cur)
            cur[1] = " ".join(s[1:])
        elif key == "mtllib":
            mtllibs.extend(s[1:])
        elif key == "f":
            if cur is None:
                cur = [path.stem, None, []]
                objects.append(cur)
            try:
                idx = [int(tok.split("/")[0]) for tok in s[1:]]
            except ValueError:
                raise FormatError(path, f"line {lineno}: bad face {line.strip()!r}") from None
            if len(idx) < 3:
                raise FormatError(path, f"line {lineno}: a face needs at least 3 vertices")
            n = len(verts)
            idx = [i - 1 if i > 0 else n + i for i in idx]
            if min(idx) < 0 or max(idx) >= n:
                raise FormatError(path, f"line {lineno}: face refers to a vertex that does not exist")
            for k in range(1, len(idx) - 1):
                cur[2].append((idx[0], idx[k], idx[k + 1]))
    V = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    out = [(name, mtl, np.asarray(F, dtype=np.int64).reshape(-1, 3)) for name, mtl, F in objects]
    return V, out, mtllibs


def _parse_mtl(path: Path) -> dict[str, dict[str, list[float]]]:
    """{material name: {"Kd": [r, g, b], "Ks": [...], "Ns": [x], ...}} from an MTL file."""
    mats: dict[str, dict[str, list[float]]] = {}
    cur = None
    for line in path.read_text(errors="replace").splitlines():
        s = line.split()
        if not s or s[0].startswith("#"):
            continue
        if s[0] == "newmtl":
            cur = mats.setdefault(" ".join(s[1:]), {})
        elif cur is not None and s[0] in ("Kd", "Ks", "Ns", "Ka", "d"):
            try:
                cur[s[0]] = [float(x) for x in s[1:]]
            except ValueError:
                raise FormatError(path, f"bad value in {line.strip()!r}") from None
    return mats


def _rgb3(v: list[float]) -> list[float]:
    """An MTL colour as 3 numbers (a single number means grey)."""
    return list(v[:3]) if len(v) >= 3 else [v[0]] * 3


def _luminance(rgb: list[float]) -> float:
    r, g, b = _rgb3(rgb)
    return 0.2126 * r + 0.7152 * g + 0.0722 * b


def material_from_mtl(entry: dict[str, list[float]]) -> tuple[Material, tuple[float, float, float]]:
    """(Material, RGB colour) from one MTL entry.

    albedo = Rec.709 luminance of ``Kd``; specular = luminance of ``Ks`` times
    min(1, ``Ns`` / 200): the MTL's specular colour is the strength of the highlight and
    ``Ns`` its sharpness, so only sharp, strong highlights count as a mirror lobe (an
    approximation: MTL's Phong model has no exact counterpart in our two-number material).
    """
    kd = entry.get("Kd", [DEFAULT_MATERIAL.albedo] * 3)
    ks = entry.get("Ks", [0.0, 0.0, 0.0])
    ns = entry.get("Ns", [0.0])[0]
    albedo = float(np.clip(_luminance(kd), 0.0, 1.0))
    spec = float(np.clip(_luminance(ks) * min(1.0, max(ns, 0.0) / 200.0), 0.0, 1.0))
    color = tuple(float(np.clip(c, 0.0, 1.0)) for c in _rgb3(kd))
    return Material(albedo, spec), color


def _material_by_name(name: str) -> tuple[str, Material, tuple[float, float, float]]:
    low = name.lower()
    for key, mkey, mat, color in SCENENET_NAME_MATERIALS:
        if key in low:
            return mkey, mat, color
    return "default", DEFAULT_MATERIAL, (0.5, 0.5, 0.5)


# --------------------------------------------------------------------------- mesh repair

def repair_nonmanifold(mesh: TriMesh) -> tuple[TriMesh, dict[str, int]]:
    """Make a mesh edge-manifold without moving any vertex; returns (mesh, counts of fixes).

    1. Exact duplicate triangles (same three vertices) are reduced: pairs with opposite
       winding (a zero-thickness double wall) are removed, same-winding copies are dropped.
    2. Edges still shared by more than two triangles are split: every triangle on such an
       edge beyond the first two gets its own copies of the edge's two vertices (same
       positions), leaving a zero-width seam. The surface looks the same to a ray caster.
    """
    F = mesh.triangles.astype(np.int64)
    V = mesh.vertices
    C = mesh.vertex_colors
    n_dup = 0
    key = np.sort(F, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    keep = np.ones(len(F), bool)
    if np.any(counts > 1):
        for g in np.flatnonzero(counts > 1):
            members = np.flatnonzero(inv == g)
            # orientation parity: a triangle and its reverse have different cyclic orders
            rolled = [tuple(np.roll(F[i], -int(np.argmin(F[i])))) for i in members]
            pos = [i for i, r in zip(members, rolled) if r == rolled[0]]
            neg = [i for i, r in zip(members, rolled) if r != rolled[0]]
            n_pairs = min(len(pos), len(neg))
            drop = pos[:n_pairs] + neg[:n_pairs]
            rest = pos[n_pairs:] + neg[n_pairs:]
            drop += rest[1:]  # same-winding copies: keep one
            keep[drop] = False
            n_dup += len(drop)
    F = F[keep]
    n_split = 0
    edges = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    ekey = np.sort(edges, axis=1)
    uniq, einv, ecount = np.unique(ekey, axis=0, return_inverse=True, return_counts=True)
    einv = einv.reshape(-1)
    bad = np.flatnonzero(ecount > 2)
    if len(bad):
        newV = [V]
        newC = [C] if C is not None else None
        nV = len(V)
        F = F.copy()
        fi_of_edge = np.arange(len(edges)) % len(F)
        for b in bad:
            faces = fi_of_edge[einv == b]
            a, c = uniq[b]
            for fi in faces[2:]:
                for old in (a, c):
                    pos = np.flatnonzero(F[fi] == old)
                    F[fi, pos] = nV
                    newV.append(V[old][None])
                    if newC is not None:
                        newC.append(C[old][None])
                    nV += 1
                n_split += 1
        V = np.concatenate(newV)
        C = np.concatenate(newC) if newC is not None else None
    out = TriMesh(V, F, mesh.name, mesh.material, C)
    return out, {"duplicate_triangles_removed": n_dup, "triangles_split_off": n_split}


# --------------------------------------------------------------------------- SceneNet

def load_scenenet_room(obj_path: str | os.PathLike, mtl_path: str | os.PathLike | None = None,
                       repair: bool = True) -> SceneSpec:
    """A SceneNet v1.0 room OBJ as a SceneSpec in realgap's z-up world (module docstring).

    One mesh per named OBJ object (empty objects skipped; duplicate names get ``_2``,
    ``_3``...). Materials come from ``mtl_path``, else from the OBJ's ``mtllib`` or a
    same-named ``.mtl`` next to it when present, else from :data:`SCENENET_NAME_MATERIALS`.
    Non-manifold objects are repaired with :func:`repair_nonmanifold` (``repair=False``
    raises a FormatError instead).
    """
    path = Path(obj_path)
    V, objects, mtllibs = _parse_obj(path)
    if not objects or all(len(F) == 0 for _, _, F in objects):
        raise FormatError(path, "OBJ has no faces")
    mtl_file = None
    if mtl_path is not None:
        mtl_file = Path(mtl_path)
        if not mtl_file.is_file():
            raise FormatError(mtl_file, "MTL file not found")
    else:
        for cand in [path.parent / m for m in mtllibs] + [path.with_suffix(".mtl")]:
            if cand.is_file():
                mtl_file = cand
                break
    mtl = _parse_mtl(mtl_file) if mtl_file is not None else {}
    R = SCENENET_TO_WORLD[:3, :3]
    meshes: list[TriMesh] = []
    materials: dict[str, Material] = {}
    used_names: dict[str, int] = {}
    for name, usemtl, F in objects:
        if len(F) == 0:
            continue
        if usemtl is not None and usemtl in mtl:
            mat, color = material_from_mtl(mtl[usemtl])
            mkey = usemtl
        else:
            mkey, mat, color = _material_by_name(name)
        materials[mkey] = mat
        u, local = np.unique(F, return_inverse=True)
        safe = "".join(ch if ch.isalnum() or ch in "._-" else "_" for ch in name)
        used_names[safe] = used_names.get(safe, 0) + 1
        if used_names[safe] > 1:
            safe = f"{safe}_{used_names[safe]}"
        verts = V[u] @ R.T
        mesh = TriMesh(verts, local.reshape(-1, 3), safe, mkey, np.tile(np.asarray(color), (len(u), 1)))
        try:
            check_mesh(mesh, path)
        except FormatError as e:
            if not repair:
                raise FormatError(path, f"object {name!r}: {e.problem}") from None
            mesh, _ = repair_nonmanifold(mesh)
            check_mesh(mesh, path)
        meshes.append(mesh)
    return SceneSpec(meshes, materials)


def load_scenenet_trajectory(path: str | os.PathLike, fps: float = 30.0, t0: float = 0.0) -> Trajectory:
    """SceneNet's ``*_SE3_3x4.txt`` as a realgap Trajectory (camera-to-world, OpenCV axes,
    z-up world; see the module docstring). Timestamps are ``t0 + i / fps`` seconds (the file
    has none). Rotations are re-orthonormalised (the file holds 6 significant digits)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    try:
        vals = np.array([float(x) for x in text.split()], dtype=np.float64)
    except ValueError:
        raise FormatError(path, "pose file holds something that is not a number") from None
    if len(vals) == 0 or len(vals) % 12:
        raise FormatError(path, f"expected 3x4 matrices (12 numbers each), got {len(vals)} numbers")
    if not np.all(np.isfinite(vals)):
        raise FormatError(path, "pose file holds NaN or infinite values")
    if not fps > 0:
        raise FormatError(path, f"fps must be positive, got {fps}")
    M = vals.reshape(-1, 3, 4)
    R = M[:, :, :3]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((err > 1e-3) | (det < 0))
    if len(bad):
        raise FormatError(path, f"pose {bad[0] + 1} is not a rotation (|R R^T - I| = {err[bad[0]]:.2g}, "
                                f"det = {det[bad[0]]:.3f})")
    U, _, Vt = np.linalg.svd(R)
    T = np.zeros((len(M), 4, 4))
    T[:, :3, :3] = U @ Vt
    T[:, :3, 3] = M[:, :, 3]
    T[:, 3, 3] = 1.0
    T = SCENENET_TO_WORLD @ T @ SCENENET_CAM_TO_OPENCV
    return Trajectory(t0 + np.arange(len(T)) / float(fps), T)


# --------------------------------------------------------------------------- T-LESS

def load_tless_model(ply_path: str | os.PathLike, name: str | None = None,
                     material: str = "tless_plastic", repair: bool = True) -> TriMesh:
    """A T-LESS CAD model (PLY, millimetres) as a TriMesh in metres, object frame unchanged.

    Non-manifold models are repaired (:func:`repair_nonmanifold`) unless ``repair=False``,
    which raises a FormatError for them. Models without vertex colours get a light grey.
    """
    mesh = load_mesh(ply_path, scale=0.001, name=name, material=material, validate=not repair)
    if repair:
        try:
            check_mesh(mesh, ply_path)
        except FormatError:
            mesh, _ = repair_nonmanifold(mesh)
            check_mesh(mesh, ply_path)
    if mesh.vertex_colors is None:
        mesh.vertex_colors = np.full((len(mesh.vertices), 3), 0.72)
    return mesh


# --------------------------------------------------------------------------- registered scenes

@register_scene("scenenet_room")
def build_scenenet_room(seed: int = 0, *, path: str) -> SceneSpec:
    """A SceneNet v1.0 room OBJ (``path``) converted to the z-up world; ``seed`` is unused."""
    return load_scenenet_room(path)


@register_scene("tless_obj")
def build_tless_scene(seed: int = 0, *, path: str, ground_size_m: float = 1.0,
                      yaw_rad: float = 0.0) -> SceneSpec:
    """One T-LESS CAD model (``path``, PLY in mm) resting on a ground plane.

    The model's lowest point is at z = 0 over the origin, turned by ``yaw_rad`` about z;
    ``seed`` varies the ground shades."""
    from synth.scenes.builtin import MATERIALS, _rot_z
    mesh = load_tless_model(path)
    lo, hi = mesh.bounds
    T = pose_matrix(_rot_z(float(yaw_rad))) @ pose_matrix(None, (-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]))
    obj = mesh.transformed(T)
    obj.name = Path(path).stem
    ground = _ground(float(ground_size_m), seed=seed, tiles=4)
    return SceneSpec([ground, obj], {"grey_floor": MATERIALS["grey_floor"], "tless_plastic": TLESS_MATERIAL})
