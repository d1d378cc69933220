"""IdealRenderer: hand-computable planes, round trips against the meshes, rays and shadow rays."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError
from data_tools.geometry import invert_pose, look_at, transform_points, unproject
from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material, SceneSpec
from synth.render import IdealRenderer, pinhole_ray_dirs, shade_rgb
from synth.scenes import build_scene

# small, deliberately non-square camera with an off-centre principal point
INTR = Intrinsics(48, 36, 40.0, 44.0, 22.3, 16.8)


def _quad(z: float, half: float, name: str, material: str = "m", slope_x: float = 0.0,
          color=None) -> TriMesh:
    """Square |x|, |y| <= half on the plane z = z + slope_x * x."""
    xy = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    v = np.c_[xy, z + slope_x * xy[:, 0]]
    vc = None if color is None else np.tile(color, (4, 1))
    return TriMesh(v, [[0, 1, 2], [0, 2, 3]], name, material, vc)


def _plane_scene(z=2.0, slope_x=0.0) -> SceneSpec:
    # a dummy mesh first so that the plane's instance id is 2
    dummy = _quad(-5.0, 0.1, "dummy_behind", "d")
    return SceneSpec([dummy, _quad(z, 3.0, "plane", "m", slope_x)],
                     {"m": Material(0.6, 0.2), "d": Material(0.1, 0.9)})


def test_ray_directions_follow_pixel_centre_convention():
    d = pinhole_ray_dirs(INTR)
    assert d.shape == (36, 48, 3) and d.dtype == np.float32
    assert np.allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-6)
    u, v = 7, 30
    ref = np.array([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, 1.0])
    assert np.allclose(d[v, u], ref / np.linalg.norm(ref), atol=1e-7)


def test_fronto_parallel_plane_gives_exact_depth_ids_normals_points():
    r = IdealRenderer(_plane_scene(z=2.0))
    res = r.render(np.eye(4), INTR)
    assert res.hit.all()
    assert np.allclose(res.depth, 2.0, atol=1e-6)
    assert np.all(res.instance_ids == 2)
    assert np.allclose(res.normals_cam, [0.0, 0.0, -1.0], atol=1e-6)
    u, v = np.meshgrid(np.arange(48), np.arange(36))
    assert np.allclose(res.points_world[..., 0], (u - INTR.cx) / INTR.fx * 2.0, atol=1e-5)
    assert np.allclose(res.points_world[..., 1], (v - INTR.cy) / INTR.fy * 2.0, atol=1e-5)
    assert np.allclose(res.t_hit, 2.0 / res.ray_dirs_cam[..., 2], rtol=1e-6)
    assert np.allclose(res.points_cam, res.points_world, atol=1e-6)  # identity pose
    albedo, spec = r.albedo_specular(res.instance_ids)
    assert np.all(albedo == np.float32(0.6)) and np.all(spec == np.float32(0.2))


def test_tilted_plane_depth_and_normal_match_closed_form():
    # plane z = 2 + 0.5 x; along pixel ray x = a z with a = (u - cx) / fx: z = 2 / (1 - 0.5 a)
    r = IdealRenderer(_plane_scene(z=2.0, slope_x=0.5))
    res = r.render(np.eye(4), INTR)
    a = (np.arange(48) - INTR.cx) / INTR.fx
    expected = np.broadcast_to(2.0 / (1 - 0.5 * a), (36, 48))
    assert np.allclose(res.depth, expected, rtol=2e-6)
    n = np.array([0.5, 0.0, -1.0]) / np.linalg.norm([0.5, 0.0, -1.0])
    assert np.allclose(res.normals_cam, n, atol=1e-6)


def test_partial_plane_hits_only_inside_its_edges():
    scene = SceneSpec([_quad(2.0, 0.25, "small")], {"m": Material()})
    res = IdealRenderer(scene).render(np.eye(4), INTR)
    x = (np.arange(48) - INTR.cx) / INTR.fx * 2.0
    y = (np.arange(36) - INTR.cy) / INTR.fy * 2.0
    inside = (np.abs(x)[None, :] < 0.25 - 1e-3) & (np.abs(y)[:, None] < 0.25 - 1e-3)
    outside = (np.abs(x)[None, :] > 0.25 + 1e-3) | (np.abs(y)[:, None] > 0.25 + 1e-3)
    assert res.hit[inside].all() and not res.hit[outside].any()
    assert np.all(res.depth[~res.hit] == 0) and np.all(np.isinf(res.t_hit[~res.hit]))
    assert np.all(res.instance_ids[~res.hit] == 0) and np.all(res.points_world[~res.hit] == 0)
    assert np.all(res.rgb[~res.hit] == 0) and np.all(res.normals_cam[~res.hit] == 0)


def test_rendering_is_invariant_to_moving_camera_and_scene_together():
    scene = build_scene("chair_b")
    T = look_at([1.5, -1.2, 1.1], [0.0, 0.0, 0.5])
    moved = SceneSpec([m.transformed(np.linalg.inv(T)) for m in scene.meshes], scene.materials)
    a = IdealRenderer(scene).render(T, INTR)
    b = IdealRenderer(moved).render(np.eye(4), INTR)
    same = a.hit & b.hit
    assert same.sum() > 0.98 * max(a.hit.sum(), b.hit.sum())  # only edge pixels may flip
    assert np.allclose(a.depth[same], b.depth[same], atol=1e-4)
    agree = a.instance_ids[same] == b.instance_ids[same]
    assert agree.mean() > 0.98
    assert np.allclose(a.normals_cam[same][agree], b.normals_cam[same][agree], atol=1e-3)


def test_room_depth_round_trip_lies_on_the_meshes():
    import open3d as o3d
    scene = build_scene("room")
    r = IdealRenderer(scene)
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    T = look_at([-1.8, -1.5, 1.5], [0.5, 0.5, 0.7])
    res = r.render(T, intr)
    assert res.hit.all()  # a closed room
    assert len(np.unique(res.instance_ids)) >= 8  # furnished
    pts = transform_points(T, unproject(res.depth, intr)[res.hit])
    assert np.allclose(pts, res.points_world[res.hit], atol=1e-4)
    dist = r.raycasting_scene.compute_distance(o3d.core.Tensor(pts[::7].astype(np.float32))).numpy()
    assert dist.mean() < 1e-3 and np.percentile(dist, 99) < 1e-3
    # and z-depth = t_hit * ray_z
    assert np.allclose(res.depth, res.t_hit * res.ray_dirs_cam[..., 2], rtol=1e-6)
    # camera-frame points agree with the world points
    back = transform_points(invert_pose(T), res.points_world[res.hit].astype(np.float64))
    assert np.allclose(back, res.points_cam[res.hit], atol=1e-4)


def test_vertex_colours_are_interpolated_and_shaded():
    tri = TriMesh([[-1, -1, 2], [1, -1, 2], [-1, 1, 2]], [[0, 1, 2]], "t", "m", np.eye(3))
    intr = Intrinsics(64, 64, 32, 32, 31.5, 31.5)
    res = IdealRenderer(SceneSpec([tri], {"m": Material(0.5, 0.0)})).render(np.eye(4), intr)
    # pixels near each corner are dominated by that corner's colour (red, green, blue)
    for (v, u), ch in (((17, 17), 0), ((17, 44), 1), ((44, 17), 2)):
        assert np.argmax(res.rgb[v, u]) == ch and res.rgb[v, u, ch] > 150
    # exact value at a pixel: base colour from barycentric weights times the Lambert factor
    v, u = 20, 22
    p = res.points_world[v, u]
    w1, w2 = (p[0] + 1) / 2, (p[1] + 1) / 2
    base = np.array([1 - w1 - w2, w1, w2])
    expected = shade_rgb(base[None], res.normals_cam[v, u][None], res.ray_dirs_cam[v, u][None],
                         np.array([True]))[0]
    assert np.all(np.abs(res.rgb[v, u].astype(int) - expected.astype(int)) <= 1)
    # a mesh without vertex colours is shaded grey with its albedo
    grey = TriMesh(tri.vertices, tri.triangles, "g", "m")
    res2 = IdealRenderer(SceneSpec([grey], {"m": Material(0.5, 0.0)})).render(np.eye(4), intr)
    c = res2.rgb[20, 22].astype(int)
    assert c[0] == c[1] == c[2] and 100 < c[0] < 130  # 0.5 * 255 * (0.3 + 0.7 cos), cos ~ 0.9


def test_render_without_rgb_and_empty_views():
    r = IdealRenderer(_plane_scene())
    res = r.render(np.eye(4), INTR, with_rgb=False)
    assert res.rgb is None and res.hit.all()
    away = look_at([0, 0, 0], [0, 0, -10], up=(0, 1, 0))  # looks away from the plane at z = 2
    away_scene = SceneSpec([_quad(2.0, 3.0, "plane")], {"m": Material()})
    res = IdealRenderer(away_scene).render(away, INTR)
    assert not res.hit.any() and np.all(res.depth == 0) and np.all(res.rgb == 0)
    with pytest.raises(RealgapError):
        r.render(np.full((4, 4), np.nan), INTR)


def test_cast_rays_and_occlusion_queries():
    r = IdealRenderer(_plane_scene(z=2.0))
    o = np.zeros((3, 3))
    d = np.array([[0, 0, 5.0], [0.3, 0, 1.0], [0, 0, -1.0]])  # unnormalised on purpose
    out = r.cast_rays(o, d)
    assert out["t_hit"][0] == pytest.approx(2.0, abs=1e-6)
    assert out["t_hit"][1] == pytest.approx(2.0 * np.sqrt(1 + 0.09), abs=1e-5)
    assert out["t_hit"][2] == pytest.approx(5.0, abs=1e-6)  # the dummy behind at z = -5
    assert list(out["instance_ids"]) == [2, 2, 1]
    assert np.allclose(out["normals_world"][0], [0, 0, -1]) and np.allclose(out["normals_world"][2], [0, 0, 1])
    assert np.allclose(out["points_world"][1], [0.6, 0, 2.0], atol=1e-5)
    miss = r.cast_rays([[0, 0, 0]], [[1, 0, 0]])
    assert np.isinf(miss["t_hit"][0]) and miss["instance_ids"][0] == 0
    assert np.all(miss["normals_world"] == 0)
    # shadow rays: through the plane -> occluded; ending on it or before it -> not
    origins = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0.5, 0.2, 1.0], [0, 0, 0]], float)
    targets = np.array([[0, 0, 3.0], [0.2, 0.1, 2.0], [0, 0, 1.9], [0.5, 0.2, 1.0], [1.0, 0, 2.5]])
    occ = r.occluded(origins, targets)
    assert occ.tolist() == [True, False, False, False, True]
    # rendered surface points are visible from a projector 7.5 cm beside the camera
    res = r.render(np.eye(4), INTR)
    pts = res.points_world.reshape(-1, 3)
    proj = np.tile([0.075, 0.0, 0.0], (len(pts), 1))
    assert not r.occluded(proj, pts).any()
    assert not r.occluded(pts, proj).any()  # and the reverse: shadow rays leaving the surface
    with pytest.raises(RealgapError):
        r.albedo_specular(np.array([3]))
    a, s = r.albedo_specular(np.array([[0, 1], [2, 2]]))
    assert a.shape == (2, 2) and a[0, 0] == 0 and a[0, 1] == np.float32(0.1) and s[0, 1] == np.float32(0.9)


def test_occlusion_by_an_object_between_projector_and_wall():
    # a wall at z = 3 and a small box-like quad at z = 1.5 covering x in [-0.25, 0.25]
    wall = _quad(3.0, 3.0, "wall")
    blocker = _quad(1.5, 0.25, "blocker")
    r = IdealRenderer(SceneSpec([wall, blocker], {"m": Material()}))
    proj = np.array([[0.0, 0.0, 0.0]] * 3)
    targets = np.array([[0.0, 0.0, 3.0], [0.4, 0.0, 3.0], [1.0, 0.0, 3.0]])
    assert r.occluded(proj, targets).tolist() == [True, True, False]  # shadow reaches x = 0.5 at z = 3
