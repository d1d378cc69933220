"""7-Scenes -> TUM converter: tiny hand-made fixture, resume, bad input, and the real chess frames."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from data_tools.errors import FormatError
from data_tools.geometry import quat_to_matrix
from data_tools.sequence import SequenceReader
from data_tools.sevenscenes import convert_7scenes
from tests.conftest import shared_path


def _make_7scenes(root, n=3, h=6, w=8):
    root.mkdir()
    rng = np.random.default_rng(0)
    poses, depths = [], []
    for k in range(n):
        stem = root / f"frame-{k:06d}"
        cv2.imwrite(str(stem) + ".color.jpg", rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
        d = rng.integers(400, 4000, (h, w)).astype(np.uint16)
        d[0, 0] = 65535 if k == 1 else 0
        cv2.imwrite(str(stem) + ".depth.png", d)
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(rng.normal(size=4))
        T[:3, 3] = [k * 0.1, 0.0, 1.0]
        np.savetxt(str(stem) + ".pose.txt", T)
        poses.append(T)
        depths.append(d)
    np.savetxt(root / "camera-intrinsics.txt", [[585, 0, 3.5], [0, 585, 2.5], [0, 0, 1]])
    return poses, depths


def test_convert_tiny_fixture(tmp_path):
    poses, depths = _make_7scenes(tmp_path / "src")
    r = convert_7scenes(tmp_path / "src", tmp_path / "dst", progress=False)
    assert r.frames == 3 and r.invalid_65535_frames == 1
    seq = SequenceReader(tmp_path / "dst")
    assert seq.camera.depth_scale == 1000.0 and seq.intrinsics.cx == 3.5
    assert len(seq) == 3
    for k, f in enumerate(seq):
        assert f.timestamp == pytest.approx(k / 30.0, abs=1e-6)
        expect = np.where(depths[k] == 65535, 0, depths[k]) / 1000.0
        np.testing.assert_allclose(f.depth, expect, atol=1e-6)
        np.testing.assert_allclose(f.pose, poses[k], atol=1e-7)
    assert f.depth[0, 0] == 0.0


def test_convert_resumes_after_interruption(tmp_path):
    _make_7scenes(tmp_path / "src", n=4)
    convert_7scenes(tmp_path / "src", tmp_path / "dst", progress=False)
    # pretend the run stopped after two frames (and rgb.txt already got the third line)
    for name, keep in (("depth.txt", 4), ("rgb.txt", 5), ("groundtruth.txt", 4)):
        p = tmp_path / "dst" / name
        p.write_text("\n".join(p.read_text().splitlines()[:keep]) + "\n")
    r = convert_7scenes(tmp_path / "src", tmp_path / "dst", progress=False)
    assert r.skipped_existing == 2 and r.frames == 4
    assert len(SequenceReader(tmp_path / "dst")) == 4


def test_convert_rejects_nan_pose(tmp_path):
    _make_7scenes(tmp_path / "src")
    (tmp_path / "src" / "frame-000002.pose.txt").write_text("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(FormatError, match="frame-000002.pose.txt: pose contains NaN"):
        convert_7scenes(tmp_path / "src", tmp_path / "dst", progress=False)
    assert not (tmp_path / "dst").exists()  # validated before anything was written


def test_convert_missing_depth(tmp_path):
    _make_7scenes(tmp_path / "src")
    (tmp_path / "src" / "frame-000001.depth.png").unlink()
    with pytest.raises(FormatError, match="frame-000001.depth.png: missing"):
        convert_7scenes(tmp_path / "src", tmp_path / "dst", progress=False)


@pytest.mark.shared_data
def test_convert_real_chess(tmp_path):
    src = shared_path("sevenscenes_chess_1000")
    from data_tools.sevenscenes import convert_7scenes as conv
    assert conv(src, tmp_path / "chess", progress=False).frames == 1000
    seq = SequenceReader(tmp_path / "chess")
    assert len(seq) == 1000 and seq.intrinsics.fx == 585.0
    f = seq[458]
    raw = cv2.imread(str(src / "frame-000458.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    raw[raw == 65535] = 0
    np.testing.assert_allclose(f.depth, raw / 1000.0, atol=1e-6)
    raw_T = np.loadtxt(src / "frame-000458.pose.txt")
    np.testing.assert_allclose(f.pose[:3, 3], raw_T[:3, 3], atol=1e-6)
    # 7-Scenes rotations are orthonormal only to ~1e-4; the converter writes the nearest rotation
    U, _, Vt = np.linalg.svd(raw_T[:3, :3])
    np.testing.assert_allclose(f.pose[:3, :3], U @ Vt, atol=1e-6)
    assert np.abs(f.pose[:3, :3] - raw_T[:3, :3]).max() < 5e-4
    # streaming: the reader holds paths, not images
    assert not hasattr(seq, "_cache")


@pytest.mark.shared_data
def test_reading_1000_frames_streams(tmp_path):
    """Iterating the 1000 converted chess frames keeps at most a few frames alive
    (holding them all would need ~2 GB: 1000 x (1.2 MB depth + 0.9 MB colour))."""
    import tracemalloc
    src = shared_path("sevenscenes_chess_1000")
    convert_7scenes(src, tmp_path / "chess", progress=False)
    seq = SequenceReader(tmp_path / "chess")
    tracemalloc.start()
    n, total = 0, 0.0
    for f in seq:
        n += 1
        total += float(f.depth[240, 320])
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert n == 1000 and total > 0
    assert peak < 30e6, f"peak traced memory {peak / 1e6:.1f} MB while streaming"
