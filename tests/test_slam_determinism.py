"""Bit-reproducibility of the icp backend whatever the thread count: the same frames on 1 and on
2 threads give byte-identical trajectories and meshes (fixed-order registration sums, per-pixel
ray casts, per-voxel fusion)."""
from __future__ import annotations

import numpy as np
import pytest

from slam.backends._p2p_kernel import normal_equations
from slam.pipeline import make_config, run_slam
from slam.threads import compute_threads, max_threads
from tests.slam_scenes import camera_path, render_frames, room_scene, write_sequence

N_FRAMES = 30

needs_two = pytest.mark.skipif(max_threads() < 2, reason="needs 2 numba threads")


@pytest.fixture(scope="module")
def seq30(tmp_path_factory):
    root = tmp_path_factory.mktemp("det")
    frames = render_frames(room_scene(), camera_path(N_FRAMES, 0.015, 0.8))
    return write_sequence(root / "seq", frames)


@needs_two
def test_normal_equations_do_not_depend_on_the_thread_count():
    """The 6x6 system summed over 100k random correspondences: identical bits on 1 and 2 threads,
    and equal (to rounding) to a plain numpy sum of the same residual terms."""
    rng = np.random.default_rng(3)
    H, W = 240, 320
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    z = (1.0 + rng.random((H, W))).astype(np.float32)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    V = np.stack([(u - 160) / 300 * z, (v - 120) / 300 * z, z], -1).astype(np.float32)
    N = rng.normal(size=(H, W, 3)).astype(np.float32)
    N /= np.linalg.norm(N, axis=-1, keepdims=True)
    tgt = V + (0.003 * rng.normal(size=(H, W, 1)) * N).astype(np.float32)
    with compute_threads(1):
        a1 = normal_equations(V, tgt, N, K, np.eye(4), 0.05, 1.0)
    with compute_threads(2):
        a2 = normal_equations(V, tgt, N, K, np.eye(4), 0.05, 1.0)
    assert a1[0].tobytes() == a2[0].tobytes() and a1[1].tobytes() == a2[1].tobytes() and a1[2:] == a2[2:]
    p, t, n = V.reshape(-1, 3).astype(np.float64), tgt.reshape(-1, 3).astype(np.float64), N.reshape(-1, 3)
    r = ((p - t) * n).sum(1)
    J = np.concatenate([np.cross(p, n), n], 1)
    assert a1[2] == H * W
    np.testing.assert_allclose(a1[0], J.T @ J, rtol=1e-9)
    np.testing.assert_allclose(a1[1], J.T @ r, rtol=1e-9, atol=1e-12)


@needs_two
def test_same_frames_on_one_and_two_threads_give_the_same_bytes(tmp_path, seq30):
    """1 and 2 compute threads, and fusion overlapped with tracking (``overlap``, a helper thread
    fusing frame t-1 while frame t is tracked) or not: the same trajectory and mesh bytes."""
    over = {"tsdf.voxel_size_m": 0.01, "tsdf.mesh_weight_threshold": 1.0, "backend_config.raycast_scale": 1.0}
    out = {}
    for n, overlap in ((1, True), (2, True), (2, False)):
        cfg = make_config("icp", "default", dict(over, overlap=overlap))
        with compute_threads(n):
            res = run_slam(seq30, tmp_path / f"t{n}{overlap}", cfg, progress=False)
        assert res.complete and res.stats["frames_tracked"] == N_FRAMES
        out[n, overlap] = {f: (tmp_path / f"t{n}{overlap}" / f).read_bytes() for f in ("trajectory.txt", "mesh.ply")}
    for key in ((2, True), (2, False)):
        assert out[1, True]["trajectory.txt"] == out[key]["trajectory.txt"]
        assert out[1, True]["mesh.ply"] == out[key]["mesh.ply"]
