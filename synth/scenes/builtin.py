"""Embedded default scenes, built in code (no downloads).

Every builder returns a :class:`data_tools.scene_spec.SceneSpec` in the realgap world frame:
metres, z up, the floor at z = 0 for the built-in scenes. Each mesh has a unique name, a
material key into ``scene.materials`` and per-vertex colours (used for the shaded RGB). All
meshes pass :func:`data_tools.mesh.check_mesh`: every closed part (box, cylinder, curved slab)
is its own vertex set, so parts that touch never share an edge; walls, floor and ceiling are
open single-sided-looking quads (the raycaster hits both sides).

Objects made of several materials are split into one mesh per material, named
``"<object>.<part>"`` (``chair_a.cushion``, ``chair_a.frame``); :func:`object_name` maps a mesh
name to its object and :func:`object_instance_ids` groups the instance ids (k + 1 for
``scene.meshes[k]``) of one object.

Each is registered with :func:`synth.scenes.registry.register_scene`. Built-in:

``room``
    a furnished 5 x 4 x 2.6 m room (parquet floor, walls, ceiling, table, two office chairs,
    cabinet with books, cardboard boxes, bin, mug, floor lamp, posters, a glossy metal panel
    leaning on a wall, a black fabric pouf). The seed moves and recolours the clutter only.
``chair_a``, ``chair_b``, ``chair_c``
    one parametric office chair (:data:`CHAIR_VARIANTS`) on a 4 x 4 m ground plane.
``scenenet_room``, ``tless_obj``
    registered by :mod:`synth.scenes.loaders` (they need a ``path``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from data_tools.errors import ConfigError
from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material, SceneSpec
from synth.scenes.registry import SceneBuilder, register_scene

def object_name(mesh_name: str) -> str:
    """The object a mesh belongs to: the part of its name before the first ``.``."""
    return mesh_name.split(".", 1)[0]


def object_instance_ids(scene: SceneSpec) -> dict[str, list[int]]:
    """Instance ids (k + 1 for ``scene.meshes[k]``) grouped by :func:`object_name`."""
    out: dict[str, list[int]] = {}
    for k, m in enumerate(scene.meshes):
        out.setdefault(object_name(m.name), []).append(k + 1)
    return out


# --------------------------------------------------------------------------- materials

MATERIALS: dict[str, Material] = {
    "wood_floor": Material(0.45, 0.10),
    "wood_light": Material(0.55, 0.08),
    "white_wall": Material(0.80, 0.00),
    "accent_wall": Material(0.55, 0.00),
    "ceiling": Material(0.85, 0.00),
    "dark_plastic": Material(0.08, 0.05),
    "black_fabric": Material(0.03, 0.00),
    "metal_panel": Material(0.50, 0.70),
    "brushed_metal": Material(0.45, 0.35),
    "cardboard": Material(0.50, 0.02),
    "white_laminate": Material(0.70, 0.20),
    "paper": Material(0.65, 0.05),
    "ceramic": Material(0.70, 0.40),
    "grey_floor": Material(0.30, 0.05),
}
"""Built-in materials: ``albedo`` = diffuse IR/visible reflectance, ``specular`` = mirror-lobe
weight (see ../shared/FORMATS.md). Values are plausible figures for the named surfaces, not
measurements."""


def _materials(*keys: str) -> dict[str, Material]:
    return {k: MATERIALS[k] for k in keys}


# --------------------------------------------------------------------------- primitives

def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def pose_matrix(R: np.ndarray | None = None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 rigid transform from a 3x3 rotation (identity if None) and a translation (m)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


@dataclass
class _Part:
    """Vertices (V, 3), triangles (F, 3) and vertex colours (V, 3) of one closed or open piece."""

    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray

    def transformed(self, T: np.ndarray) -> "_Part":
        return _Part(self.vertices @ T[:3, :3].T + T[:3, 3], self.triangles, self.colors)


def _lattice_box(n: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Surface of the unit cube [-0.5, 0.5]^3 subdivided into n[0] x n[1] x n[2] cells.

    Returns (vertices (V, 3), triangles (F, 3)); closed, edge-manifold, counter-clockwise seen
    from outside. Subdivision lets callers bend the box smoothly (curved backrests).
    """
    nx, ny, nz = n
    gi, gj, gk = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    idx = (gi * (ny + 1) + gj) * (nz + 1) + gk
    quads = []

    def face(axis: int, side: int) -> None:
        # the two in-plane axes (a, b) are ordered so that a x b points along +axis
        a, b = {0: (1, 2), 1: (2, 0), 2: (0, 1)}[axis]
        sl = [slice(None)] * 3
        sl[axis] = side * n[axis]
        f = idx[tuple(sl)]  # 2D over the two remaining axes, in increasing axis order
        if a > b:
            f = f.T
        q = np.stack([f[:-1, :-1], f[1:, :-1], f[1:, 1:], f[:-1, 1:]], axis=-1).reshape(-1, 4)
        quads.append(q if side == 1 else q[:, ::-1])

    for axis in range(3):
        face(axis, 0)
        face(axis, 1)
    q = np.concatenate(quads)
    tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    used, inv = np.unique(tri, return_inverse=True)
    pts = np.stack([gi, gj, gk], axis=-1).reshape(-1, 3)[used] / np.array(n, float) - 0.5
    return pts, inv.reshape(-1, 3)


def box(size, T: np.ndarray | None = None, color=(0.5, 0.5, 0.5)) -> _Part:
    """Closed box of ``size`` (sx, sy, sz) metres centred at the origin, then moved by T."""
    v, f = _lattice_box((1, 1, 1))
    part = _Part(v * np.asarray(size, float), f, np.tile(np.asarray(color, float), (len(v), 1)))
    return part.transformed(T) if T is not None else part


def cylinder(radius: float, height: float, T: np.ndarray | None = None, color=(0.5, 0.5, 0.5),
             sections: int = 24, radius_top: float | None = None) -> _Part:
    """Closed (truncated-cone) cylinder along +z from z=0 to z=height, axis through the origin."""
    rt = radius if radius_top is None else radius_top
    a = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    v = np.concatenate([np.c_[ring * radius, np.zeros(sections)], np.c_[ring * rt, np.full(sections, height)],
                        [[0.0, 0.0, 0.0], [0.0, 0.0, height]]])
    i = np.arange(sections)
    j = (i + 1) % sections
    cb, ct = 2 * sections, 2 * sections + 1
    side = np.concatenate([np.c_[i, j, sections + j], np.c_[i, sections + j, sections + i]])
    bottom = np.c_[np.full(sections, cb), j, i]
    top = np.c_[np.full(sections, ct), sections + i, sections + j]
    part = _Part(v, np.concatenate([side, bottom, top]), np.tile(np.asarray(color, float), (len(v), 1)))
    return part.transformed(T) if T is not None else part


def quad(corners, color=(0.5, 0.5, 0.5), colors=None) -> _Part:
    """Open quad from 4 corners (4, 3) in counter-clockwise order seen from its front side."""
    c = np.asarray(corners, float).reshape(4, 3)
    col = np.tile(np.asarray(color, float), (4, 1)) if colors is None else np.asarray(colors, float)
    return _Part(c, np.array([[0, 1, 2], [0, 2, 3]]), col)


def curved_slab(width: float, height: float, thickness: float, radius: float,
                T: np.ndarray | None = None, color=(0.5, 0.5, 0.5), segments: int = 12) -> _Part:
    """Closed slab (width along y, thickness along x, height along z) bent around a vertical axis.

    The slab is centred at the origin and curves towards +x at its ends with curvature
    radius ``radius`` metres (``inf`` = flat), like an office-chair backrest wrapping around
    the sitter who faces +x.
    """
    v, f = _lattice_box((1, segments, 1))
    x = v[:, 0] * thickness
    y = v[:, 1] * width
    z = v[:, 2] * height
    if math.isfinite(radius):
        ang = y / radius
        r = radius - x  # the axis of the bend is at x = +radius
        x, y = radius - r * np.cos(ang), r * np.sin(ang)
    part = _Part(np.stack([x, y, z], axis=1), f, np.tile(np.asarray(color, float), (len(v), 1)))
    return part.transformed(T) if T is not None else part


def merge_parts(parts: list[_Part], name: str, material: str) -> TriMesh:
    """One TriMesh from disjoint parts (vertex sets stay separate, so no edge is shared)."""
    verts, tris, cols = [], [], []
    off = 0
    for p in parts:
        verts.append(p.vertices)
        tris.append(p.triangles + off)
        cols.append(p.colors)
        off += len(p.vertices)
    return TriMesh(np.concatenate(verts), np.concatenate(tris), name, material,
                   np.clip(np.concatenate(cols), 0.0, 1.0))


# --------------------------------------------------------------------------- chairs

@dataclass(frozen=True)
class ChairParams:
    """Geometry of a parametric 5-star office chair; the sitter faces +x, origin on the floor
    under the gas column."""

    seat_width_m: float = 0.48
    """Seat size across (y), metres."""
    seat_depth_m: float = 0.46
    """Seat size front to back (x), metres."""
    seat_height_m: float = 0.47
    """Height of the top of the seat cushion above the floor, metres."""
    seat_thickness_m: float = 0.07
    """Seat cushion thickness, metres."""
    back_height_m: float = 0.50
    """Backrest height, metres."""
    back_width_m: float = 0.46
    """Backrest width (arc length), metres."""
    back_radius_m: float = 0.55
    """Horizontal curvature radius of the backrest (inf = flat), metres."""
    back_recline_rad: float = 0.17
    """Backward tilt of the backrest from vertical, radians."""
    armrests: bool = False
    """Whether the chair has armrests."""
    base_radius_m: float = 0.33
    """Reach of the 5-star base legs from the column axis, metres."""


CHAIR_VARIANTS: dict[str, ChairParams] = {
    "chair_a": ChairParams(),
    "chair_b": ChairParams(armrests=True),
    "chair_c": ChairParams(seat_width_m=0.51, back_height_m=0.58, back_radius_m=1.2, armrests=True),
}
"""Three near-identical office chairs: ``chair_b`` = ``chair_a`` + armrests; ``chair_c`` has
armrests, a 3 cm wider seat and a taller (0.58 vs 0.50 m), flatter (1.2 vs 0.55 m radius)
backrest."""

CUSHION_COLOR = (0.05, 0.05, 0.06)
FRAME_COLOR = (0.12, 0.12, 0.13)


def chair_meshes(variant: str | ChairParams = "chair_a", name: str | None = None,
                 T: np.ndarray | None = None) -> list[TriMesh]:
    """The meshes of one office chair: ``<name>.cushion`` (seat + backrest, ``black_fabric``)
    and ``<name>.frame`` (base, casters, column, mechanism, back bar, armrests,
    ``dark_plastic``), moved by the 4x4 transform ``T`` (default identity).

    The materials come from :data:`MATERIALS`; a scene using these meshes must include
    ``black_fabric`` and ``dark_plastic`` in its material table.
    """
    if isinstance(variant, ChairParams):
        p, vname = variant, "chair"
    else:
        if variant not in CHAIR_VARIANTS:
            raise ConfigError(f"unknown chair variant {variant!r}; known: {', '.join(CHAIR_VARIANTS)}")
        p, vname = CHAIR_VARIANTS[variant], variant
    name = name or vname
    frame: list[_Part] = []
    # 5-star base: legs sloping slightly down to the casters
    hub_z, leg_end_z, caster_h = 0.10, 0.065, 0.05
    for k in range(5):
        a = 2 * np.pi * k / 5 + np.pi / 5  # no leg straight forward, one straight back
        L = p.base_radius_m
        mid = np.array([L / 2 * math.cos(a), L / 2 * math.sin(a), (hub_z + leg_end_z) / 2])
        slope = math.atan2(hub_z - leg_end_z, L)
        R = _rot_z(a) @ _rot_y(slope)
        frame.append(box((L, 0.045, 0.035), pose_matrix(R, mid), FRAME_COLOR))
        cx, cy = (L - 0.02) * math.cos(a), (L - 0.02) * math.sin(a)
        frame.append(cylinder(0.025, caster_h, pose_matrix(None, (cx, cy, 0.0)), FRAME_COLOR, sections=12))
    frame.append(cylinder(0.055, 0.05, pose_matrix(None, (0, 0, hub_z - 0.03)), FRAME_COLOR, sections=16))
    seat_bottom = p.seat_height_m - p.seat_thickness_m
    mech_h = 0.05
    col_top = seat_bottom - mech_h
    frame.append(cylinder(0.035, 0.18, pose_matrix(None, (0, 0, hub_z + 0.02)), FRAME_COLOR, sections=16))
    frame.append(cylinder(0.022, col_top - hub_z - 0.02, pose_matrix(None, (0, 0, hub_z + 0.02)),
                          (0.35, 0.35, 0.37), sections=16))
    frame.append(box((0.22, 0.20, mech_h), pose_matrix(None, (0.0, 0.0, col_top + mech_h / 2)), FRAME_COLOR))
    cushion: list[_Part] = []
    cushion.append(box((p.seat_depth_m, p.seat_width_m, p.seat_thickness_m),
                       pose_matrix(None, (0.0, 0.0, seat_bottom + p.seat_thickness_m / 2)), CUSHION_COLOR))
    # backrest: bent slab behind the seat, reclined backwards about the y axis
    back_x = -p.seat_depth_m / 2 - 0.02
    back_z0 = p.seat_height_m + 0.06
    Rb = _rot_y(-p.back_recline_rad)
    centre = np.array([back_x, 0.0, back_z0]) + Rb @ np.array([0.0, 0.0, p.back_height_m / 2])
    cushion.append(curved_slab(p.back_width_m, p.back_height_m, 0.06, p.back_radius_m,
                               pose_matrix(Rb, centre), CUSHION_COLOR))
    # back support bar: from the mechanism to the back of the backrest
    bar_top = np.array([back_x - 0.05, 0.0, back_z0]) + Rb @ np.array([0.0, 0.0, 0.25 * p.back_height_m])
    bar_bottom = np.array([-0.10, 0.0, seat_bottom - 0.03])
    d = bar_top - bar_bottom
    Rbar = _rot_y(math.atan2(d[0], d[2]))
    frame.append(box((0.03, 0.06, float(np.linalg.norm(d))), pose_matrix(Rbar, (bar_top + bar_bottom) / 2), FRAME_COLOR))
    if p.armrests:
        for s in (-1.0, 1.0):
            y = s * (p.seat_width_m / 2 + 0.035)
            frame.append(box((0.04, 0.03, 0.22), pose_matrix(None, (-0.02, y, p.seat_height_m + 0.08)), FRAME_COLOR))
            frame.append(box((0.05, 0.03, 0.03), pose_matrix(None, (-0.02, s * (p.seat_width_m / 2 + 0.005),
                                                                   seat_bottom - 0.01)), FRAME_COLOR))
            frame.append(box((0.26, 0.075, 0.03), pose_matrix(None, (-0.01, y, p.seat_height_m + 0.205)), FRAME_COLOR))
    meshes = [merge_parts(cushion, f"{name}.cushion", "black_fabric"),
              merge_parts(frame, f"{name}.frame", "dark_plastic")]
    if T is not None:
        meshes = [m.transformed(T) for m in meshes]
    return meshes


def _ground(size: float, name: str = "ground", material: str = "grey_floor", tiles: int = 8,
            seed: int = 0) -> TriMesh:
    """Square ground plane of side ``size`` metres at z = 0, facing up, as a chequer of
    slightly different greys (so the RGB has texture)."""
    rng = np.random.default_rng(seed)
    parts = []
    e = np.linspace(-size / 2, size / 2, tiles + 1)
    for i in range(tiles):
        for j in range(tiles):
            g = 0.32 + 0.06 * ((i + j) % 2) + rng.uniform(-0.02, 0.02)
            parts.append(quad([[e[i], e[j], 0], [e[i + 1], e[j], 0], [e[i + 1], e[j + 1], 0], [e[i], e[j + 1], 0]],
                              (g, g, g * 1.02)))
    return merge_parts(parts, name, material)


def build_chair(variant: str = "chair_a", seed: int = 0, ground_size_m: float = 4.0,
                yaw_rad: float = 0.0) -> SceneSpec:
    """One office chair (:data:`CHAIR_VARIANTS`) standing on a ground plane at the origin.

    ``yaw_rad`` turns the chair about z (0: the sitter faces +x); ``seed`` only varies the
    ground tiles' shades.
    """
    if not ground_size_m > 0:
        raise ConfigError(f"ground_size_m must be positive, got {ground_size_m}")
    T = pose_matrix(_rot_z(float(yaw_rad)))
    meshes = [_ground(float(ground_size_m), seed=seed)] + chair_meshes(variant, T=T)
    return SceneSpec(meshes, _materials("grey_floor", "black_fabric", "dark_plastic"))


def _chair_builder(variant: str) -> SceneBuilder:
    def build(seed: int = 0, ground_size_m: float = 4.0, yaw_rad: float = 0.0) -> SceneSpec:
        return build_chair(variant, seed, ground_size_m, yaw_rad)
    build.__name__ = f"build_{variant}"
    build.__doc__ = f"Office chair {variant} (CHAIR_VARIANTS) on a ground plane; see build_chair."
    return build


for _v in CHAIR_VARIANTS:
    register_scene(_v)(_chair_builder(_v))


# --------------------------------------------------------------------------- room

ROOM_SIZE_M = (5.0, 4.0, 2.6)
"""Inner size of the ``room`` scene (x, y, z), metres; the room spans x in [-2.5, 2.5],
y in [-2, 2], z in [0, 2.6]."""


def _parquet(sx: float, sy: float, rng: np.random.Generator) -> TriMesh:
    """Floor of staggered wooden planks (each its own quad with its own shade), facing up."""
    parts = []
    plank_w, plank_l = 0.20, 1.0
    nrow = int(round(sy / plank_w))
    for r in range(nrow):
        y0, y1 = -sy / 2 + r * plank_w, -sy / 2 + (r + 1) * plank_w
        off = rng.uniform(0, plank_l)
        xs = np.concatenate([[-sx / 2], np.arange(-sx / 2 + off, sx / 2, plank_l), [sx / 2]])
        xs = np.unique(np.clip(xs, -sx / 2, sx / 2))
        for x0, x1 in zip(xs[:-1], xs[1:]):
            if x1 - x0 < 1e-3:
                continue
            base = np.array([0.55, 0.38, 0.22]) * rng.uniform(0.8, 1.15)
            # a light grain gradient along the plank
            c0, c1 = base * rng.uniform(0.9, 1.0), base * rng.uniform(1.0, 1.1)
            parts.append(quad([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]],
                              colors=[c0, c1, c1, c0]))
    return merge_parts(parts, "floor", "wood_floor")


def _poster(name: str, centre, normal_axis: str, size, rng: np.random.Generator) -> TriMesh:
    """A framed poster on a wall: a thin closed frame box plus a grid of coloured patches
    1 mm in front of it (open quads). ``normal_axis`` is the direction the poster faces."""
    w, h = size
    cols, rows = 4, 3
    dirs = {"+x": (np.array([0, -1, 0.]), np.array([1, 0, 0.])), "-x": (np.array([0, 1, 0.]), np.array([-1, 0, 0.])),
            "+y": (np.array([1, 0, 0.]), np.array([0, 1, 0.])), "-y": (np.array([-1, 0, 0.]), np.array([0, -1, 0.]))}
    right, n = dirs[normal_axis]
    up = np.array([0, 0, 1.0])
    centre = np.asarray(centre, float)
    R = np.stack([right, up, n], axis=1)  # box axes: x=right, y=up, z=normal
    parts = [box((w + 0.06, h + 0.06, 0.02), pose_matrix(R, centre + n * 0.01), (0.15, 0.1, 0.08))]
    palette = rng.uniform(0.1, 0.95, size=(cols * rows, 3))
    for k in range(cols * rows):
        i, j = k % cols, k // cols
        u0, u1 = -w / 2 + i * w / cols, -w / 2 + (i + 1) * w / cols
        v0, v1 = -h / 2 + j * h / rows, -h / 2 + (j + 1) * h / rows
        c = centre + n * 0.021
        corners = [c + right * u0 + up * v0, c + right * u1 + up * v0, c + right * u1 + up * v1, c + right * u0 + up * v1]
        parts.append(quad(corners, palette[k]))
    return merge_parts(parts, name, "paper")


@register_scene("room")
def build_room(seed: int = 0) -> SceneSpec:
    """A furnished 5 x 4 x 2.6 m room (see the module docstring), floor at z = 0.

    Furniture positions are fixed; ``seed`` shuffles floor-plank shades, poster colours and
    the placement of the cardboard boxes and the mug within small ranges.
    """
    rng = np.random.default_rng(seed)
    sx, sy, sz = ROOM_SIZE_M
    hx, hy = sx / 2, sy / 2
    meshes: list[TriMesh] = [_parquet(sx, sy, rng)]
    white = (0.90, 0.90, 0.87)
    # walls: open quads facing into the room (counter-clockwise seen from inside)
    walls = {
        "wall_south": [[-hx, -hy, 0], [hx, -hy, 0], [hx, -hy, sz], [-hx, -hy, sz]],
        "wall_east": [[hx, -hy, 0], [hx, hy, 0], [hx, hy, sz], [hx, -hy, sz]],
        "wall_north": [[hx, hy, 0], [-hx, hy, 0], [-hx, hy, sz], [hx, hy, sz]],
        "wall_west": [[-hx, hy, 0], [-hx, -hy, 0], [-hx, -hy, sz], [-hx, hy, sz]],
    }
    for wname, corners in walls.items():
        accent = wname == "wall_east"
        color = (0.55, 0.63, 0.70) if accent else white
        c = np.array(corners, float)
        shade = np.array([1.0, 1.0, 0.93, 0.93])[:, None]  # slightly darker towards the ceiling
        meshes.append(merge_parts([quad(c, colors=np.asarray(color) * shade)], wname,
                                  "accent_wall" if accent else "white_wall"))
    meshes.append(merge_parts([quad([[-hx, -hy, sz], [-hx, hy, sz], [hx, hy, sz], [hx, -hy, sz]], (0.93, 0.93, 0.92))],
                              "ceiling", "ceiling"))
    # skirting boards along the walls (closed thin boxes)
    sk = [box((sx, 0.015, 0.08), pose_matrix(None, (0, -hy + 0.0075, 0.04)), (0.95, 0.95, 0.95)),
          box((sx, 0.015, 0.08), pose_matrix(None, (0, hy - 0.0075, 0.04)), (0.95, 0.95, 0.95)),
          box((0.015, sy - 0.03, 0.08), pose_matrix(None, (-hx + 0.0075, 0, 0.04)), (0.95, 0.95, 0.95)),
          box((0.015, sy - 0.03, 0.08), pose_matrix(None, (hx - 0.0075, 0, 0.04)), (0.95, 0.95, 0.95))]
    meshes.append(merge_parts(sk, "skirting", "white_laminate"))
    # door on the west wall
    meshes.append(merge_parts([box((0.04, 0.9, 2.05), pose_matrix(None, (-hx + 0.02, 1.1, 1.025)), (0.62, 0.45, 0.30)),
                               box((0.06, 0.12, 0.02), pose_matrix(None, (-hx + 0.07, 0.75, 1.0)), (0.7, 0.7, 0.72))],
                              "door", "wood_light"))
    # table in the middle, slightly towards the north-east
    tx, ty, tw, td, th = 0.4, 0.3, 1.4, 0.8, 0.75
    meshes.append(merge_parts([box((tw, td, 0.04), pose_matrix(None, (tx, ty, th - 0.02)), (0.70, 0.52, 0.34))],
                              "table.top", "wood_light"))
    legs = [box((0.05, 0.05, th - 0.04), pose_matrix(None, (tx + sxl * (tw / 2 - 0.06), ty + syl * (td / 2 - 0.06),
                                                             (th - 0.04) / 2)), (0.6, 0.6, 0.62))
            for sxl in (-1, 1) for syl in (-1, 1)]
    meshes.append(merge_parts(legs, "table.legs", "brushed_metal"))
    # two office chairs at the table, facing it
    meshes += chair_meshes("chair_a", "chair_1", pose_matrix(_rot_z(np.pi / 2 + 0.15), (tx - 0.25, ty - 0.75, 0)))
    meshes += chair_meshes("chair_b", "chair_2", pose_matrix(_rot_z(-0.1), (tx - 1.15, ty + 0.05, 0)))
    # objects on the table: a cardboard box, a glossy metal can (mug-like), a small book stack
    mx, my = tx + 0.35 + rng.uniform(-0.1, 0.1), ty + 0.1 + rng.uniform(-0.1, 0.1)
    meshes.append(merge_parts([cylinder(0.04, 0.11, pose_matrix(None, (mx, my, th)), (0.75, 0.76, 0.78))],
                              "can", "metal_panel"))
    meshes.append(merge_parts([cylinder(0.045, 0.10, pose_matrix(None, (tx - 0.3, ty + 0.2, th)), (0.85, 0.25, 0.2),
                                        radius_top=0.05)], "mug", "ceramic"))
    a = rng.uniform(-0.4, 0.4)
    meshes.append(merge_parts([box((0.30, 0.22, 0.16), pose_matrix(_rot_z(a), (tx + 0.1, ty - 0.15, th + 0.08)),
                                   (0.62, 0.46, 0.30))], "box_table", "cardboard"))
    # cabinet against the north wall with books on top
    cab_x, cab_w, cab_d, cab_h = -1.3, 1.2, 0.4, 0.9
    cab = [box((cab_w, cab_d, cab_h), pose_matrix(None, (cab_x, hy - cab_d / 2 - 0.02, cab_h / 2)), (0.92, 0.92, 0.90))]
    meshes.append(merge_parts(cab, "cabinet", "white_laminate"))
    books, bx = [], cab_x - 0.45
    for k in range(7):
        w = rng.uniform(0.03, 0.06)
        h = rng.uniform(0.18, 0.27)
        books.append(box((w, 0.17, h), pose_matrix(None, (bx + w / 2, hy - 0.15, cab_h + h / 2)),
                         rng.uniform(0.15, 0.85, 3)))
        bx += w + 0.005
    meshes.append(merge_parts(books, "books", "paper"))
    # cardboard boxes in the south-west corner (seeded placement)
    cb = []
    for k, (bsz, base) in enumerate([((0.5, 0.4, 0.35), (-1.9, -1.5)), ((0.4, 0.35, 0.3), (-1.3, -1.6)),
                                     ((0.35, 0.3, 0.25), (-1.85, -1.45))]):
        jitter = rng.uniform(-0.05, 0.05, 2)
        z0 = 0.0 if k < 2 else 0.35
        cb.append(box(bsz, pose_matrix(_rot_z(rng.uniform(-0.3, 0.3)), (base[0] + jitter[0], base[1] + jitter[1],
                                                                         z0 + bsz[2] / 2)),
                      np.array([0.60, 0.44, 0.28]) * rng.uniform(0.9, 1.1)))
    for k, p in enumerate(cb):
        meshes.append(merge_parts([p], f"box_{k + 1}", "cardboard"))
    # waste bin (dark plastic cylinder) and a black fabric pouf
    meshes.append(merge_parts([cylinder(0.14, 0.35, pose_matrix(None, (1.4, -0.6, 0)), (0.10, 0.10, 0.11), radius_top=0.16)],
                              "bin", "dark_plastic"))
    meshes.append(merge_parts([cylinder(0.25, 0.40, pose_matrix(None, (-0.6, -1.2, 0)), (0.04, 0.04, 0.045), sections=32)],
                              "pouf", "black_fabric"))
    # floor lamp in the north-east corner
    lamp = [cylinder(0.15, 0.03, pose_matrix(None, (2.1, 1.6, 0)), (0.2, 0.2, 0.2)),
            cylinder(0.015, 1.45, pose_matrix(None, (2.1, 1.6, 0.03)), (0.6, 0.6, 0.6), sections=12)]
    meshes.append(merge_parts(lamp, "lamp.stand", "brushed_metal"))
    meshes.append(merge_parts([cylinder(0.22, 0.28, pose_matrix(None, (2.1, 1.6, 1.45)), (0.95, 0.92, 0.8), radius_top=0.14)],
                              "lamp.shade", "paper"))
    # glossy metal panel leaning against the east wall (tilted 20 degrees from vertical)
    tilt = math.radians(20.0)
    ph, pw = 1.0, 0.7
    Rp = _rot_y(tilt)  # top leans towards +x (the wall)
    pc = np.array([hx - 0.02 - math.sin(tilt) * ph / 2 - 0.01, -1.1, math.cos(tilt) * ph / 2 + 0.01])
    meshes.append(merge_parts([box((0.012, pw, ph), pose_matrix(Rp, pc), (0.72, 0.74, 0.78))], "panel", "metal_panel"))
    # posters
    meshes.append(_poster("poster_1", (0.6, -hy + 0.001, 1.55), "+y", (1.0, 0.7), rng))
    meshes.append(_poster("poster_2", (hx - 0.001, 0.6, 1.5), "-x", (0.8, 0.6), rng))
    meshes.append(_poster("poster_3", (-hx + 0.001, -0.7, 1.5), "+x", (0.7, 0.9), rng))
    return SceneSpec(meshes, _materials(*sorted({m.material for m in meshes})))


# --------------------------------------------------------------------------- procedural rooms

@register_scene("procedural_room")
def build_procedural_room(seed: int = 0) -> SceneSpec:
    """A random furnished room, one per seed (training worlds of the neural memory, thesis 4.4.3).

    The seed draws everything: the inner size (3.5 - 6.5 m x 3 - 5.5 m, 2.4 - 2.8 m high; floor at
    z = 0, centred on the origin), wall colours (one accent wall), a parquet floor, 1 - 3 posters,
    and 5 - 10 pieces of furniture against the walls or free-standing (cabinets, shelves with
    books, tables, cardboard boxes, bins, poufs, office chairs) in random sizes, colours and
    orientations. Free-standing pieces keep 1.2 m around the room's centre clear so that a robot
    started there can move.
    """
    rng = np.random.default_rng(seed)
    sx, sy, sz = rng.uniform(3.5, 6.5), rng.uniform(3.0, 5.5), rng.uniform(2.4, 2.8)
    hx, hy = sx / 2, sy / 2
    meshes: list[TriMesh] = [_parquet(sx, sy, rng)]
    walls = {
        "wall_south": ([[-hx, -hy, 0], [hx, -hy, 0], [hx, -hy, sz], [-hx, -hy, sz]], "+y"),
        "wall_east": ([[hx, -hy, 0], [hx, hy, 0], [hx, hy, sz], [hx, -hy, sz]], "-x"),
        "wall_north": ([[hx, hy, 0], [-hx, hy, 0], [-hx, hy, sz], [hx, hy, sz]], "-y"),
        "wall_west": ([[-hx, hy, 0], [-hx, -hy, 0], [-hx, -hy, sz], [-hx, hy, sz]], "+x"),
    }
    base = rng.uniform(0.7, 0.95, 3)
    accent = list(walls)[int(rng.integers(4))]
    for wname, (corners, _n) in walls.items():
        color = rng.uniform(0.2, 0.8, 3) if wname == accent else base
        shade = np.array([1.0, 1.0, 0.93, 0.93])[:, None]
        meshes.append(merge_parts([quad(np.array(corners, float), colors=np.asarray(color) * shade)], wname,
                                  "accent_wall" if wname == accent else "white_wall"))
    meshes.append(merge_parts([quad([[-hx, -hy, sz], [-hx, hy, sz], [hx, hy, sz], [hx, -hy, sz]], (0.93, 0.93, 0.92))],
                              "ceiling", "ceiling"))
    for k in range(int(rng.integers(1, 4))):
        wname = list(walls)[int(rng.integers(4))]
        n = walls[wname][1]
        along = hx if n in ("+y", "-y") else hy
        u = rng.uniform(-along + 0.6, along - 0.6)
        off = {"+y": (u, -hy + 0.001), "-y": (u, hy - 0.001), "+x": (-hx + 0.001, u), "-x": (hx - 0.001, u)}[n]
        meshes.append(_poster(f"poster_{k + 1}", (off[0], off[1], rng.uniform(1.2, 1.7)), n,
                              (rng.uniform(0.5, 1.1), rng.uniform(0.4, 0.9)), rng))
    kinds = ["cabinet", "shelf", "table", "box", "bin", "pouf", "chair"]
    placed: list[tuple[float, float, float]] = []     # (x, y, radius) footprints
    for k in range(int(rng.integers(5, 11))):
        kind = kinds[int(rng.integers(len(kinds)))]
        for _try in range(40):
            against = kind in ("cabinet", "shelf") or rng.random() < 0.4
            w, d = {"cabinet": (rng.uniform(0.6, 1.6), rng.uniform(0.35, 0.6)),
                    "shelf": (rng.uniform(0.6, 1.2), rng.uniform(0.25, 0.4)),
                    "table": (rng.uniform(0.8, 1.6), rng.uniform(0.6, 0.9)),
                    "box": (rng.uniform(0.25, 0.6), rng.uniform(0.25, 0.5)),
                    "bin": (0.3, 0.3), "pouf": (0.5, 0.5), "chair": (0.65, 0.65)}[kind]
            rad = 0.5 * math.hypot(w, d)
            if against:
                side = int(rng.integers(4))
                a = side * math.pi / 2
                if side % 2 == 0:
                    x, y = rng.uniform(-hx + rad, hx - rad), (-hy + d / 2 + 0.02) * (1 if side == 0 else -1)
                else:
                    x, y = (hx - d / 2 - 0.02) * (1 if side == 1 else -1), rng.uniform(-hy + rad, hy - rad)
                yaw = a
            else:
                x, y = rng.uniform(-hx + rad, hx - rad), rng.uniform(-hy + rad, hy - rad)
                yaw = rng.uniform(-math.pi, math.pi)
                if math.hypot(x, y) < 1.2 + rad:
                    continue
            if any(math.hypot(x - px, y - py) < rad + pr + 0.05 for px, py, pr in placed):
                continue
            placed.append((x, y, rad))
            R = _rot_z(yaw)
            col = rng.uniform(0.1, 0.9, 3)
            name = f"{kind}_{k + 1}"
            if kind == "cabinet":
                h = rng.uniform(0.7, 1.9)
                meshes.append(merge_parts([box((w, d, h), pose_matrix(R, (x, y, h / 2)), col)], name, "white_laminate"))
            elif kind == "shelf":
                h, parts = rng.uniform(1.2, 2.0), []
                for z in np.linspace(0.02, h - 0.02, int(rng.integers(3, 6))):
                    parts.append(box((w, d, 0.03), pose_matrix(R, (x, y, z)), col))
                    bx = -w / 2 + 0.05
                    while bx < w / 2 - 0.08 and z + 0.3 < h:
                        bw, bh = rng.uniform(0.02, 0.06), rng.uniform(0.15, 0.26)
                        off = R @ np.array([bx + bw / 2, 0.0, 0.0])
                        parts.append(box((bw, d * 0.8, bh), pose_matrix(R, (x + off[0], y + off[1], z + 0.015 + bh / 2)),
                                         rng.uniform(0.1, 0.9, 3)))
                        bx += bw + rng.uniform(0.0, 0.08)
                meshes.append(merge_parts(parts, name, "wood_light"))
            elif kind == "table":
                h = rng.uniform(0.65, 0.8)
                parts = [box((w, d, 0.04), pose_matrix(R, (x, y, h - 0.02)), col)]
                for sxl in (-1, 1):
                    for syl in (-1, 1):
                        off = R @ np.array([sxl * (w / 2 - 0.05), syl * (d / 2 - 0.05), 0.0])
                        parts.append(box((0.05, 0.05, h - 0.04), pose_matrix(R, (x + off[0], y + off[1], (h - 0.04) / 2)),
                                         (0.5, 0.5, 0.52)))
                meshes.append(merge_parts(parts, name, "wood_light"))
            elif kind == "box":
                h = rng.uniform(0.2, 0.6)
                meshes.append(merge_parts([box((w, d, h), pose_matrix(R, (x, y, h / 2)),
                                               np.array([0.6, 0.44, 0.28]) * rng.uniform(0.8, 1.2))], name, "cardboard"))
            elif kind == "bin":
                meshes.append(merge_parts([cylinder(0.14, rng.uniform(0.3, 0.5), pose_matrix(None, (x, y, 0)), col,
                                                    radius_top=0.16)], name, "dark_plastic"))
            elif kind == "pouf":
                meshes.append(merge_parts([cylinder(0.25, 0.4, pose_matrix(None, (x, y, 0)), col * 0.3, sections=32)],
                                          name, "black_fabric"))
            else:
                meshes += chair_meshes(["chair_a", "chair_b", "chair_c"][int(rng.integers(3))], name,
                                       pose_matrix(R, (x, y, 0)))
            break
    return SceneSpec(meshes, _materials(*sorted({m.material for m in meshes})))
