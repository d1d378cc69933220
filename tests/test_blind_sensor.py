"""tests/blind_sensor.py, the blind structured-light generator: deterministic files the project's readers
load, the answer it promises, and one hand-checkable property per effect (lattice, shadow rays, lens
inverse, rolling-shutter rows, noise scaling, dropout laws, fattening radius, bias)."""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blind_sensor as bs  # noqa: E402

from data_tools.sequence import SequenceReader  # noqa: E402

REVIEWER_KEYS = {"incidence_dropout": "angle50_deg", "lens_distortion": "k1", "disparity_quantization": "step_px",
                 "edge_fattening": "radius_px", "rolling_shutter": "readout_time_s", "low_reflectance": "signal50"}


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _depths(out: Path) -> list[np.ndarray]:
    seq = SequenceReader(out)
    return [seq.read_depth(k).astype(np.float64) for k in range(len(seq))]


def test_same_arguments_write_byte_identical_files(tmp_path):
    a1 = bs.generate(tmp_path / "a", "projector_shadow", 3, n_frames=2)
    a2 = bs.generate(tmp_path / "b", "projector_shadow", 3, n_frames=2)
    assert a1 == a2
    fa, fb = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert fa.keys() == fb.keys() and fa == fb
    assert {"camera.json", "scene.json", "depth.txt", "rgb.txt", "groundtruth.txt", "answer.json"} <= fa.keys()


def test_another_seed_is_another_sensor_and_scene(tmp_path):
    bs.generate(tmp_path / "a", None, 1, n_frames=2)
    bs.generate(tmp_path / "b", None, 2, n_frames=2)
    ca, cb = (json.loads((tmp_path / x / "camera.json").read_text()) for x in "ab")
    assert ca["fx"] != cb["fx"] and ca["sensor"]["baseline_m"] != cb["sensor"]["baseline_m"]
    assert (tmp_path / "a" / "scene.json").read_bytes() != (tmp_path / "b" / "scene.json").read_bytes()
    assert ca["fx"] != ca["fy"]


def test_noise_seed_changes_only_the_noise(tmp_path):
    bs.generate(tmp_path / "a", None, 4, n_frames=2, noise_seed=11)
    bs.generate(tmp_path / "b", None, 4, n_frames=2, noise_seed=12)
    fa, fb = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert fa.keys() == fb.keys()
    differ = {k for k in fa if fa[k] != fb[k]}
    assert differ and all(k.startswith("depth/") for k in differ)
    za, zb = _depths(tmp_path / "a")[0], _depths(tmp_path / "b")[0]
    both = (za > 0) & (zb > 0)
    assert abs(both.mean() - 1) < 0.6 and np.median(np.abs(za - zb)[both]) < 0.05   # same scene, other noise


@pytest.mark.parametrize("effect", [None, *bs.EFFECTS])
def test_answer_and_depth_files_for_every_effect(tmp_path, effect):
    out = tmp_path / "seq"
    ans = bs.generate(out, effect, 5, n_frames=2)
    assert set(ans) == {"effect", "seed", "noise2m", "bias_at_m", "params"}
    assert ans["effect"] == effect and ans["seed"] == 5
    assert json.loads((out / "answer.json").read_text())["effect"] == effect
    s = bs.build(5, effect, 2)
    assert ans["noise2m"] == pytest.approx(4 * s.rig.sigma_d / s.rig.fb, rel=0.01)
    assert 0.005 < ans["noise2m"] < 0.1
    if effect == "depth_bias":
        assert set(ans["bias_at_m"]) == {1.0, 2.0, 3.0}
    else:
        assert ans["bias_at_m"] is None
    if effect in REVIEWER_KEYS:
        assert REVIEWER_KEYS[effect] in ans["params"]
    if effect == "edge_fattening":
        assert isinstance(ans["params"]["radius_px"], int)
    seq = SequenceReader(out)
    cam = json.loads((out / "camera.json").read_text())
    assert len(seq) == 2 and seq.trajectory is not None and len(seq.scene.meshes) >= 7
    for k, rel in enumerate(seq.depth_files):
        raw = cv2.imread(str(out / rel), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (120, 160)
        c = bs.cast(s, k)
        z = raw / cam["depth_scale"]
        valid = raw > 0
        assert 0.2 < valid.mean() < 1.0
        assert np.all(z[valid] >= s.rig.near_m - 1e-3) and np.all(z[valid] <= s.rig.far_m + 1e-3)
        assert not np.any(valid & ~c["hit"])


def test_none_effect_noise_matches_noise2m(tmp_path):
    ans = bs.generate(tmp_path / "n", None, 3, n_frames=4)
    s = bs.build(3, None, 4)
    zm = np.array(_depths(tmp_path / "n"))
    zt = np.array([bs.cast(s, k)["z"] for k in range(4)])
    ok = zm > 0
    # per pixel: std of (measured - true) / (z^2 sigma_d / f b) is 1
    rn = ((zm - zt) / (zt ** 2 * s.rig.sigma_d / s.rig.fb))[ok]
    assert rn.std() == pytest.approx(1.0, abs=0.05) and abs(rn.mean()) < 0.05
    band = ok & (np.abs(zt - 2.0) < 0.1)                      # the floor/walls near 2 m
    assert band.sum() > 1000
    assert np.std((zm - zt)[band]) == pytest.approx(ans["noise2m"], rel=0.15)


def test_quantised_disparities_lie_on_the_step_lattice(tmp_path):
    ans = bs.generate(tmp_path / "q", "disparity_quantization", 2, n_frames=2)
    s = bs.build(2, "disparity_quantization", 2)
    p = ans["params"]
    assert 1.5 <= p["step_to_noise"] <= 8.0 and 0 < p["step_px"] < 1
    for z in _depths(tmp_path / "q"):
        k = s.rig.fb / z[z > 0] / p["step_px"] - p["level_phase"]
        assert np.abs(k - np.round(k)).max() < 0.02                 # PNG rounding only
        assert len(np.unique(np.round(k))) > 5


def test_shadowed_pixels_are_where_the_shadow_ray_is_blocked(tmp_path):
    bs.generate(tmp_path / "s", "projector_shadow", 1, n_frames=2, noise_seed=5)
    bs.generate(tmp_path / "n", None, 1, n_frames=2, noise_seed=5)
    s = bs.build(1, "projector_shadow", 2)
    cam = json.loads((tmp_path / "s" / "camera.json").read_text())
    assert cam["sensor"]["projector_offset_m"] == [s.rig.side * s.rig.baseline_m, 0.0, 0.0]
    zs, zn = _depths(tmp_path / "s"), _depths(tmp_path / "n")
    for k in range(2):
        c = bs.cast(s, k)
        mask = bs.shadow_mask(s, c)
        assert mask.sum() > 50
        np.testing.assert_array_equal(zs[k] == 0, (zn[k] == 0) | mask)
        np.testing.assert_array_equal(zs[k][zs[k] > 0], zn[k][zs[k] > 0])
        # by hand, for some shadowed pixels: the projector is behind the surface, or a solid holds a point
        # of the segment to the projector, or the segment crosses a rectangle
        ys, xs = np.nonzero(mask)
        for y, x in list(zip(ys, xs))[::20]:
            assert _blocked_by_hand(s, c["point"][y, x], c["projector_rows"][y], c["normal"][y, x])
        ys, xs = np.nonzero(~mask & c["hit"])
        for y, x in list(zip(ys, xs))[::400]:
            assert not _blocked_by_hand(s, c["point"][y, x], c["projector_rows"][y], c["normal"][y, x])


def _blocked_by_hand(s, p, q, n) -> bool:
    if np.dot(q - p, n) <= 0:
        return True
    pts = p + np.linspace(0.002, 0.998, 4000)[:, None] * (q - p)
    for part in s.parts:
        for prim in part.prims:
            if isinstance(prim, bs.Sphere) and np.any(np.linalg.norm(pts - prim.c, axis=1) < prim.r):
                return True
            if isinstance(prim, bs.Box) and np.any(np.all(np.abs((pts - prim.c) @ prim.R) < prim.h, axis=1)):
                return True
            if isinstance(prim, bs.Rect):
                nr = np.cross(prim.a, prim.b)
                side = (pts - prim.o) @ nr
                cross = np.flatnonzero(np.sign(side[1:]) != np.sign(side[:-1]))
                for i in cross:
                    w = pts[i] - prim.o
                    a_, b_ = w @ prim.a / (prim.a @ prim.a), w @ prim.b / (prim.b @ prim.b)
                    if 0 <= a_ <= 1 and 0 <= b_ <= 1:
                        return True
    return False


def test_shadow_matches_an_independent_mesh_cast_from_the_projector(tmp_path):
    o3d = pytest.importorskip("open3d")
    bs.generate(tmp_path / "s", "projector_shadow", 4, n_frames=1, noise_seed=2)
    bs.generate(tmp_path / "n", None, 4, n_frames=1, noise_seed=2)
    seq = SequenceReader(tmp_path / "s")
    scene = o3d.t.geometry.RaycastingScene()
    for m in seq.scene.meshes:
        scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                            o3d.core.Tensor(m.triangles.astype(np.uint32)))

    def cast(O, D):
        rays = np.concatenate([np.broadcast_to(O, D.shape), D], -1).reshape(-1, 6).astype(np.float32)
        return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(D.shape[:-1])
    K, T = seq.intrinsics, seq.poses[0]
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    d = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], -1) @ T[:3, :3].T
    P = T[:3, 3] + cast(T[:3, 3], d)[..., None] * d
    Pj = T[:3, 3] + T[:3, :3] @ np.array(seq.camera.sensor.projector_offset_m)
    dj = P - Pj
    L = np.linalg.norm(dj, axis=-1)
    lit = cast(Pj, dj / L[..., None]) > L - 2e-3
    zs, zn = seq.read_depth(0), _depths(tmp_path / "n")[0]
    shadowed = (zn > 0) & (zs == 0)
    assert shadowed.sum() > 50
    assert (shadowed != ((zn > 0) & ~lit)).sum() <= 3


def test_lens_rays_invert_opencv_distortion(tmp_path):
    ans = bs.generate(tmp_path / "d", "lens_distortion", 3, n_frames=1)
    s = bs.build(3, "lens_distortion", 1)
    k1 = ans["params"]["k1"]
    assert 0.04 <= abs(k1) <= 0.25
    assert json.loads((tmp_path / "d" / "camera.json").read_text())["distortion"] == [0.0] * 5   # not declared
    r = s.rig
    K = np.array([[r.fx, 0, r.cx], [0, r.fy, r.cy], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(r.width, dtype=float), np.arange(r.height, dtype=float))
    und = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), K, np.array([k1, 0, 0, 0, 0.0]),
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14))
    rays = bs.camera_rays(s)
    np.testing.assert_allclose(rays[..., :2].reshape(-1, 2), und.reshape(-1, 2), atol=1e-7)
    # and distorting the ray back with OpenCV's forward model lands on the pixel
    xu, yu = rays[..., 0], rays[..., 1]
    f = 1 + k1 * (xu ** 2 + yu ** 2)
    np.testing.assert_allclose(xu * f * r.fx + r.cx, u, atol=1e-6)


def test_rolling_shutter_rows_see_their_own_pose(tmp_path):
    for seed in range(20):                         # a seed whose reference row is the first or last row
        s = bs.build(seed, "rolling_shutter", 2)
        if s.params["reference_row"] in (0.0, 1.0):
            break
    ans = bs.generate(tmp_path / "r", "rolling_shutter", seed, n_frames=2)
    p = ans["params"]
    assert 0.010 <= p["readout_time_s"] <= 0.035 and s.motion.moving
    t = bs.row_times(s, 1)
    assert t[-1] - t[0] == pytest.approx(p["readout_time_s"])
    vref = int(p["reference_row"] * (s.rig.height - 1))
    assert t[vref] == s.timestamps[1]
    z_rs = bs.cast(s, 1)["z"]
    z_gs = bs.cast(dataclasses.replace(s, effect=None), 1)["z"]      # the same path, global shutter
    np.testing.assert_array_equal(z_rs[vref], z_gs[vref])
    far_row = s.rig.height - 1 - vref
    assert np.median(np.abs(z_rs[far_row] - z_gs[far_row])) > 1e-3
    gt = SequenceReader(tmp_path / "r").poses[1]
    R, C = s.motion.pose(s.timestamps[1:2])
    np.testing.assert_allclose(gt[:3, 3], C[0], atol=1e-8)
    np.testing.assert_allclose(gt[:3, :3], R[0], atol=1e-8)


def test_dropout_laws_are_half_at_their_50_percent_points(tmp_path):
    for effect, seed in (("incidence_dropout", 0), ("low_reflectance", 2)):
        ans = bs.generate(tmp_path / effect, effect, seed, n_frames=4, noise_seed=9)
        bs.generate(tmp_path / f"{effect}_base", None, seed, n_frames=4, noise_seed=9)
        s = bs.build(seed, effect, 4)
        z, zb = _depths(tmp_path / effect), _depths(tmp_path / f"{effect}_base")
        p = ans["params"]
        near, drop = [], []
        for k in range(4):
            c = bs.cast(s, k)
            if effect == "incidence_dropout":
                x = np.degrees(np.arccos(c["cos"])) - p["angle50_deg"]
                sel = np.abs(x) < 1.0
            else:
                sel = np.abs(np.log10(c["signal"] / p["signal50"] + 1e-30)) < 0.04
            sel &= zb[k] > 0
            near.append(sel.sum())
            drop.append((z[k] == 0)[sel])
        drop = np.concatenate(drop)
        assert sum(near) > 300, effect
        assert drop.mean() == pytest.approx(0.5, abs=0.08), effect
        for k in range(4):                           # dropouts only remove pixels; the rest is the base
            keep = z[k] > 0
            assert np.all(zb[k][keep] == z[k][keep])


def test_edge_fattening_spreads_the_foreground_by_radius_px():
    s = bs.build(2, "edge_fattening", 1)
    r = s.params["radius_px"]
    c = bs.cast(s, 0)
    D0 = s.rig.fb / c["z"]
    D1 = bs.fatten(s, c, D0)
    changed = D1 != D0
    assert changed.sum() > 100 and np.all(D1[changed] > D0[changed] + s.params["min_jump_px"])
    edge = bs.foreground_edges(s, c, D0, s.params["min_jump_px"])
    dist = ndimage.distance_transform_cdt(~edge, metric="chessboard")
    assert dist[changed].max() == r
    assert np.bincount(dist[changed], minlength=r + 1)[1:].min() > 0.3 * changed.sum() / r / 2
    # every new value is the disparity of a foreground edge pixel in the window
    vals = set(np.round(D0[edge], 9))
    assert all(x in vals for x in np.round(D1[changed], 9))


def test_depth_bias_answer_matches_the_measured_mean_error(tmp_path):
    ans = bs.generate(tmp_path / "b", "depth_bias", 1, n_frames=4)
    s = bs.build(1, "depth_bias", 4)
    zm = np.array(_depths(tmp_path / "b"))
    zt = np.array([bs.cast(s, k)["z"] for k in range(4)])
    for z0 in (2.0, 3.0):
        band = (zm > 0) & (np.abs(zt - z0) < 0.1)
        assert band.sum() > 1000
        err = (zm - zt)[band].mean()
        assert err == pytest.approx(ans["bias_at_m"][z0], abs=max(0.002, 0.1 * abs(ans["bias_at_m"][z0])))
    b = ans["bias_at_m"]
    assert max(abs(b[1.0]), abs(b[2.0]), abs(b[3.0])) > 0.005
