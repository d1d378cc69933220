"""slam.metrics: hand-computable fixtures, invariances, round trips and a cross-check with evo."""
from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from conftest import shared_path
from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.geometry import quat_to_matrix, rotation_angle_rad
from data_tools.trajectory import Trajectory, associate, read_tum
from slam import metrics as M

# ---------------------------------------------------------------------------------------------
# helpers


def rot_z(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def random_rotation(rng) -> np.ndarray:
    return quat_to_matrix(rng.normal(size=4))


def poses_from(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.zeros((len(p), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    T[:, 3, 3] = 1
    return T


def traj_from_positions(p, t0=0.0, dt=0.1, R=None) -> Trajectory:
    p = np.asarray(p, dtype=float)
    R = np.broadcast_to(np.eye(3), (len(p), 3, 3)) if R is None else R
    return Trajectory(t0 + dt * np.arange(len(p)), poses_from(R, p))


def synthetic_pair(seed=0, n=80, noise_m=0.01, noise_deg=0.5):
    """A helix reference and a noisy estimate expressed in another world frame."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    p = np.stack([np.cos(0.1 * k), np.sin(0.1 * k), 0.02 * k], axis=1)
    R = np.stack([rot_z(3 * i) @ random_rotation(np.random.default_rng(1000)) for i in k])
    ref = Trajectory(10.0 + 0.033 * k, poses_from(R, p))
    dR = np.stack([quat_to_matrix(np.r_[rng.normal(scale=np.deg2rad(noise_deg) / 2, size=3), 1.0]) for _ in k])
    est_local = Trajectory(ref.timestamps + rng.uniform(-0.004, 0.004, n),
                           poses_from(R @ dR, p + rng.normal(scale=noise_m, size=p.shape)))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = random_rotation(rng), rng.normal(size=3)
    return ref, est_local.transformed(T)


def apply_sim3(traj: Trajectory, R, t, s) -> Trajectory:
    return M.Alignment("test", R, t, s).apply(traj)


# ---------------------------------------------------------------------------------------------
# hand-computable fixtures

SQUARE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1.0]])


def test_ate_constant_offset_is_exact():
    ref = traj_from_positions(SQUARE)
    est = traj_from_positions(SQUARE + [0.1, 0.0, 0.0])
    r = M.ate(ref, est, align="none")
    assert r.pairs == 5 and len(r.errors) == 5
    for k in ("rmse", "mean", "median", "min", "max"):
        assert r.stats[k] == pytest.approx(0.1, abs=1e-15)
    assert r.stats["std"] == pytest.approx(0.0, abs=1e-15)
    # a pure translation is removed entirely by se3 and by origin alignment
    assert M.ate(ref, est, align="se3").rmse < 1e-12
    o = M.ate(ref, est, align="origin")
    assert o.rmse < 1e-15
    np.testing.assert_allclose(o.alignment.t, [-0.1, 0, 0], atol=1e-15)


def test_ate_statistics_single_outlier():
    ref = traj_from_positions(SQUARE[:4])
    est = traj_from_positions(SQUARE[:4] + [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0.4]])
    s = M.ate(ref, est, align="none").stats
    # errors (0, 0, 0, 0.4): rmse sqrt(0.16/4), mean 0.1, median 0, std sqrt(0.04 - 0.01)
    assert s["rmse"] == pytest.approx(0.2)
    assert s["mean"] == pytest.approx(0.1)
    assert s["median"] == 0.0 and s["min"] == 0.0
    assert s["max"] == pytest.approx(0.4)
    assert s["std"] == pytest.approx(math.sqrt(0.03))


def test_se3_alignment_recovers_known_rigid_motion():
    ref = traj_from_positions(SQUARE)
    Rk, tk = rot_z(90), np.array([2.0, -1.0, 0.5])
    est = apply_sim3(ref, Rk, tk, 1.0)          # est = Rk ref + tk
    r = M.ate(ref, est, align="se3")
    assert r.rmse < 1e-12
    np.testing.assert_allclose(r.alignment.R, Rk.T, atol=1e-12)      # undoes the motion
    np.testing.assert_allclose(r.alignment.t, -Rk.T @ tk, atol=1e-12)
    assert r.alignment.s == 1.0
    # unaligned, every corner is off by its known distance
    d = np.linalg.norm(est.positions - ref.positions, axis=1)
    np.testing.assert_allclose(M.ate(ref, est, align="none").errors, d, atol=1e-15)


def test_sim3_alignment_recovers_scale():
    ref = traj_from_positions(SQUARE)
    est = apply_sim3(ref, rot_z(30), [0.3, 0.2, 0.1], 0.5)
    r = M.ate(ref, est, align="sim3")
    assert r.rmse < 1e-12
    assert r.alignment.s == pytest.approx(2.0, rel=1e-12)
    assert M.ate(ref, est, align="se3").rmse > 0.1     # a rigid fit cannot undo the scale


def test_rotation_ape_known_angle():
    ref = traj_from_positions(SQUARE)
    R_est = np.stack([R @ rot_z(10) for R in ref.poses[:, :3, :3]])
    est = Trajectory(ref.timestamps, poses_from(R_est, ref.positions))
    deg = M.ape(ref, est, "rotation_angle_deg", align="none")
    np.testing.assert_allclose(deg.errors, 10.0, atol=1e-12)
    assert deg.unit == "deg"
    rad = M.ape(ref, est, "rotation_angle_rad", align="none")
    np.testing.assert_allclose(rad.errors, np.deg2rad(10.0), atol=1e-14)
    full = M.ape(ref, est, "full", align="none")       # |R - I|_F = sqrt(4 (1 - cos a))
    np.testing.assert_allclose(full.errors, math.sqrt(4 * (1 - math.cos(np.deg2rad(10)))), atol=1e-14)
    assert M.ape(ref, est, "translation", align="none").rmse == 0.0


def test_rotation_angle_is_accurate_at_0_and_pi():
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(3)
    angles = np.array([0.0, 1e-9, 1e-5, 0.3, 2.0, np.pi - 1e-6, np.pi])
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R = Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    np.testing.assert_allclose(rotation_angle_rad(R), angles, atol=1e-9)


def test_rpe_constant_speed_error():
    n = 11
    ref = traj_from_positions(np.c_[np.arange(n) * 1.0, np.zeros(n), np.zeros(n)])
    est = traj_from_positions(np.c_[np.arange(n) * 1.1, np.zeros(n), np.zeros(n)])
    r1 = M.rpe(ref, est, delta=1)
    assert len(r1.errors) == n - 1 and r1.pairs == n
    np.testing.assert_allclose(r1.errors, 0.1, atol=1e-12)
    r2 = M.rpe(ref, est, delta=2)               # pairs (0,2), (2,4), ... (8,10)
    np.testing.assert_array_equal(r2.index_pairs, [[0, 2], [2, 4], [4, 6], [6, 8], [8, 10]])
    np.testing.assert_allclose(r2.errors, 0.2, atol=1e-12)
    np.testing.assert_allclose(r2.timestamps, est.timestamps[[2, 4, 6, 8, 10]])
    ra = M.rpe(ref, est, delta=2, all_pairs=True)
    assert len(ra.errors) == n - 2
    # 1.5 m of travelled estimate path: steps of 1.1 m reach it after 2 poses
    rm = M.rpe(ref, est, delta=1.5, delta_unit="m")
    np.testing.assert_array_equal(rm.index_pairs[:, 1] - rm.index_pairs[:, 0], 2)
    np.testing.assert_allclose(rm.errors, 0.2, atol=1e-12)
    rot = M.rpe(ref, est, delta=1, relation="rotation_angle_deg")
    np.testing.assert_allclose(rot.errors, 0.0, atol=1e-12)


def test_pairs_by_path_matches_definition():
    p = np.c_[[0, 0.04, 0.08, 0.13, 0.2, 0.21, 0.3], np.zeros(7), np.zeros(7)]
    # consecutive: path since last chosen pose reaches 0.1 at poses 3 (0.13) and 6 (0.17)
    np.testing.assert_array_equal(M.pairs_by_path(p, 0.1), [[0, 3], [3, 6]])
    # all pairs: for each i the j > i whose path distance is nearest 0.1, kept if within 0.012
    # (i=0: 0.08 -> off by 0.02; i=1: 0.09; i=2: 0.12; i=3: 0.08; i=4: 0.10; i=5: 0.09)
    np.testing.assert_array_equal(M.pairs_by_path(p, 0.1, 0.012, all_pairs=True), [[1, 3], [4, 6], [5, 6]])


# ---------------------------------------------------------------------------------------------
# invariances


def test_se3_ate_invariant_to_rigid_motion_of_estimate():
    ref, est = synthetic_pair(seed=1)
    base = M.ate(ref, est, "se3")
    base_rot = M.ape(ref, est, "rotation_angle_deg", "se3")
    base_rpe = M.rpe(ref, est, delta=3)
    rng = np.random.default_rng(42)
    for _ in range(3):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = random_rotation(rng), rng.normal(scale=5.0, size=3)
        moved = est.transformed(T)
        assert abs(M.ate(ref, moved, "se3").rmse - base.rmse) < 1e-9
        assert abs(M.ape(ref, moved, "rotation_angle_deg", "se3").rmse - base_rot.rmse) < 1e-9
        assert abs(M.rpe(ref, moved, delta=3).rmse - base_rpe.rmse) < 1e-9   # RPE needs no alignment
        assert M.ate(ref, moved, "none").rmse > 10 * base.rmse                # the motion did matter


def test_sim3_ate_invariant_to_similarity_of_estimate():
    ref, est = synthetic_pair(seed=2)
    base = M.ate(ref, est, "sim3").rmse
    rng = np.random.default_rng(7)
    for s in (0.25, 3.0):
        moved = apply_sim3(est, random_rotation(rng), rng.normal(size=3), s)
        r = M.ate(ref, moved, "sim3")
        assert abs(r.rmse - base) < 1e-9
        assert M.ate(ref, moved, "se3").rmse > 2 * base                       # scale matters for se3


def test_umeyama_matches_evo_and_recovers_similarity():
    geometry = pytest.importorskip("evo.core.geometry")
    rng = np.random.default_rng(5)
    X = rng.normal(size=(3, 30))
    Rk, tk, sk = random_rotation(rng), rng.normal(size=3), 1.7
    Y = sk * Rk @ X + tk[:, None]
    R, t, s = M.umeyama_alignment(X, Y, with_scale=True)
    np.testing.assert_allclose(R, Rk, atol=1e-12)
    np.testing.assert_allclose(t, tk, atol=1e-12)
    assert s == pytest.approx(sk, rel=1e-12)
    Yn = Y + rng.normal(scale=0.05, size=Y.shape)
    for scale in (False, True):
        ours, theirs = M.umeyama_alignment(X, Yn, scale), geometry.umeyama_alignment(X, Yn, scale)
        for a, b in zip(ours, theirs):
            np.testing.assert_allclose(a, b, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# bad input


def test_no_association_names_both_trajectories():
    ref = traj_from_positions(SQUARE)
    est = traj_from_positions(SQUARE, t0=100.0)
    with pytest.raises(RealgapError, match=r"no associated poses between gt\.txt .* and est\.txt"):
        M.ate(ref, est, ref_name="gt.txt", est_name="est.txt")


def test_too_few_pairs_and_degenerate_alignment():
    ref = traj_from_positions(SQUARE)
    est = traj_from_positions(SQUARE[:2])
    with pytest.raises(RealgapError, match="at least 3 associated poses"):
        M.ate(ref, est, align="se3")
    assert M.ate(ref, est, align="origin").pairs == 2          # origin alignment needs one pair
    line = traj_from_positions(np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)])
    with pytest.raises(RealgapError, match="degenerate"):
        M.ate(line, line, align="se3")
    with pytest.raises(ConfigError, match="unknown alignment"):
        M.ate(ref, ref, align="affine")
    with pytest.raises(ConfigError, match="integer"):
        M.rpe(ref, ref, delta=1.5)
    with pytest.raises(RealgapError, match="no pose pairs"):
        M.rpe(ref, ref, delta=10)


def test_read_tum_drops_duplicate_timestamps_like_evo(tmp_path):
    """FORMATS.md section 5: the first pose of a repeated timestamp is kept, one warning names the
    file, the timestamp and the line; strict mode makes it an error."""
    p = tmp_path / "dup.txt"
    p.write_text("# c\n1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n2.0 5 0 0 0 0 0 1\n2.0 6 0 0 0 0 0 1\n"
                 "3.0 2 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match="duplicated timestamp"):
        read_tum(p, drop_duplicate_timestamps=False)
    with pytest.warns(UserWarning, match=r"dup\.txt: line 4: timestamp 2\.000000 repeats .* \(and 1 more\)"):
        t = read_tum(p)
    np.testing.assert_array_equal(t.timestamps, [1, 2, 3])
    np.testing.assert_array_equal(t.positions[:, 0], [0, 1, 2])      # the first one is kept
    ok = _write(tmp_path / "ok.txt", "1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")                               # nothing dropped: no warning
        assert len(read_tum(ok, drop_duplicate_timestamps=True)) == 2
    bad = tmp_path / "bad.txt"
    bad.write_text("1.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"bad\.txt: line 3: expected 8 values"):
        read_tum(bad, drop_duplicate_timestamps=True)
    unsorted = _write(tmp_path / "unsorted.txt", "2.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match="not sorted"):                # other checks still apply
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read_tum(unsorted, drop_duplicate_timestamps=True)


def _write(path, text):
    path.write_text(text)
    return path


def test_eval_config_validation():
    assert M.EvalConfig.from_dict(M.PRESETS["evo"].to_dict()).max_dt == 0.01
    with pytest.raises(ConfigError, match="unknown evaluation option"):
        M.EvalConfig.from_dict({"maxdt": 1})
    with pytest.raises(ConfigError, match="delta unit"):
        M.EvalConfig(delta_unit="s").validate()


# ---------------------------------------------------------------------------------------------
# result round trip


def test_metric_result_save_load_round_trip(tmp_path):
    ref, est = synthetic_pair(seed=4)
    for res in (M.ate(ref, est, "sim3"), M.rpe(ref, est, delta=2, relation="rotation_angle_deg")):
        d = json.loads(res.to_json())
        for k in M.STAT_KEYS + ("pairs", "align", "unit", "info"):
            assert k in d
        folder = res.save(tmp_path / res.metric)
        for name in ("stats.json", "info.json", "errors.npy", "estimate_aligned.txt"):
            assert (folder / name).is_file()
        back = M.MetricResult.load(folder)
        assert back.stats == res.stats                                   # exact via JSON floats
        np.testing.assert_array_equal(back.errors, res.errors)
        np.testing.assert_array_equal(back.timestamps, res.timestamps)
        assert (back.metric, back.relation, back.unit, back.pairs) == (res.metric, res.relation, res.unit, res.pairs)
        np.testing.assert_allclose(back.alignment.matrix, res.alignment.matrix, atol=0)
        np.testing.assert_allclose(back.aligned.poses, res.aligned.poses, atol=1e-7)   # 9 digits in TUM
        np.testing.assert_allclose(back.aligned.timestamps, res.aligned.timestamps, atol=1e-6)
        if res.index_pairs is not None:
            np.testing.assert_array_equal(back.index_pairs, res.index_pairs)
        # the saved trajectories reproduce the metric
        assert M.ate(back.reference, back.aligned, "none").rmse == pytest.approx(
            M.ate(res.reference, res.aligned, "none").rmse, abs=1e-7)
    with pytest.raises(FormatError, match="not a metric result folder"):
        M.MetricResult.load(tmp_path)


# ---------------------------------------------------------------------------------------------
# cross-check with evo on its own test trajectories

FR1 = ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt")
FR2 = ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt")


@pytest.fixture(scope="module")
def evo_mods():
    pytest.importorskip("evo")
    from evo.core import metrics as em, sync
    from evo.core.trajectory import PoseTrajectory3D
    from evo.main_ape import ape as evo_ape
    from evo.main_rpe import rpe as evo_rpe
    from evo.tools import file_interface
    return dict(metrics=em, sync=sync, PoseTrajectory3D=PoseTrajectory3D, ape=evo_ape, rpe=evo_rpe,
                read=file_interface.read_tum_trajectory_file)


_cache: dict = {}


def _load(names):
    """(ours_ref, ours_est, path_ref, path_est); fr2/desk ground truth repeats one timestamp."""
    if names not in _cache:
        pr, pe = (shared_path("evo_trajectories", n) for n in names)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _cache[names] = (read_tum(pr, drop_duplicate_timestamps=True), read_tum(pe), pr, pe)
    return _cache[names]


def _evo_align_kw(mode):
    return dict(align=mode in ("se3", "sim3"), correct_scale=mode == "sim3", align_origin=mode == "origin")


def _to_evo(evo_mods, traj):
    return evo_mods["PoseTrajectory3D"](poses_se3=list(traj.poses), timestamps=traj.timestamps.copy())


def test_reference_numbers():
    ref, est, _, _ = _load(FR1)
    assert round(M.ate(ref, est, "se3", max_dt=0.02).rmse, 6) == 0.013473
    assert round(M.ate(ref, est, "se3", max_dt=0.01).rmse, 6) == 0.013470
    ref, est, _, _ = _load(FR2)
    assert M.ate(ref, est, "se3", max_dt=0.02).rmse == pytest.approx(0.0081, abs=1e-4)


@pytest.mark.parametrize("names", [FR1, FR2], ids=["fr1_xyz", "fr2_desk"])
@pytest.mark.parametrize("max_dt", [0.01, 0.02])
def test_association_matches_evo(evo_mods, names, max_dt):
    ref, est, pr, pe = _load(names)
    eref, eest = evo_mods["read"](str(pr)), evo_mods["read"](str(pe))
    sref, sest = evo_mods["sync"].associate_trajectories(eref, eest, max_diff=max_dt)
    ia, ib = associate(ref.timestamps, est.timestamps, max_dt)
    ours = set(zip(ref.timestamps[ia].tolist(), est.timestamps[ib].tolist()))
    theirs = list(zip(sref.timestamps.tolist(), sest.timestamps.tolist()))
    if names == FR2 and max_dt == 0.02:
        # evo matches each estimate pose to its nearest ground-truth pose, so across a gap in the
        # ground truth one ground-truth pose serves two estimate poses; ours is one-to-one.
        extra = [p for p in theirs if p not in ours]
        assert ours <= set(theirs) and len(theirs) == len(ours) + len(extra) == 2225
        gt_used = [p[0] for p in theirs]
        assert extra and all(gt_used.count(p[0]) == 2 for p in extra)
    else:
        assert len(ours) == len(theirs) and ours == set(theirs)


@pytest.mark.parametrize("names", [FR1, FR2], ids=["fr1_xyz", "fr2_desk"])
@pytest.mark.parametrize("mode", ["se3", "sim3", "origin", "none"])
def test_ape_matches_evo_end_to_end(evo_mods, names, mode):
    """evo reads, associates (its own code, 0.01 s where the associations agree) and computes."""
    ref, est, pr, pe = _load(names)
    em = evo_mods["metrics"]
    if ("evo", names) not in _cache:
        _cache["evo", names] = evo_mods["sync"].associate_trajectories(
            evo_mods["read"](str(pr)), evo_mods["read"](str(pe)), max_diff=0.01)
    eref, eest = _cache["evo", names]
    for rel, erel in (("translation", em.PoseRelation.translation_part),
                      ("rotation_angle_deg", em.PoseRelation.rotation_angle_deg)):
        theirs = evo_mods["ape"](_copy(eref), _copy(eest), erel, **_evo_align_kw(mode))
        ours = M.ape(ref, est, rel, mode, max_dt=0.01)
        assert ours.pairs == eref.num_poses
        for k in M.STAT_KEYS:
            assert abs(ours.stats[k] - theirs.stats[k]) < 1e-9, (rel, k)
        np.testing.assert_allclose(ours.errors, theirs.np_arrays["error_array"], atol=1e-9)


def _copy(traj):
    import copy
    return copy.deepcopy(traj)


@pytest.mark.parametrize("names", [FR1, FR2], ids=["fr1_xyz", "fr2_desk"])
@pytest.mark.parametrize("mode", ["se3", "sim3", "origin"])
def test_ate_matches_evo_on_same_pairs_at_tum_max_dt(evo_mods, names, mode):
    ref, est, _, _ = _load(names)
    r, e = M.associate_trajectories(ref, est, 0.02)
    theirs = evo_mods["ape"](_to_evo(evo_mods, r), _to_evo(evo_mods, e),
                             evo_mods["metrics"].PoseRelation.translation_part, **_evo_align_kw(mode))
    ours = M.ate(ref, est, mode, max_dt=0.02)
    assert abs(ours.rmse - theirs.stats["rmse"]) < 1e-9
    np.testing.assert_allclose(ours.alignment.matrix, theirs.np_arrays["alignment_transformation_sim3"], atol=1e-9)


@pytest.mark.parametrize("names", [FR1, FR2], ids=["fr1_xyz", "fr2_desk"])
@pytest.mark.parametrize("delta,unit,all_pairs,mode", [(1, "frames", False, "none"), (10, "frames", True, "none"),
                                                       (0.1, "m", False, "none"), (0.1, "m", True, "sim3")])
def test_rpe_matches_evo(evo_mods, names, delta, unit, all_pairs, mode):
    ref, est, _, _ = _load(names)
    em = evo_mods["metrics"]
    r, e = M.associate_trajectories(ref, est, 0.02)
    for rel, erel in (("translation", em.PoseRelation.translation_part),
                      ("rotation_angle_deg", em.PoseRelation.rotation_angle_deg)):
        theirs = evo_mods["rpe"](_to_evo(evo_mods, r), _to_evo(evo_mods, e), erel, delta=delta,
                                 delta_unit=em.Unit.frames if unit == "frames" else em.Unit.meters,
                                 all_pairs=all_pairs, **_evo_align_kw(mode))
        ours = M.rpe(ref, est, delta, unit, rel, all_pairs, align=mode, max_dt=0.02)
        assert len(ours.errors) == len(theirs.np_arrays["error_array"])
        assert abs(ours.rmse - theirs.stats["rmse"]) < 1e-9, rel
        np.testing.assert_allclose(ours.timestamps, theirs.np_arrays["timestamps"])
