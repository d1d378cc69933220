"""data_tools: geometry round trips, camera/scene/trajectory formats, streaming sequence I/O."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from data_tools.camera import Camera, Intrinsics, SensorSpec, read_camera_json, write_camera_json
from data_tools.errors import FormatError, RealgapError
from data_tools.geometry import (invert_pose, is_rigid, look_at, matrix_to_quat, pose_from_tum,
                                 pose_to_tum, project, quat_to_matrix, unproject)
from data_tools.mesh import TriMesh, check_mesh, save_mesh
from data_tools.scene_spec import Material, SceneSpec, read_scene_json, write_scene_json
from data_tools.sequence import Frame, SequenceReader, SequenceWriter, encode_depth
from data_tools.trajectory import Trajectory, associate, read_tum, write_tum


def random_pose(rng) -> np.ndarray:
    q = rng.normal(size=4)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = rng.normal(size=3)
    return T


# ---------------------------------------------------------------- geometry
def test_quaternion_round_trip_and_known_rotation():
    rng = np.random.default_rng(0)
    for _ in range(50):
        T = random_pose(rng)
        np.testing.assert_allclose(pose_from_tum(pose_to_tum(T)), T, atol=1e-12)
    # 90 deg about z: q = (0, 0, sin 45, cos 45)
    R = quat_to_matrix([0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(matrix_to_quat(R), [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_invert_pose_and_rigidity():
    rng = np.random.default_rng(1)
    T = random_pose(rng)
    np.testing.assert_allclose(invert_pose(T) @ T, np.eye(4), atol=1e-12)
    assert is_rigid(T)
    bad = T.copy()
    bad[0, 0] = np.nan
    assert not is_rigid(bad)


def test_unproject_project_round_trip_on_tiny_depth():
    intr = Intrinsics(4, 3, fx=2.0, fy=2.0, cx=1.5, cy=1.0)
    depth = np.array([[1.0, 2.0, 3.0, 4.0], [0.5, 1.5, 2.5, 3.5], [1.0, 1.0, 1.0, 1.0]])
    pts = unproject(depth, intr)
    # hand computed: pixel (u=0, v=0) at z=1 -> x = (0-1.5)/2 = -0.75, y = (0-1)/2 = -0.5
    np.testing.assert_allclose(pts[0, 0], [-0.75, -0.5, 1.0])
    uv, z = project(pts, intr)
    u, v = np.meshgrid(np.arange(4.0), np.arange(3.0))
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-12)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-12)
    np.testing.assert_allclose(z, depth)


def test_look_at_uses_opencv_axes():
    T = look_at([0, -2, 1], [0, 0, 1])
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)   # z forward
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # y down (world z up)
    assert is_rigid(T)


def test_intrinsics_scaling_keeps_pixel_centres():
    i = Intrinsics(640, 480, 580, 580, 319.5, 239.5)
    h = i.scaled(0.5)
    assert (h.width, h.height) == (320, 240)
    assert h.cx == pytest.approx(159.5) and h.fx == pytest.approx(290)


# ---------------------------------------------------------------- camera.json
def test_camera_json_round_trip(tmp_path):
    cam = Camera(Intrinsics(640, 480, 580, 581, 319.5, 239.5, (0.1, -0.2, 0.001, 0.0, 0.05)), 1000.0,
                 SensorSpec("structured_light", 0.075, (0.075, 0, 0), {"model": "kinect_v1"}))
    write_camera_json(tmp_path / "camera.json", cam)
    back = read_camera_json(tmp_path / "camera.json")
    assert back == cam
    assert back.sensor.extra == {"model": "kinect_v1"}


@pytest.mark.parametrize("content, needle", [
    ({"width": 640, "height": 480, "fx": 580, "fy": 580, "cx": 320}, "missing key(s): cy, depth_scale"),
    ({"width": 640, "height": 480, "fx": 580, "fy": 580, "cx": 320, "cy": 240, "depth_scale": 0}, "depth_scale"),
    ({"width": 640, "height": 480, "fx": -1, "fy": 580, "cx": 320, "cy": 240, "depth_scale": 1}, "focal"),
    ({"width": 640, "height": 480, "fx": 5, "fy": 5, "cx": 3, "cy": 2, "depth_scale": 1,
      "sensor": {"type": "lidar"}}, "sensor.type"),
])
def test_camera_json_errors_name_the_file(tmp_path, content, needle):
    p = tmp_path / "camera.json"
    p.write_text(json.dumps(content))
    with pytest.raises(FormatError) as e:
        read_camera_json(p)
    assert str(p) in str(e.value) and needle in str(e.value)


def test_camera_json_invalid_json(tmp_path):
    p = tmp_path / "camera.json"
    p.write_text("{width: 640")
    with pytest.raises(FormatError, match="not valid JSON"):
        read_camera_json(p)


# ---------------------------------------------------------------- trajectories
def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    traj = Trajectory(np.arange(5) * 0.1 + 100.0, np.stack([random_pose(rng) for _ in range(5)]))
    write_tum(tmp_path / "t.txt", traj)
    back = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-7)


@pytest.mark.parametrize("lines, needle", [
    (["2.0 0 0 0 0 0 0 1", "1.0 0 0 0 0 0 0 1"], "not sorted"),
    (["1.0 0 0 0 0 0 0 1", "1.0 0 0 0 0 0 0 1"], "duplicated timestamp"),
    (["1.0 0 nan 0 0 0 0 1"], "NaN"),
    (["1.0 0 0 0 0 0 0 2"], "not unit length"),
    (["1.0 0 0 0 0 0 1"], "expected 8 values"),
    (["# only a comment"], "no poses"),
])
def test_tum_bad_input(tmp_path, lines, needle):
    p = tmp_path / "traj.txt"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(FormatError) as e:
        read_tum(p, drop_duplicate_timestamps=False)     # strict: a repeated timestamp is an error too
    assert needle in str(e.value) and str(p) in str(e.value)


def test_associate_nearest_unique_within_max_dt():
    a = np.array([0.00, 0.10, 0.20, 0.30])
    b = np.array([0.005, 0.095, 0.11, 0.35])
    ia, ib = associate(a, b, max_dt=0.02)
    # 0.00-0.005, 0.10-0.095 (0.005 beats 0.11's 0.01), 0.30-0.35 too far, 0.20 has none
    assert ia.tolist() == [0, 1] and ib.tolist() == [0, 1]
    ia, ib = associate(a, b, max_dt=0.06)
    assert ia.tolist() == [0, 1, 3] and ib.tolist() == [0, 1, 3]  # 0.11 not reused for 0.20 (0.09 > 0.06)


# ---------------------------------------------------------------- sequences
def _tiny_camera(w=8, h=6, scale=5000.0):
    return Camera(Intrinsics(w, h, 5.0, 5.0, (w - 1) / 2, (h - 1) / 2), scale, None)


def _frames(n, cam, rng):
    h, w = cam.intrinsics.shape
    out = []
    for k in range(n):
        depth = rng.uniform(0.5, 4.0, size=(h, w)).astype(np.float32)
        depth[0, 0] = 0.0  # an invalid pixel
        depth = np.round(depth * cam.depth_scale) / cam.depth_scale
        rgb = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        out.append(Frame(1.0 + k / 30.0, depth.astype(np.float32), rgb, random_pose(rng)))
    return out


def _box(name="box", size=1.0, offset=(0, 0, 0)) -> TriMesh:
    import trimesh
    b = trimesh.creation.box((size, size, size))
    return TriMesh(np.asarray(b.vertices) + offset, np.asarray(b.faces), name, "wood")


def test_sequence_write_read_identical(tmp_path):
    rng = np.random.default_rng(3)
    cam = _tiny_camera()
    frames = _frames(4, cam, rng)
    scene = SceneSpec([_box()], {"wood": Material(0.45, 0.1, {"ior": 1.5})})
    with SequenceWriter(tmp_path / "seq", cam, scene) as w:
        for f in frames:
            w.write(f)
    seq = SequenceReader(tmp_path / "seq")
    assert len(seq) == 4 and seq.camera == cam
    for f, g in zip(frames, seq):
        np.testing.assert_array_equal(g.depth, f.depth)   # exact: values were on the depth grid
        np.testing.assert_array_equal(g.rgb, f.rgb)
        np.testing.assert_allclose(g.pose, f.pose, atol=1e-7)
        assert g.timestamp == pytest.approx(f.timestamp, abs=1e-6)
    sc = seq.scene
    assert len(sc.meshes) == 1 and sc.meshes[0].material == "wood"
    assert sc.materials["wood"].albedo == 0.45 and sc.materials["wood"].extra == {"ior": 1.5}
    np.testing.assert_allclose(sc.meshes[0].vertices, scene.meshes[0].vertices, atol=1e-6)


def test_sequence_resume_keeps_written_frames(tmp_path):
    rng = np.random.default_rng(4)
    cam = _tiny_camera()
    frames = _frames(5, cam, rng)
    w = SequenceWriter(tmp_path / "seq", cam)
    for f in frames[:3]:
        w.write(f)
    # simulate a crash after rgb.txt/groundtruth.txt got frame 4 but depth.txt did not
    t = f"{frames[3].timestamp:.6f}"
    with open(tmp_path / "seq" / "rgb.txt", "a") as fh:
        fh.write(f"{t} rgb/{t}.png\n")
    with pytest.raises(RealgapError, match="already holds a sequence"):
        SequenceWriter(tmp_path / "seq", cam)
    w2 = SequenceWriter(tmp_path / "seq", cam, resume=True)
    assert len(w2) == 3
    for f in frames[3:]:
        w2.write(f)
    seq = SequenceReader(tmp_path / "seq")
    assert len(seq) == 5
    np.testing.assert_array_equal(seq[4].depth, frames[4].depth)


def test_encode_depth_handles_nan_and_range():
    d = np.array([[np.nan, -1.0, 0.0, 1.0, 20.0]])
    assert encode_depth(d, 5000).tolist() == [[0, 0, 0, 5000, 0]]


def _write_tiny_seq(tmp_path):
    rng = np.random.default_rng(5)
    cam = _tiny_camera()
    with SequenceWriter(tmp_path / "seq", cam) as w:
        for f in _frames(3, cam, rng):
            w.write(f)
    return tmp_path / "seq"


def test_bad_depth_png_8bit(tmp_path):
    seq = _write_tiny_seq(tmp_path)
    first = (seq / "depth.txt").read_text().splitlines()[2].split()[1]
    cv2.imwrite(str(seq / first), np.zeros((6, 8), np.uint8))
    with pytest.raises(FormatError, match="must be 16-bit") as e:
        SequenceReader(seq)[0]
    assert first in str(e.value)


def test_bad_depth_png_corrupt(tmp_path):
    seq = _write_tiny_seq(tmp_path)
    first = (seq / "depth.txt").read_text().splitlines()[2].split()[1]
    (seq / first).write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(FormatError, match="cannot decode"):
        SequenceReader(seq)[0]


def test_missing_file_listed_in_depth_txt(tmp_path):
    seq = _write_tiny_seq(tmp_path)
    with open(seq / "depth.txt", "a") as f:
        f.write("9.0 depth/nothere.png\n")
    with pytest.raises(FormatError, match="nothere.png"):
        SequenceReader(seq)


def test_unsorted_depth_txt(tmp_path):
    seq = _write_tiny_seq(tmp_path)
    lines = (seq / "depth.txt").read_text().splitlines()
    (seq / "depth.txt").write_text("\n".join(lines[:2] + lines[2:][::-1]) + "\n")
    with pytest.raises(FormatError, match="not sorted") as e:
        SequenceReader(seq)
    assert "depth.txt" in str(e.value)


def test_nan_pose_in_groundtruth(tmp_path):
    seq = _write_tiny_seq(tmp_path)
    lines = (seq / "groundtruth.txt").read_text().splitlines()
    parts = lines[-1].split()
    parts[2] = "nan"
    (seq / "groundtruth.txt").write_text("\n".join(lines[:-1] + [" ".join(parts)]) + "\n")
    with pytest.raises(FormatError, match="NaN"):
        SequenceReader(seq)


def test_depth_size_mismatch_with_camera(tmp_path):
    seq = _write_tiny_seq(tmp_path)
    cam = json.loads((seq / "camera.json").read_text())
    cam["width"] = 10
    (seq / "camera.json").write_text(json.dumps(cam))
    with pytest.raises(FormatError, match="camera says 10x6"):
        SequenceReader(seq)[0]


def test_default_camera_without_camera_json(tmp_path):
    seq = _write_tiny_seq(tmp_path)
    (seq / "camera.json").unlink()
    r = SequenceReader(seq)
    assert r.camera == Camera.tum_default() and not r.has_camera_json


# ---------------------------------------------------------------- meshes / scene.json
def test_empty_mesh_rejected(tmp_path):
    import trimesh
    trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)).export(tmp_path / "empty.ply")
    (tmp_path / "scene.json").write_text(json.dumps({"meshes": [{"file": "empty.ply"}]}))
    with pytest.raises(FormatError, match="empty"):
        read_scene_json(tmp_path / "scene.json")


def test_non_manifold_mesh_rejected(tmp_path):
    # three triangles sharing the edge (0, 1): a "book" with three pages
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(FormatError, match="non-manifold"):
        check_mesh(TriMesh(v, f, "book"))
    save_mesh(tmp_path / "book.ply", TriMesh(v, f, "book"))
    (tmp_path / "scene.json").write_text(json.dumps({"meshes": [{"file": "book.ply"}]}))
    with pytest.raises(FormatError, match="non-manifold") as e:
        read_scene_json(tmp_path / "scene.json")
    assert "book.ply" in str(e.value)


def test_scene_json_unknown_material_and_keys(tmp_path):
    save_mesh(tmp_path / "b.ply", _box())
    (tmp_path / "scene.json").write_text(json.dumps({"meshes": [{"file": "b.ply", "material": "gold"}]}))
    with pytest.raises(FormatError, match="'gold'"):
        read_scene_json(tmp_path / "scene.json")
    (tmp_path / "scene.json").write_text(json.dumps({
        "meshes": [{"file": "b.ply", "material": "gold"}],
        "materials": {"gold": {"albedo": 0.9, "specular": 0.8, "roughness": 0.1}}}))
    sc = read_scene_json(tmp_path / "scene.json")
    assert sc.materials["gold"].extra == {"roughness": 0.1}


def test_scene_json_round_trip_units(tmp_path):
    scene = SceneSpec([_box("a"), _box("b", 0.5, (2, 0, 0))], {"wood": Material(0.4, 0.0)})
    write_scene_json(tmp_path, scene)
    back = read_scene_json(tmp_path / "scene.json")
    assert [m.name for m in back.meshes] == ["a", "b"]
    np.testing.assert_allclose(back.meshes[1].bounds, [[1.75, -0.25, -0.25], [2.25, 0.25, 0.25]], atol=1e-9)


def test_progress_is_whole_lines_when_not_a_terminal(capsys, monkeypatch):
    import data_tools.progress as P
    from data_tools.progress import LineProgress, progress_bar
    # fast work on a log: the first and the last line only (lines at most every LINE_MIN_SECONDS)
    fast = progress_bar(total=50, desc="fast", unit="frame")
    for _ in range(50):
        fast.update(1)
    fast.close()
    assert len(capsys.readouterr().err.splitlines()) == 2
    monkeypatch.setattr(P, "LINE_MIN_SECONDS", 0.0)
    bar = progress_bar(total=20, desc="job", unit="frame")      # pytest's stderr is not a terminal
    assert isinstance(bar, LineProgress)
    for _ in range(20):
        bar.update(1)
    bar.set_postfix_str("1 cut")
    bar.close()
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert "\r" not in err and lines[0] == "job: 0/20 frame" and len(lines) == 1 + 10 + 1
    assert lines[-1].startswith("job: 20/20 frame done") and lines[-1].endswith("[1 cut]")
    assert list(progress_bar(range(3), desc="it", initial=2)) == [0, 1, 2]
    assert capsys.readouterr().err.splitlines()[-1].startswith("it: 5/5 it done")
    list(progress_bar(range(3), desc="quiet", enabled=False))
    assert capsys.readouterr().err == ""


def test_canonical_mesh_ignores_vertex_and_triangle_order():
    """Two orderings of one surface (shuffled vertices, shuffled and rotated triangles) give the
    identical canonical mesh, with each triangle's winding kept."""
    import trimesh

    from data_tools.mesh import TriMesh
    box = trimesh.creation.icosphere(subdivisions=1)
    a = TriMesh(box.vertices, box.faces, vertex_colors=np.abs(box.vertices))
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(box.vertices))
    inv = np.argsort(perm)
    tri = inv[box.faces][rng.permutation(len(box.faces))]
    tri = np.roll(tri, 1, axis=1)                   # same winding, another first corner
    b = TriMesh(box.vertices[perm], tri, vertex_colors=np.abs(box.vertices[perm]))
    ca, cb = a.canonical(), b.canonical()
    np.testing.assert_array_equal(ca.vertices, cb.vertices)
    np.testing.assert_array_equal(ca.triangles, cb.triangles)
    np.testing.assert_array_equal(ca.vertex_colors, cb.vertex_colors)
    # the same triangles with the same outward normals
    n0 = trimesh.Trimesh(a.vertices, a.triangles, process=False).face_normals
    n1 = trimesh.Trimesh(ca.vertices, ca.triangles, process=False).face_normals
    np.testing.assert_allclose(np.sort(n0, axis=0), np.sort(n1, axis=0), atol=1e-12)


def test_canonical_mesh_merges_vertices_at_the_same_position():
    """Two squares whose shared edge has its two vertices emitted twice (as marching cubes does
    where blocks meet), listed in either order: one canonical mesh, with 6 vertices, not 8."""
    from data_tools.mesh import TriMesh
    P = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0]], float)
    T = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    perm = np.array([4, 7, 5, 6, 0, 1, 2, 3])          # the duplicates come first here
    inv = np.argsort(perm)
    a = TriMesh(P, T).canonical()
    b = TriMesh(P[perm], inv[T]).canonical()
    assert len(a.vertices) == 6
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)
