"""``data make-reference --plane``: a simulated capture of a flat target in front of a far wall,
without poses. The fitted poses put the target on z = 0, the masks hold the target and not the
wall behind, and the sensor lab then compares only masked-in pixels: scrambling the measured depth
outside the masks changes nothing."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from data_tools.sequence import SequenceReader


def _capture(root: Path, frames: int = 4) -> Path:
    """A 0.2 m square target facing the camera at 1.0-1.6 m, a back wall 1 m behind it, Kinect v1
    (160x120 crop, direct effects); written without ground truth."""
    from data_tools.scene_spec import Material, SceneSpec
    from data_tools.sequence import Frame, SequenceWriter
    from synth.sensor.config import SensorConfig
    from synth.sensor.simulator import SensorSimulator
    from synth.sensor.testscenes import quad_mesh
    target = quad_mesh([0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], "target", "target", 2)
    back = quad_mesh([0, 0, -1.0], [3, 0, 0], [0, 3, 0], "back", "back", 2)
    scene = SceneSpec([target, back], {"target": Material(0.6, 0.0), "back": Material(0.4, 0.0)})
    sim = SensorSimulator(SensorConfig.from_spec("kinect_v1", "axial_noise,projector_shadow", 160, 120), None, scene)
    out = root / "capture"
    rng = np.random.default_rng(1)
    with SequenceWriter(out, sim.camera()) as w:
        for k in range(frames):
            T = np.eye(4)                       # camera looking along -z at the target (OpenCV axes)
            T[:3, :3] = np.diag([1.0, -1.0, -1.0])
            from recog.symmetry import _rot
            T[:3, :3] = _rot(rng.normal(size=3), np.radians(2)) @ T[:3, :3]
            T[:3, 3] = [0.02 * k, -0.01 * k, 1.0 + 0.2 * k]
            r = sim.simulate(T, seed=k, with_rgb=False)
            w.write(Frame(k / 30.0, r.depth, None, None, k))
    (out / "groundtruth.txt").unlink(missing_ok=True)
    return out


@pytest.fixture(scope="module")
def plane_ref(tmp_path_factory):
    root = tmp_path_factory.mktemp("plane")
    cap = _capture(root)
    ref = root / "ref"
    # the back wall fills more of the image than the target: without a window RANSAC takes the wall
    assert main(["data", "make-reference", str(cap), "--plane", "--out", str(root / "wall"), "--no-progress"]) == 0
    wall = json.loads((root / "wall" / "plane_reference.json").read_text())
    assert max(p["distance_m"] for p in wall["planes"]) > 2.5
    assert main(["data", "make-reference", str(cap), "--plane", "--roi", "50,30,110,90", "--out", str(ref),
                 "--no-progress"]) == 0
    return cap, ref


def test_poses_put_the_target_on_z0_and_masks_hold_it(plane_ref):
    from data_tools.geometry import unproject
    cap, ref = plane_ref
    seq = SequenceReader(ref)
    assert seq.has_masks and seq.has_groundtruth and len(seq.trajectory) == 4
    meta = json.loads((ref / "plane_reference.json").read_text())
    dists = [p["distance_m"] for p in meta["planes"]]
    np.testing.assert_allclose(sorted(dists), [1.0, 1.2, 1.4, 1.6], atol=0.02)   # camera-to-target distance
    for i in range(len(seq)):
        m = seq.read_mask(i)
        z = seq.read_depth(i)
        assert 0.1 < m.mean() < 0.2 and not m[:30].any() and not m[:, :50].any()     # inside the window
        wall = z > np.median(z[m]) + 0.5                                 # the back wall, 1 m behind
        assert wall.any() and not (m & wall).any()
        P = unproject(z, seq.intrinsics)[m]
        T = seq.poses[i]
        world_z = P @ T[2, :3] + T[2, 3]
        assert np.abs(np.median(world_z)) < 0.002 and np.percentile(np.abs(world_z), 95) < 0.02


def test_lab_ignores_pixels_outside_the_masks(plane_ref, tmp_path):
    cap, ref = plane_ref
    scrambled = tmp_path / "scrambled"
    shutil.copytree(ref, scrambled)
    seq = SequenceReader(scrambled)
    from data_tools.sequence import read_depth_png, write_depth_png
    rng = np.random.default_rng(0)
    for i in range(len(seq)):
        p = scrambled / seq.depth_files[i]
        p.unlink()                                   # hard-linked to the capture: write a new file
        z = read_depth_png(ref / seq.depth_files[i], seq.camera.depth_scale)
        m = seq.read_mask(i)
        z = np.where(m, z, rng.uniform(0.5, 4.0, z.shape) * (rng.random(z.shape) > 0.3)).astype(np.float32)
        write_depth_png(p, z, seq.camera.depth_scale)
    gaps = []
    for s, out in ((ref, tmp_path / "a"), (scrambled, tmp_path / "b")):
        assert main(["sensor", "compare", str(s), "--effects", "axial_noise", "--out", str(out),
                     "--compare-preset", "fast", "--report-frames", "0", "--no-progress"]) == 0
        gaps.append(json.loads((out / "metrics.json").read_text())["gap"])
    assert gaps[0] == pytest.approx(gaps[1], abs=1e-12), gaps
    page = (tmp_path / "a" / "report.html").read_text()
    assert "Khoshelham" in page and (tmp_path / "a" / "figures" / "plane_noise.png").is_file()
    assert (tmp_path / "a" / "figures" / "plane_residual_map.png").is_file()
    # and without the masks the scrambled background does change the gap
    (scrambled / "mask.txt").unlink()
    assert main(["sensor", "compare", str(scrambled), "--effects", "axial_noise", "--out", str(tmp_path / "c"),
                 "--compare-preset", "fast", "--report-frames", "0", "--no-progress"]) == 0
    assert json.loads((tmp_path / "c" / "metrics.json").read_text())["gap"] != pytest.approx(gaps[0], abs=1e-3)


def test_plane_reference_errors(plane_ref, tmp_path, capsys):
    cap, ref = plane_ref
    for argv, words in ((["data", "make-reference", str(cap), "--plane"], ["--out"]),
                        (["data", "make-reference", str(cap), "--plane", "--out", str(tmp_path / "r"), "--roi",
                          "5,5,2"], ["--roi"]),
                        (["data", "make-reference", str(cap), "--plane", "--out", str(ref)], ["--overwrite"])):
        capsys.readouterr()
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "Traceback" not in err, err
        for w in words:
            assert w in err, (w, err)


def test_calibration_numbers_by_hand():
    """Noise table and mean residual map on hand-made observations."""
    from types import SimpleNamespace

    from synth.lab.calibration import khoshelham_sigma_m, mean_residual_maps, nguyen_sigma_m, plane_noise_table
    assert khoshelham_sigma_m(2.0) == pytest.approx(0.0057) and nguyen_sigma_m(0.4) == pytest.approx(0.0012)
    ideal = np.full((20, 20), 1.5, np.float32)
    ideal[:, :5] = 0                                     # off the target
    rng = np.random.default_rng(0)
    obs = []
    for k in range(3):
        meas = (ideal + rng.normal(0, 0.004, ideal.shape) + 0.002).astype(np.float32) * (ideal > 0)
        sim = (ideal + rng.normal(0, 0.002, ideal.shape)).astype(np.float32) * (ideal > 0)
        obs.append(SimpleNamespace(ideal=ideal, measured=meas, simulated=sim, index=k))
    rows = plane_noise_table(obs)
    assert len(rows) == 3 and all(r["distance_m"] == pytest.approx(1.5) for r in rows)
    assert np.mean([r["measured_mm"] for r in rows]) == pytest.approx(4.0, rel=0.15)
    assert np.mean([r["simulated_mm"] for r in rows]) == pytest.approx(2.0, rel=0.15)
    m, s = mean_residual_maps(obs)
    assert np.isnan(m[:, :5]).all() and np.nanmean(m) == pytest.approx(2.0, abs=0.5)


def _plane_depth(intr, n, d):
    """Depth (H, W) of the camera-frame plane n.X + d = 0 along every pixel ray."""
    from data_tools.geometry import pixel_rays
    r = pixel_rays(intr, unit=False)
    return (-d / (r @ n)).astype(np.float32)


def test_flatness_check_cuts_objects_in_the_band_and_keeps_a_clean_plane():
    """A floor seen at 1.5-2.5 m with 3 mm of noise: every tile is kept and the refitted plane is the
    true one; with an 8 mm thick board lying on it (inside the +-3 sigma band the mask keeps) the
    board's tiles are cut, the plane stays the floor (offset within 1 mm, not pulled by the board),
    and a roof of two planes 4 deg apart is not a clean plane at all."""
    from data_tools.camera import Intrinsics
    from slam.plane_reference import PlaneReferenceConfig, flat_support, plane_mask
    intr = Intrinsics(320, 240, 290.0, 290.0, 159.5, 119.5)
    n = np.array([0.0, -np.cos(np.radians(50)), -np.sin(np.radians(50))])
    d = 1.4
    rng = np.random.default_rng(0)
    z = _plane_depth(intr, n, d)
    noisy = (z + 0.003 * rng.standard_normal(z.shape)).astype(np.float32)
    cfg = PlaneReferenceConfig()
    mask = plane_mask(noisy, intr, n, d, None, cfg.mask_threshold_m)
    clean = flat_support(noisy, intr, mask, n, d, cfg)
    assert clean.kept == clean.tiles > 30 and abs(clean.d - d) < 1e-3
    board = noisy.copy()
    sl = (slice(100, 160), slice(120, 200))
    board[sl] = (_plane_depth(intr, n, d - 0.008)[sl] + 0.003 * rng.standard_normal((60, 80))).astype(np.float32)
    mask = plane_mask(board, intr, n, d, None, cfg.mask_threshold_m)
    assert mask[sl].mean() > 0.9                           # the band alone keeps the board
    fs = flat_support(board, intr, mask, n, d, cfg)
    assert fs.mask[110:150, 130:190].sum() == 0 and fs.kept < fs.tiles
    assert abs(fs.d - d) < 1e-3 and np.degrees(np.arccos(min(1.0, abs(fs.n @ n)))) < 0.2
    # a roof: the right half tilted by 4 deg about the image's vertical line through the centre
    n2 = np.array([np.sin(np.radians(4)), n[1], n[2]])
    n2 /= np.linalg.norm(n2)
    roof = noisy.copy()
    roof[:, 160:] = _plane_depth(intr, n2, d)[:, 160:]
    mask = plane_mask(roof, intr, n, d, None, 0.05)
    fs = flat_support(roof, intr, mask, n, d, cfg)
    assert fs.kept < cfg.min_flat_share * fs.tiles or fs.mask[:, 160:].mean() < 0.2


def test_mask_keeps_the_sensors_holes_and_noise_tails_on_the_target():
    """The mask is where the target is, not where the sensor measured it well: a fronto-parallel
    wall at 2.4 m with noise 2.5 x Nguyen et al.'s sigma (the +-3 sigma band alone would cut the
    residuals at 1.2 of their std and read the noise 0.7 x too low) and 4 % of its pixels dropped
    at random, plus a 20x20 hole: the kept residuals' robust std is the true one within 3 %, the
    holes inside the target are in the mask (the lab then sees the hole rate), and the image beyond
    the target's edge (a far wall, 1 m behind) stays out."""
    from data_tools.camera import Intrinsics
    from slam.plane_reference import PlaneReferenceConfig, _nguyen_sigma, flat_support, plane_mask
    intr = Intrinsics(320, 240, 290.0, 290.0, 159.5, 119.5)
    n, d = np.array([0.0, 0.0, -1.0]), 2.4
    rng = np.random.default_rng(3)
    sigma = 2.5 * float(_nguyen_sigma(2.4))
    depth = (d + sigma * rng.standard_normal((240, 320))).astype(np.float32)
    depth[:, 260:] = 3.4                                          # beyond the target's edge
    holes = rng.random(depth.shape) < 0.04
    holes[100:120, 100:120] = True
    holes[:, 260:] = False
    depth[holes] = 0.0
    cfg = PlaneReferenceConfig()
    fs = flat_support(depth, intr, plane_mask(depth, intr, n, d, None, cfg.mask_threshold_m), n, d, cfg)
    m = fs.mask
    assert m[:, 260:].sum() == 0 and m[:, :250].mean() > 0.95
    assert m[holes].mean() > 0.95                                 # the holes count as target pixels
    r = depth[m & (depth > 0)] - d
    robust = 1.4826 * np.median(np.abs(r - np.median(r)))
    assert robust == pytest.approx(sigma, rel=0.03)
