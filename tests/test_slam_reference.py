"""slam.reference: a reference mesh fused from a sequence at its ground-truth poses.

Cross-check: fusing the ideal depth of a known synthetic scene must give back that scene's
surface (within a fraction of a voxel), and the written scene.json must render the same depth
as the original scene.
"""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from data_tools.errors import FormatError
from data_tools.mesh import TriMesh, check_mesh
from data_tools.sequence import SequenceReader
from slam.reference import (NAMED_CAMERAS, ReferenceConfig, clean_mesh, fuse_reference, make_reference,
                            named_camera)
from slam.tsdf import TSDFConfig

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ideal_seq(tmp_path_factory) -> Path:
    """8 ideal (noise-free) 160x120 frames of the built-in room."""
    from synth.sequence import SEQUENCE_PRESETS, generate_sequence
    cfg = replace(SEQUENCE_PRESETS["kinect_v1"], frames=8, seed=1).with_resolution(160, 120)
    out = tmp_path_factory.mktemp("ref") / "room"
    generate_sequence(cfg, out, progress=False)
    return out


def test_clean_mesh_drops_non_manifold_degenerate_and_small_pieces():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1],   # fan of 3 on edge 0-1
                  [5, 5, 5], [6, 5, 5], [5, 6, 5]], float)                    # a separate triangle
    t = np.array([[0, 1, 2], [0, 1, 3], [1, 0, 4], [0, 1, 2], [2, 2, 1], [5, 6, 7]], np.int32)
    with pytest.raises(FormatError):
        check_mesh(TriMesh(v, t))
    m, dropped = clean_mesh(TriMesh(v, t, name="x", material="m"))
    # duplicate + degenerate go first; the 3 triangles on edge 0-1 all touch it -> dropped
    assert m.triangles.shape == (1, 3) and dropped == 5
    np.testing.assert_allclose(m.vertices[m.triangles[0]], v[[5, 6, 7]])
    assert m.name == "x" and m.material == "m"
    # a clean strip of 2 triangles survives; min_component removes it when asked
    strip = TriMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float),
                    np.array([[0, 1, 2], [1, 3, 2]], np.int32))
    assert clean_mesh(strip)[1] == 0
    assert clean_mesh(strip, min_component_triangles=3)[0].triangles.shape == (0, 3)


def test_fused_reference_matches_the_true_scene(ideal_seq):
    """Fused ideal depth -> mesh within ~half a voxel of the true surfaces; renders agree."""
    from synth.render import IdealRenderer
    seq = SequenceReader(ideal_seq)
    cfg = ReferenceConfig(tsdf=TSDFConfig(voxel_size_m=0.02, integrate_color=False, depth_max_m=6.0),
                          min_component_triangles=50)
    res = fuse_reference(seq, cfg)
    assert res.frames_fused == 8 and res.frames_without_pose == 0
    check_mesh(res.mesh)
    truth = seq.scene
    import open3d as o3d
    scene = o3d.t.geometry.RaycastingScene()
    for m in truth.meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m.to_open3d()))
    d = scene.compute_distance(o3d.core.Tensor(res.mesh.vertices.astype(np.float32))).numpy()
    assert np.median(d) < 0.25 * 0.02 and np.percentile(d, 95) < 0.02
    # the reference renders like the truth where both see a surface
    ren_true, ren_ref = IdealRenderer(truth), IdealRenderer(type(truth)([res.mesh], {}))
    k = 4
    a = ren_true.render(seq.poses[k], seq.intrinsics, with_rgb=False).depth
    b = ren_ref.render(seq.poses[k], seq.intrinsics, with_rgb=False).depth
    both = (a > 0) & (b > 0)
    assert both.mean() > 0.8
    assert np.median(np.abs(a[both] - b[both])) < 0.005


def test_make_reference_cli_copies_and_does_not_touch_source(ideal_seq, tmp_path):
    src_files = sorted(p.name for p in ideal_seq.iterdir())
    out = tmp_path / "with_ref"
    args = ["data", "make-reference", str(ideal_seq), "--out", str(out), "--voxel", "0.03", "--depth-max", "6",
            "--material", "room_fused", "--albedo", "0.4", "--max-frames", "4"]
    assert main(args) == 0
    assert sorted(p.name for p in ideal_seq.iterdir()) == src_files  # source untouched
    sc = json.loads((out / "scene.json").read_text())
    assert sc["meshes"][0]["material"] == "room_fused" and sc["materials"]["room_fused"]["albedo"] == 0.4
    meta = json.loads((out / "reference_config.json").read_text())
    assert meta["result"]["frames_fused"] == 4 and meta["config"]["tsdf"]["voxel_size_m"] == 0.03
    r = SequenceReader(out)
    assert len(r) == 8 and r.has_scene and len(r.scene.meshes) == 1
    np.testing.assert_array_equal(r.read_depth(3), SequenceReader(ideal_seq).read_depth(3))
    # same options again: the finished output is kept, and the command says --overwrite (the re-run rule)
    mtime = (out / "meshes" / "reference.ply").stat().st_mtime_ns
    assert main(args) == 1
    assert (out / "meshes" / "reference.ply").stat().st_mtime_ns == mtime
    p = subprocess.run([sys.executable, "-m", "app", *args[:-2], "--max-frames", "3"], capture_output=True, text=True,
                       cwd=REPO, timeout=120)
    assert p.returncode == 1 and "--overwrite" in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_make_reference_errors_and_named_cameras(ideal_seq, tmp_path):
    import shutil
    nogt = tmp_path / "nogt"
    shutil.copytree(ideal_seq, nogt, ignore=shutil.ignore_patterns("groundtruth.txt", "scene.json", "meshes"))
    with pytest.raises(FormatError, match="groundtruth"):
        make_reference(nogt)
    p = subprocess.run([sys.executable, "-m", "app", "data", "make-reference", str(nogt), "--camera", "tum_fr9"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert p.returncode == 1 and "tum_fr1" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert named_camera("tum_fr1").intrinsics.fx == 517.3
    assert NAMED_CAMERAS["sevenscenes"].depth_scale == 1000.0


def test_make_reference_copy_opens_when_a_depth_frame_has_no_colour(ideal_seq, tmp_path):
    """The copy lists the same depth frames as the source, so every one of them must be copied,
    also a depth frame without a colour image within 0.02 s (it is not in reader.depth_files)."""
    import shutil
    src = tmp_path / "gap"
    shutil.copytree(ideal_seq, src)
    lines = (src / "rgb.txt").read_text().splitlines()
    body = [ln for ln in lines if not ln.startswith("#")]
    (src / "rgb.txt").write_text("\n".join([ln for ln in lines if ln.startswith("#")] + body[:3] + body[4:]) + "\n")
    assert len(SequenceReader(src).depth_files) == 7
    out = tmp_path / "gap_ref"
    make_reference(src, out, ReferenceConfig(tsdf=TSDFConfig(voxel_size_m=0.05, integrate_color=False)))
    assert sorted(p.name for p in (out / "depth").iterdir()) == sorted(p.name for p in (src / "depth").iterdir())
    assert len(SequenceReader(out).depth_files) == 7
