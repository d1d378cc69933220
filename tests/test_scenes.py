"""Built-in scenes, the scene registry, mesh primitives and the SceneNet / T-LESS loaders."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.errors import ConfigError, FormatError
from data_tools.geometry import is_rigid
from data_tools.mesh import TriMesh, check_mesh
from synth.scenes import build_scene, object_instance_ids, scene_names
from synth.scenes.builtin import CHAIR_VARIANTS, _lattice_box, chair_meshes, curved_slab, cylinder
from synth.scenes.loaders import (SCENENET_TO_WORLD, load_scenenet_room, load_scenenet_trajectory,
                                  load_tless_model, repair_nonmanifold)
from tests.conftest import shared_path

BUILTIN = ["room", "chair_a", "chair_b", "chair_c"]


def _edge_counts(tri: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    t = v[f]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


# --------------------------------------------------------------------------- primitives

@pytest.mark.parametrize("n", [(1, 1, 1), (1, 6, 1), (2, 3, 4)])
def test_lattice_box_is_closed_and_outward(n):
    v, f = _lattice_box(n)
    assert np.all(_edge_counts(f) == 2)  # closed 2-manifold
    assert _signed_volume(v, f) == pytest.approx(1.0)  # unit cube, counter-clockwise outside
    assert np.allclose(np.abs(v).max(0), 0.5)


def test_cylinder_closed_with_expected_volume():
    p = cylinder(0.1, 0.5, sections=64)
    assert np.all(_edge_counts(p.triangles) == 2)
    # a 64-gon prism: area = 0.5 * n * r^2 * sin(2 pi / n)
    expected = 0.5 * 64 * 0.01 * np.sin(2 * np.pi / 64) * 0.5
    assert _signed_volume(p.vertices, p.triangles) == pytest.approx(expected, rel=1e-9)


def test_curved_slab_bends_towards_plus_x_and_stays_closed():
    flat = curved_slab(0.5, 0.4, 0.05, np.inf, segments=10)
    bent = curved_slab(0.5, 0.4, 0.05, 0.5, segments=10)
    assert np.all(_edge_counts(bent.triangles) == 2)
    assert _signed_volume(bent.vertices, bent.triangles) > 0
    assert np.ptp(flat.vertices[:, 0]) == pytest.approx(0.05)
    ends = np.abs(bent.vertices[:, 1]) > 0.2
    assert bent.vertices[ends, 0].min() > 0.0  # the ends wrap forward (towards the sitter)


# --------------------------------------------------------------------------- registry

def test_registry_lists_builtin_and_loader_scenes():
    names = scene_names()
    for n in BUILTIN + ["scenenet_room", "tless_obj"]:
        assert n in names


def test_build_scene_errors_are_config_errors():
    with pytest.raises(ConfigError, match="known scenes: .*room"):
        build_scene("no_such_scene")
    with pytest.raises(ConfigError, match="no parameter"):
        build_scene("room", width=3)
    with pytest.raises(ConfigError, match="needs parameter.*path"):
        build_scene("scenenet_room")
    with pytest.raises(ConfigError, match="unknown chair variant"):
        chair_meshes("chair_z")


@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_scene_meshes_are_valid(name):
    scene = build_scene(name, seed=0)
    names = [m.name for m in scene.meshes]
    assert len(set(names)) == len(names)
    for m in scene.meshes:
        check_mesh(m)
        assert m.material in scene.materials
        assert m.vertex_colors is not None and m.vertex_colors.shape == m.vertices.shape
        assert m.vertex_colors.min() >= 0 and m.vertex_colors.max() <= 1
    for mat in scene.materials.values():
        assert 0 <= mat.albedo <= 1 and 0 <= mat.specular <= 1


def test_room_layout_and_materials():
    scene = build_scene("room")
    v = np.concatenate([m.vertices for m in scene.meshes])
    assert np.allclose(v.min(0), [-2.5, -2.0, 0.0], atol=1e-9)
    assert np.allclose(v.max(0), [2.5, 2.0, 2.6], atol=1e-9)
    by_name = {m.name: m for m in scene.meshes}
    for required in ("floor", "ceiling", "wall_north", "table.top", "chair_1.cushion", "chair_2.frame",
                     "panel", "bin", "box_1"):
        assert required in by_name
    mats = {scene.material_of(m).albedo for m in scene.meshes}
    assert min(mats) <= 0.05 and max(mats) >= 0.8  # black fabric ... white wall
    assert scene.material_of(by_name["panel"]).specular >= 0.5  # glossy metal panel
    # the panel is tilted: its long axis is neither vertical nor horizontal
    p = by_name["panel"].vertices
    assert 0.8 < np.ptp(p[:, 2]) < 1.0 and np.ptp(p[:, 0]) > 0.3


def test_room_is_deterministic_and_seed_moves_clutter_only():
    a, b, c = build_scene("room", seed=0), build_scene("room", seed=0), build_scene("room", seed=1)
    for ma, mb in zip(a.meshes, b.meshes):
        assert ma.name == mb.name and np.array_equal(ma.vertices, mb.vertices)
        assert np.array_equal(ma.vertex_colors, mb.vertex_colors)
    by_c = {m.name: m for m in c.meshes}
    same = {m.name for m in a.meshes if np.array_equal(m.vertices, by_c[m.name].vertices)}
    assert {"table.top", "chair_1.frame", "wall_east", "cabinet"} <= same
    assert "box_1" not in same and "can" not in same


def test_chairs_differ_but_are_similar():
    sizes, areas, verts = {}, {}, {}
    for v in CHAIR_VARIANTS:
        scene = build_scene(v)
        parts = [m for m in scene.meshes if m.name.startswith(v)]
        assert {m.name for m in parts} == {f"{v}.cushion", f"{v}.frame"}
        allv = np.concatenate([m.vertices for m in parts])
        sizes[v] = np.ptp(allv, axis=0)
        areas[v] = sum(m.area() for m in parts)
        verts[v] = allv
        assert allv[:, 2].min() == pytest.approx(0.0, abs=1e-9)  # stands on the ground
    names = list(CHAIR_VARIANTS)
    for i in range(3):
        for j in range(i + 1, 3):
            a, b = names[i], names[j]
            assert np.all(np.abs(sizes[a] - sizes[b]) <= 0.15 * sizes[a])  # similar
            assert abs(areas[a] - areas[b]) > 0.03 * areas[a]  # but not the same chair
    assert sizes["chair_c"][2] > sizes["chair_a"][2] + 0.05  # taller backrest


def test_object_instance_ids_group_parts():
    scene = build_scene("room")
    groups = object_instance_ids(scene)
    assert len(groups["chair_1"]) == 2 and len(groups["table"]) == 2
    ids = sorted(i for g in groups.values() for i in g)
    assert ids == list(range(1, len(scene.meshes) + 1))


# --------------------------------------------------------------------------- repair

def test_repair_removes_back_to_back_duplicates_and_splits_fins():
    # a square (2 triangles) + a fin of two triangles on the diagonal edge (0, 2), plus the
    # first triangle again with reversed winding (a zero-thickness double wall)
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1], [0.5, 0.5, -1]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4], [2, 0, 5], [2, 1, 0]])
    mesh = TriMesh(v, f, "bad")
    with pytest.raises(FormatError, match="non-manifold"):
        check_mesh(mesh)
    fixed, counts = repair_nonmanifold(mesh)
    check_mesh(fixed)
    assert counts["duplicate_triangles_removed"] == 2
    assert counts["triangles_split_off"] >= 1
    # no vertex moved: every repaired vertex is one of the originals
    d = np.linalg.norm(fixed.vertices[:, None] - v[None], axis=2).min(1)
    assert np.all(d == 0)


# --------------------------------------------------------------------------- shared data loaders

def test_scenenet_room_loads_in_z_up_world():
    obj = shared_path("scenenet_room_89", "room_89_simple.obj")
    scene = load_scenenet_room(obj)
    names = [m.name for m in scene.meshes]
    assert len(names) == 21 and len(set(names)) == 21  # 24 objects, 3 of them empty
    for m in scene.meshes:
        check_mesh(m)
    by = {m.name: m for m in scene.meshes}
    assert by["floor_enclose_1"].bounds[:, 2] == pytest.approx([-0.1, -0.1], abs=0.01)
    assert by["ceiling_enclose"].bounds[0, 2] == pytest.approx(2.79, abs=0.01)
    z = by["chair_fx"].vertices[:, 2]
    assert z.min() == pytest.approx(-0.105, abs=0.01) and 0.8 < z.max() < 0.9  # a chair stands up
    assert scene.material_of(by["room_skeleton"]).albedo == pytest.approx(0.8)
    assert np.allclose(SCENENET_TO_WORLD[:3, :3] @ [0, 1, 0], [0, 0, 1])


def test_scenenet_trajectory_is_upright_camera_to_world_inside_room():
    traj = load_scenenet_trajectory(shared_path("scenenet_room_89", "trajectory_random_poses_SE3_3x4.txt"))
    scene = load_scenenet_room(shared_path("scenenet_room_89", "room_89_simple.obj"))
    assert len(traj) == 500
    assert np.allclose(np.diff(traj.timestamps), 1 / 30)
    assert all(is_rigid(T) for T in traj.poses[::25])
    v = np.concatenate([m.vertices for m in scene.meshes])
    lo, hi = v.min(0), v.max(0)
    p = traj.positions
    assert np.all((p > lo) & (p < hi))  # camera centres inside the room
    assert np.all(traj.poses[:, 2, 1] < 0)  # image y (down) points to world -z: upright
    assert np.allclose(traj.poses[:, 2, 0], 0, atol=1e-6)  # no roll: image x is horizontal
    # cross-check with the raw file: t is the centre; the optical axis is +z of SceneNet's T_wc
    raw = np.loadtxt(shared_path("scenenet_room_89", "trajectory_random_poses_SE3_3x4.txt")).reshape(-1, 3, 4)
    assert np.allclose(p, raw[:, :, 3] @ SCENENET_TO_WORLD[:3, :3].T, atol=1e-9)
    assert np.allclose(traj.poses[:, :3, 2], raw[:, :, 2] @ SCENENET_TO_WORLD[:3, :3].T, atol=1e-5)


def test_scenenet_views_see_the_closed_room():
    from data_tools.camera import Intrinsics
    from synth.render import IdealRenderer
    scene = build_scene("scenenet_room", path=str(shared_path("scenenet_room_89", "room_89_simple.obj")))
    traj = load_scenenet_trajectory(shared_path("scenenet_room_89", "trajectory_random_poses_SE3_3x4.txt"))
    r = IdealRenderer(scene)
    intr = Intrinsics(80, 60, 52.5, 52.5, 39.5, 29.5)
    for T in traj.poses[::100]:
        res = r.render(T, intr, with_rgb=False)
        assert res.hit.mean() > 0.99
        assert np.all(res.depth[res.hit] < 8.0)


def test_tless_models_load_in_metres_and_repair():
    m = load_tless_model(shared_path("tless_cad", "obj_01.ply"))
    check_mesh(m)
    assert np.allclose(np.ptp(m.vertices, axis=0), [0.034, 0.034, 0.062], atol=0.002)  # mm -> m
    for obj in ("obj_07.ply", "obj_11.ply"):  # the two non-manifold models
        p = shared_path("tless_cad", obj)
        with pytest.raises(FormatError, match="non-manifold"):
            load_tless_model(p, repair=False)
        fixed = load_tless_model(p)
        check_mesh(fixed)
    scene = build_scene("tless_obj", path=str(shared_path("tless_cad", "obj_05.ply")))
    obj = scene.meshes[1]
    assert obj.name == "obj_05" and obj.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)
