"""synth.raster: the rasteriser back-end of IdealRenderer against Open3D's ray cast (the
reference), on hand-made cases where the rasteriser's shortcuts could go wrong (triangles
crossing the camera plane, edge-on triangles, the camera inside a box) and on the room."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError
from data_tools.geometry import look_at
from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material, SceneSpec
from synth.render.raster import Rasterizer
from synth.render import IdealRenderer
from synth.scenes import build_scene
from synth.trajectories import make_trajectory

INTR = Intrinsics(64, 48, 50.0, 52.0, 31.2, 24.7)


def _scene(*meshes: TriMesh) -> SceneSpec:
    return SceneSpec(list(meshes), {"m": Material(0.5, 0.0)})


def _compare(scene: SceneSpec, poses, intr: Intrinsics, max_edge_px: int = 0) -> None:
    """Raster and ray cast agree: same hit mask, ids and normals (up to ``max_edge_px``
    pixels per view on edges through pixel centres), depth to 1e-5 relative."""
    ras, ref = IdealRenderer(scene, backend="raster"), IdealRenderer(scene, backend="raycast")
    assert ras.backend == "raster" and ref.backend == "raycast"
    for T in poses:
        a, b = ras.render(T, intr, with_rgb=True), ref.render(T, intr, with_rgb=True)
        differ = (a.hit != b.hit) | (a.instance_ids != b.instance_ids)
        both = a.hit & b.hit
        differ |= both & (np.abs(a.normals_cam - b.normals_cam).max(axis=-1) > 1e-4)
        assert int(differ.sum()) <= max_edge_px
        ok = both & ~differ
        assert np.allclose(a.depth[ok], b.depth[ok], rtol=1e-5, atol=1e-6)
        assert np.allclose(a.t_hit[ok], b.t_hit[ok], rtol=1e-5, atol=1e-6)
        assert np.allclose(a.points_world[ok], b.points_world[ok], atol=1e-5)
        assert np.all(a.depth[~a.hit] == 0) and np.all(np.isinf(a.t_hit[~a.hit]))
        assert np.all(a.normals_cam[~a.hit] == 0) and np.all(a.instance_ids[~a.hit] == 0)
        # vertex colours at the barycentric weights: within one grey level of the reference
        assert np.abs(a.rgb[ok].astype(int) - b.rgb[ok].astype(int)).max(initial=0) <= 1


def test_triangle_crossing_the_camera_plane_is_covered_exactly():
    # one big triangle with a corner behind the camera (z < 0) and two in front: a projection
    # of the corners would wrap around; the homogeneous test must not
    tri = TriMesh(np.array([[0.0, 1.0, -2.0], [-3.0, 1.0, 4.0], [3.0, 1.0, 4.0]]), [[0, 1, 2]], "floor", "m")
    T = np.eye(4)
    res = IdealRenderer(_scene(tri)).render(T, INTR)
    # the floor y = 1 is below the camera: hits exactly in the lower image rows, at z = 1 / y_n
    v = np.arange(INTR.height)
    yn = (v - INTR.cy) / INTR.fy
    rows_hit = res.hit.any(axis=1)
    assert not rows_hit[yn <= 0].any() and rows_hit[yn > 0.3].all()
    vv, uu = np.nonzero(res.hit)
    assert np.allclose(res.depth[vv, uu], 1.0 / yn[vv], rtol=1e-6)
    _compare(_scene(tri), [T, look_at([0.2, 0.1, 0.0], [0.0, 0.9, 3.0])], INTR)


def test_edge_on_triangle_and_triangle_behind_give_no_hits():
    edge_on = TriMesh(np.array([[0.0, -1.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 3.0]]), [[0, 1, 2]], "edge", "m")
    behind = TriMesh(np.array([[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [0.0, 1.0, -1.0]]), [[0, 1, 2]], "b", "m")
    # the edge-on triangle lies in the plane x = 0, which contains the camera centre
    intr = Intrinsics(16, 12, 10.0, 10.0, 7.5, 5.5)  # no pixel centre on x = 0
    for m in (edge_on, behind):
        assert not IdealRenderer(_scene(m)).render(np.eye(4), intr).hit.any()


def test_camera_inside_a_box_every_wall_crosses_the_view():
    V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    F = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    box = TriMesh(V, F, "box", "m")
    rng = np.random.default_rng(4)
    poses = [look_at(rng.uniform(-0.6, 0.6, 3), rng.uniform(-3, 3, 3)) for _ in range(6)]
    res = IdealRenderer(_scene(box)).render(poses[0], INTR)
    assert res.hit.all()  # closed box around the camera
    _compare(_scene(box), poses, INTR, max_edge_px=2)


def test_room_matches_the_ray_cast_from_walkthrough_and_random_poses():
    scene = build_scene("room", seed=0)
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    traj = make_trajectory("walkthrough", scene, 6, seed=1)
    rng = np.random.default_rng(0)
    lo, hi = np.min([m.vertices.min(0) for m in scene.meshes], 0), np.max([m.vertices.max(0) for m in scene.meshes], 0)
    rand = [look_at(rng.uniform(lo + 0.3, hi - 0.3), rng.uniform(lo, hi)) for _ in range(6)]
    _compare(scene, list(traj.poses) + rand, intr, max_edge_px=3)


def test_thread_bands_give_identical_images():
    scene = build_scene("room", seed=0)
    ras = Rasterizer([(m.vertices, m.triangles) for m in scene.meshes])
    intr = Intrinsics(96, 72, 88.0, 88.0, 47.5, 35.5)
    T = make_trajectory("walkthrough", scene, 3, seed=0).poses[1]
    dz = IdealRenderer(scene).ray_dirs_cam(intr)[..., 2]
    one = ras.render(T, intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height, dz, with_uv=True, n_threads=1)
    three = ras.render(T, intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height, dz, with_uv=True, n_threads=3)
    assert one.keys() == three.keys()
    for k in one:
        assert np.array_equal(one[k], three[k]), k


def test_unknown_backend_is_refused():
    with pytest.raises(RealgapError, match="backend"):
        IdealRenderer(build_scene("room", seed=0), backend="opengl")


def test_rows_with_their_own_poses_match_a_per_row_ray_cast():
    """Rolling shutter / sub-exposure views (synth.sensor.state.cast_view): the rasterised
    bands see the same surfaces as one Open3D ray per pixel except at silhouettes (bands keep
    the image motion below 0.1 px), and depth is exact per row everywhere else."""
    from synth.sensor.effects.rolling_shutter import row_times_frames
    from synth.sensor.state import cast_view, interpolate_pose
    scene = build_scene("room", seed=0)
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    traj = make_trajectory("walkthrough", scene, 40, seed=0)
    ras, ref = IdealRenderer(scene), IdealRenderer(scene, backend="raycast")
    s = row_times_frames(intr.height, 0.03, 1 / 30)
    for i, speed_up in ((5, 1.0), (20, 8.0), (33, 30.0)):  # up to ~1 m and 0.5 rad per frame period
        rows = interpolate_pose(traj.poses[i], traj.poses[i - 1], s * speed_up)
        a = cast_view(ras, ras.ray_dirs_cam(intr), rows)
        b = cast_view(ref, ref.ray_dirs_cam(intr), rows)
        differ = (a.hit != b.hit) | (a.instance_ids != b.instance_ids)
        both = a.hit & b.hit & ~differ
        differ |= both & (np.abs(a.normals_cam - b.normals_cam).max(axis=-1) > 1e-4)
        assert differ.mean() < 5e-4, differ.sum()
        ok = both & ~differ
        np.testing.assert_allclose(a.depth[ok], b.depth[ok], rtol=1e-5)
        np.testing.assert_allclose(a.points_world[ok], b.points_world[ok], atol=1e-5)
        np.testing.assert_allclose(a.points_cam[ok], b.points_cam[ok], atol=1e-5)
        np.testing.assert_allclose(a.row_c2w, b.row_c2w, atol=1e-6)  # (the ray cast keeps float32 origins)
    # all rows at one pose: exactly the single-pose render
    T = traj.poses[7]
    a = cast_view(ras, ras.ray_dirs_cam(intr), T)
    r = ras.render(T, intr, with_rgb=False)
    np.testing.assert_array_equal(a.hit, r.hit)
    np.testing.assert_allclose(a.depth, r.depth, rtol=1e-6)


def _render_in_child(q) -> None:
    import synth.jit as R
    R.THREADS = 2
    scene = build_scene("room", seed=0)
    res = IdealRenderer(scene).render(make_trajectory("walkthrough", scene, 2, seed=0).poses[0], INTR)
    q.put(int(res.hit.sum()))


def test_thread_bands_work_in_a_forked_child():
    """The shared band thread pool is rebuilt after a fork (a forked child has no threads)."""
    import multiprocessing as mp

    import synth.jit as R
    scene = build_scene("room", seed=0)
    R_old, R.THREADS = R.THREADS, 2
    try:
        want = int(IdealRenderer(scene).render(make_trajectory("walkthrough", scene, 2, seed=0).poses[0], INTR)
                   .hit.sum())  # the parent's pool now exists
    finally:
        R.THREADS = R_old
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_render_in_child, args=(q,))
    p.start()
    p.join(60)
    alive = p.is_alive()
    if alive:
        p.kill()
    assert not alive, "render in a forked child hung"
    assert p.exitcode == 0 and q.get(timeout=5) == want


def test_rows_with_their_own_poses_do_not_depend_on_threads_or_the_middle_pose():
    """render_rows: the visibility bands are one grid over the image (1, 2 or 3 threads give
    the same image, also when the band height does not divide the threads' 16-row blocks), and
    a triangle seen edge-on from the middle row's pose is still drawn in the other rows."""
    from synth.sensor.effects.rolling_shutter import row_times_frames
    from synth.sensor.state import interpolate_pose
    W, H, f, cx, cy = 64, 48, 50.0, 31.5, 23.5
    d = np.stack(np.meshgrid((np.arange(W) - cx) / f, (np.arange(H) - cy) / f), -1)
    dz = (1 / np.sqrt(1 + (d ** 2).sum(-1))).astype(np.float32)
    # a plane x = 0 through the camera centre at the middle row only (camera slides along x)
    V = np.array([[0, -1, 1.0], [0, 1, 1.0], [0, 0, 3.0], [0, -1, 3.0]])
    r = Rasterizer([(V, np.array([[0, 1, 2], [0, 2, 3]]))])
    rows = np.tile(np.eye(4), (H, 1, 1))
    rows[:, 0, 3] = np.linspace(-0.05, 0.05, H)
    rows[H // 2, 0, 3] = 0.0
    ref = np.stack([r.render(rows[v], f, f, cx, cy, W, H, dz)["hit"][v] for v in range(H)])
    got = r.render_rows(rows, f, f, cx, cy, W, H, dz)["hit"]
    assert ref.sum() > 20 and np.array_equal(got, ref)
    # the room with band heights 5-12 rows: identical for 1, 2 and 3 threads
    scene = build_scene("room", seed=0)
    ras = Rasterizer([(m.vertices, m.triangles) for m in scene.meshes])
    traj = make_trajectory("walkthrough", scene, 30, seed=0)
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    dz2 = IdealRenderer(scene).ray_dirs_cam(intr)[..., 2]
    s = row_times_frames(intr.height, 0.03, 1 / 30)
    for i, k in ((5, 0.15), (12, 0.1), (20, 0.05)):
        rows = interpolate_pose(traj.poses[i], traj.poses[i - 1], s * k)
        outs = [ras.render_rows(rows, intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height, dz2, n_threads=n)
                for n in (1, 2, 3)]
        for o in outs[1:]:
            for key in ("triangle", "depth", "normals_cam"):
                np.testing.assert_array_equal(o[key], outs[0][key])
