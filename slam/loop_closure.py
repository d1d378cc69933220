"""Loop closure after tracking: keyframes, ORB loop candidates, dense ICP verification, a pose
graph, and the TSDF fused again with the corrected poses.

Run by :func:`slam.pipeline.run_slam` once every frame is tracked (online backends listed in
``LoopClosureConfig.backends``):

1. *Keyframes*: the first tracked frame, then every tracked frame that moved more than
   ``keyframe_trans_m`` or turned more than ``keyframe_rot_deg`` from the last keyframe
   (odometry poses).
2. *Candidates*: for each keyframe j, the earlier keyframes i at least ``min_separation_s`` before
   it ranked by ORB matches (Lowe's ratio test) between their colour images; the best
   ``candidates_per_keyframe`` with ``min_matches`` matches or more are candidates. Sequences
   without colour use the odometry instead: earlier keyframes within ``proximity_m`` looking the
   same way (within 30 degrees).
3. *Verification* (:mod:`slam.loop_verify`): dense point-to-plane ICP of j's depth onto i's,
   started from an ORB/PnP guess (else from the odometry's relative pose), with the tracker's
   kind of failure checks (correspondences, fitness, RMS residual), an information check and a
   consistency check against the drift the odometry could have accumulated in between.
4. *Pose graph* (:mod:`slam.pose_graph`): odometry edges between consecutive keyframes, verified
   loops as uncertain edges; Open3D's global optimisation with its line process prunes loops that
   disagree with the rest. Every tracked frame is then moved with its keyframes' correction.
5. *Map*: the TSDF is *re-integrated* from scratch with the corrected poses (every tracked frame
   read and fused again), not deformed: a TSDF stores no per-frame contributions to move, and a
   second fusion pass costs about what the first fusion did, well under the tracking's cost.
   Nothing is recomputed when no loop survives: the odometry poses and the map stay as they were.

The odometry trajectory is kept as ``RUN/trajectory_odometry.txt`` when loops changed the poses;
``stats.json['loop_closure']`` reports keyframes, candidates, rejections by reason, the closures
kept, and (when the sequence has ground truth) ATE before and after and the number of *false*
closures: a kept loop off the ground truth's relative pose by more than ``false_closure_m`` or
``false_closure_deg`` (``closures_off_reference``) *and* by as much off the alignment the two
depth images give when registered from that relative pose (the depth's own answer at the true
place). The second condition matters for references that are estimates themselves: 7-Scenes'
KinectFusion poses jump by up to 4 cm against the depth within two frames
(``benchmarks/bench_reference_consistency.py --short 2``), so a loop that agrees with the depth
can sit centimetres off them; a loop in the wrong place or the wrong basin is off both.
"""
from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from data_tools.errors import ConfigError
from data_tools.geometry import rotation_angle_rad
from slam.registration import check_positive


@dataclass
class LoopClosureConfig:
    """Loop-closure options (``slam run --loop-closure.NAME VALUE``)."""

    enabled: bool = False
    """Close loops after tracking (for the backends in ``backends``); false leaves the odometry
    poses and the map exactly as tracked. Off by default: on 7-Scenes chess (the KinectFusion
    reference) the closures it finds move the trajectory by about as much as the odometry is off,
    ATE 2.90 -> 3.06 cm on 1000 frames with refined loops (none of them false), at the cost of a
    second fusion pass; its reference is itself off by about 3 cm where it revisits a place and
    jumps by up to 4 cm against the depth within two frames (docs/slam.md)."""
    backends: tuple[str, ...] = ("icp",)
    """Backends whose runs get loop closure when ``enabled``."""
    keyframe_trans_m: float = 0.15
    """A tracked frame that moved more than this from the last keyframe becomes a keyframe, metres."""
    keyframe_rot_deg: float = 15.0
    """... or turned more than this, degrees."""
    min_separation_s: float = 5.0
    """Loop candidates are at least this far apart in time, seconds (nearer ones are odometry)."""
    candidates_per_keyframe: int = 3
    """Candidates verified per keyframe (the earlier keyframes with the most ORB matches)."""
    max_compared: int = 24
    """ORB matching compares each keyframe with at most this many earlier keyframes: those nearest
    to it by the odometry (distance plus 0.5 m per radian of viewing direction), so the search grows
    linearly with the keyframes, not quadratically; 0 = compare with every earlier keyframe. The
    odometry drifts by centimetres over a loop, far less than the spacing of 24 keyframes."""
    orb_features: int = 800
    """ORB key points per keyframe colour image."""
    min_matches: int = 40
    """Fewest ORB matches (ratio test 0.8) for a pair to be a candidate."""
    pnp_min_inliers: int = 20
    """Fewest PnP RANSAC inliers for the ORB pose guess (else the odometry's guess is used)."""
    proximity_m: float = 0.5
    """Without colour images: candidate keyframes within this distance (odometry poses), metres."""
    voxel_m: float = 0.04
    """Voxel size of the keyframe point clouds registered by the verification ICP, metres."""
    max_correspondence_m: tuple[float, ...] = (0.12, 0.06, 0.03)
    """Largest point distance of an ICP correspondence per verification stage, coarse to fine, metres."""
    icp_iterations: int = 20
    """Maximum ICP iterations per stage."""
    min_correspondences: int = 300
    """Reject a loop with fewer inlier correspondences at the finest stage."""
    min_fitness: float = 0.4
    """Reject a loop when fewer than this fraction of the later keyframe's points have a partner."""
    max_rmse_m: float = 0.015
    """Reject a loop whose inlier RMS distance is larger, metres."""
    min_constraint: float = 0.02
    """Reject a loop whose correspondences do not pin every translation direction: the smallest
    eigenvalue of the translation information per correspondence (0 = one plane, 1/3 = three
    orthogonal planes) below this."""
    max_drift_m: float = 0.1
    """Reject a loop that asks the odometry for a larger translation correction than this plus
    ``max_drift_per_m`` times the path between the keyframes, metres."""
    max_drift_per_m: float = 0.05
    """Translation drift allowed per metre of path, metres (5 %)."""
    max_drift_deg: float = 5.0
    """Reject a loop that asks for a larger rotation correction than this plus
    ``max_drift_deg_per_m`` times the path, degrees."""
    max_drift_deg_per_m: float = 2.0
    """Rotation drift allowed per metre of path, degrees."""
    line_process_m: float = 0.1
    """Scale of the pose graph's line process, metres (Open3D's ``max_correspondence_distance`` of
    the global optimisation): a loop edge whose alignment the optimum leaves off by much more than
    about this is weighed down and pruned. Larger than the ICP's finest distance: the residual
    misalignment of true loops is the drift spread over the odometry, centimetres."""
    edge_prune_threshold: float = 0.25
    """Line-process weight under which the pose graph drops a loop edge (Open3D's option)."""
    preference_loop_closure: float = 2.0
    """Weight of the loop edges against the odometry in the pose graph (Open3D's option)."""
    refine: bool = True
    """Refine each loop that passed verification with the tracker's projective point-to-plane ICP
    on the two keyframes' depth images (:func:`slam.loop_verify.refine_loop`, 1.5 cm finest
    distance) and keep it only when the refinement agrees with the verification within
    ``refine_agree_m`` / ``refine_agree_deg`` and fits (fitness >= ``min_fitness``, RMS residual
    <= ``refine_max_rmse_m``)."""
    refine_agree_m: float = 0.03
    """Largest translation between the verified and the refined loop transform, metres."""
    refine_agree_deg: float = 2.0
    """Largest rotation between the verified and the refined loop transform, degrees."""
    refine_max_rmse_m: float = 0.01
    """Largest RMS point-to-plane residual of the refined loop, metres (the inliers lie within
    1.5 cm, so even a good loop between two noisy Kinect frames leaves 6-7 mm)."""
    false_closure_m: float = 0.05
    """With ground truth: a kept loop off the true relative pose by more than this, and as far off
    the depth's alignment started from the true relative pose, is counted false, metres."""
    false_closure_deg: float = 3.0
    """... or by more than this, degrees."""

    def validate(self) -> "LoopClosureConfig":
        check_positive(self, "refine_agree_m", "refine_agree_deg", "refine_max_rmse_m")
        check_positive(self, "keyframe_trans_m", "keyframe_rot_deg", "candidates_per_keyframe", "orb_features",
                       "min_matches", "voxel_m", "icp_iterations", "max_rmse_m", "proximity_m", "line_process_m",
                       "false_closure_m", "false_closure_deg")
        check_positive(self, "min_separation_s", "max_compared", "pnp_min_inliers", "min_correspondences", "min_fitness",
                       "min_constraint", "max_drift_m", "max_drift_per_m", "max_drift_deg", "max_drift_deg_per_m",
                       "edge_prune_threshold", "preference_loop_closure", allow_zero=True)
        if not self.max_correspondence_m or any(not (d > 0) for d in self.max_correspondence_m):
            raise ConfigError("LoopClosureConfig.max_correspondence_m needs one or more distances > 0")
        return self

    def applies_to(self, backend: str) -> bool:
        """True when a run of ``backend`` gets loop closure."""
        return bool(self.enabled) and backend in self.backends


@dataclass
class Keyframe:
    """A keyframe of the odometry trajectory."""

    row: int
    """Position in the run's frame list (records / poses)."""
    index: int
    """Frame index in the sequence."""
    timestamp: float
    pose: np.ndarray
    """(4, 4) odometry camera-to-world pose."""
    path_m: float
    """Length of the odometry path from the first tracked frame to this one, metres."""
    cloud: object = None
    """Open3D point cloud of the depth (camera frame; :func:`slam.loop_verify.keyframe_cloud`)."""
    features: object = None
    """ORB (key points, descriptors) of the colour image, or None without colour."""
    depth: np.ndarray | None = None


def select_keyframes(timestamps, poses, trans_m: float, rot_deg: float) -> list[tuple[int, float]]:
    """(row, path length) of the keyframes among ``poses`` (rows with None are failed frames):
    the first tracked one, then each that moved ``trans_m`` or turned ``rot_deg`` from the last."""
    out, last, prev, path = [], None, None, 0.0
    for row, P in enumerate(poses):
        if P is None:
            continue
        if prev is not None:
            path += float(np.linalg.norm(P[:3, 3] - prev[:3, 3]))
        prev = P
        if last is None or np.linalg.norm(P[:3, 3] - last[:3, 3]) > trans_m or \
                math.degrees(rotation_angle_rad(last[:3, :3].T @ P[:3, :3])) > rot_deg:
            out.append((row, path))
            last = P
    return out


def _orb_match_count(fa, fb, ratio: float = 0.8) -> int:
    import cv2
    if fa is None or fb is None or fa[1] is None or fb[1] is None or len(fa[1]) < 2 or len(fb[1]) < 2:
        return 0
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(fb[1], fa[1], k=2)
    return sum(1 for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance)


def _view_distance(Pa: np.ndarray, Pb: np.ndarray) -> float:
    """Distance of two camera poses for the candidate search: metres between the centres plus
    0.5 m per radian between the viewing directions."""
    cos = float(np.clip(Pa[:3, 2] @ Pb[:3, 2], -1.0, 1.0))
    return float(np.linalg.norm(Pa[:3, 3] - Pb[:3, 3])) + 0.5 * math.acos(cos)


def find_candidates(kfs: list[Keyframe], c: LoopClosureConfig) -> list[tuple[int, int, int]]:
    """(i, j, score) loop candidates, i < j keyframe numbers, j's best ``candidates_per_keyframe``
    earlier keyframes by ORB matches (or by odometry proximity without colour: score 0), among the
    ``max_compared`` earlier keyframes nearest to j."""
    out = []
    for j, kj in enumerate(kfs):
        scored = []
        pool = [i for i in range(j) if kj.timestamp - kfs[i].timestamp >= c.min_separation_s]
        if c.max_compared and len(pool) > c.max_compared:
            pool = sorted(pool, key=lambda i: (_view_distance(kfs[i].pose, kj.pose), i))[: c.max_compared]
            pool.sort()
        for i in pool:
            ki = kfs[i]
            if kj.features is not None and ki.features is not None:
                n = _orb_match_count(ki.features, kj.features)
                if n >= c.min_matches:
                    scored.append((n, i))
            else:
                d = float(np.linalg.norm(kj.pose[:3, 3] - ki.pose[:3, 3]))
                cos = float(ki.pose[:3, 2] @ kj.pose[:3, 2])
                if d <= c.proximity_m and cos >= math.cos(math.radians(30.0)):
                    scored.append((-d, i))
        scored.sort(key=lambda s: (-s[0], s[1]))
        out += [(i, j, int(max(n, 0))) for n, i in scored[: c.candidates_per_keyframe]]
    return out


REJECTION_CATEGORIES = ("too few correspondences", "low fitness", "residual", "degenerate geometry",
                        "inconsistent with odometry", "refinement disagrees", "refinement residual")
"""Keys of ``stats.json['loop_closure']['rejected_by']`` (the check that rejected a candidate)."""


def _category(reason: str) -> str:
    return next((k for k in REJECTION_CATEGORIES if reason.startswith(k)), reason)


def _relative_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    E = np.linalg.inv(T_ref) @ T_est
    return float(np.linalg.norm(E[:3, 3])), math.degrees(rotation_angle_rad(E[:3, :3]))


def close_loops(reader, records: list[dict], poses: list, cfg, intr, progress: bool = False):
    """Close loops over a tracked run. ``records``/``poses`` are the pipeline's per-frame rows
    (poses as flat 16-lists, None for failed frames); ``cfg`` the run's SlamConfig.

    Returns (new poses in the same form, a new :class:`slam.tsdf.TSDFVolume` fused with them or
    None when nothing changed, the ``stats.json['loop_closure']`` dictionary)."""
    from data_tools.progress import progress_bar
    from slam.loop_verify import one_thread
    c = cfg.loop_closure
    t_start = time.perf_counter()
    P = [None if p is None else np.asarray(p, np.float64).reshape(4, 4) for p in poses]
    times = np.array([r["timestamp"] for r in records], np.float64)
    stats = {"keyframes": 0, "candidates": 0, "candidates_rejected": 0, "rejected_by": {},
             "closures_verified": 0, "closures": 0, "closure_pairs": [], "applied": False}
    volume = None
    with one_thread():       # bit-reproducible registration sums (slam/loop_verify.py)
        new_P = _close(reader, records, P, times, c, cfg.tsdf, intr, stats)
    stats["seconds_closing"] = time.perf_counter() - t_start
    if stats["applied"]:
        from slam.tsdf import TSDFVolume
        t0 = time.perf_counter()
        volume = TSDFVolume(cfg.tsdf)
        todo = [r for r, p in enumerate(new_P) if p is not None]
        bar = progress_bar(total=len(todo), desc="loop closure: re-integrating", unit="frame") if progress else None
        for r in todo:
            f = reader[records[r]["index"]]
            volume.integrate(f.depth, f.rgb, intr, new_P[r])
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        stats["seconds_reintegrating"] = time.perf_counter() - t0
    out = [None if p is None else np.asarray(p).reshape(-1).tolist() for p in new_P]
    return out, volume, stats


def _ground_truth_stats(reader, records, P_old, P_new, kfs, kept_loops, c: LoopClosureConfig, stats: dict,
                        intr=None, depth_range: tuple[float, float] = (0.1, 4.0)) -> None:
    """ATE (SE(3)-aligned RMSE, metres) before/after, the closures off the reference and the false
    closures (module docstring), when ``reader`` has ground truth; ``intr`` and ``depth_range``
    register the keyframes' depth from the reference's relative pose (None: no depth check, every
    loop off the reference counts false)."""
    if not getattr(reader, "has_groundtruth", False):
        return
    from data_tools.trajectory import Trajectory
    from slam.metrics import ate
    rows = [r for r, p in enumerate(P_old) if p is not None]
    ts = [records[r]["timestamp"] for r in rows]
    import warnings
    try:
        with warnings.catch_warnings():     # a short run's ill-conditioned alignment: not the user's concern here
            warnings.simplefilter("ignore")
            stats["ate_before_m"] = ate(reader.groundtruth, Trajectory(ts, [P_old[r] for r in rows])).rmse
            stats["ate_after_m"] = ate(reader.groundtruth, Trajectory(ts, [P_new[r] for r in rows])).rmse
    except Exception as e:     # too few associated poses: report why instead of failing the run
        stats["ate_error"] = str(e)
    false = off = 0
    gt = reader.poses if hasattr(reader, "poses") else None
    if gt is not None:
        from slam.loop_verify import refine_loop
        for i, j, v in kept_loops:
            Gi, Gj = gt[kfs[i].index], gt[kfs[j].index]
            if not (np.all(np.isfinite(Gi)) and np.all(np.isfinite(Gj))):
                continue
            G_rel = np.linalg.inv(Gi) @ Gj
            dt, da = _relative_error(v.transformation, G_rel)
            if not (dt > c.false_closure_m or da > c.false_closure_deg):
                continue
            off += 1
            if intr is not None and kfs[i].depth is not None and kfs[j].depth is not None:
                T_depth = refine_loop(kfs[j].depth, kfs[i].depth, intr, G_rel, *depth_range)[0]
                dt, da = _relative_error(v.transformation, T_depth)
                if not (dt > c.false_closure_m or da > c.false_closure_deg):
                    continue
            false += 1
        stats["false_closures"] = false
        stats["closures_off_reference"] = off



def _close(reader, records, P, times, c: LoopClosureConfig, tsdf, intr, stats: dict) -> list:
    """Steps 1-4 of the module docstring; fills ``stats``, returns the corrected poses (``P`` itself
    when no loop survives)."""
    from slam.backends._features import orb_features, pnp_guess
    from slam.loop_verify import information_matrix, keyframe_cloud, odometry_consistency, refine_loop, verify_loop
    from slam.pose_graph import GraphEdge, interpolate_corrections, optimise_pose_graph
    new_P = P
    sel = select_keyframes(times, P, c.keyframe_trans_m, c.keyframe_rot_deg)
    stats["keyframes"] = len(sel)
    if len(sel) < 2 or times[sel[-1][0]] - times[sel[0][0]] < c.min_separation_s:
        return P            # no two keyframes far enough apart in time: no candidate, nothing to read
    kfs: list[Keyframe] = []
    for row, path in sel:
        f = reader[records[row]["index"]]
        kf = Keyframe(row, int(records[row]["index"]), float(times[row]), P[row], path)
        kf.cloud = keyframe_cloud(f.depth, intr, tsdf.depth_min_m, tsdf.depth_max_m, c.voxel_m)
        kf.features = orb_features(f.rgb, c.orb_features) if f.rgb is not None else None
        kf.depth = f.depth
        kfs.append(kf)
    stats["keyframes"] = len(kfs)
    cands = find_candidates(kfs, c)
    stats["candidates"] = len(cands)
    rejected: Counter = Counter()
    loops: list[tuple[int, int, object]] = []
    fine = float(c.max_correspondence_m[-1])
    for i, j, _score in cands:
        ki, kj = kfs[i], kfs[j]
        T_odo = np.linalg.inv(ki.pose) @ kj.pose          # camera j -> camera i by the odometry
        init = T_odo
        if ki.features is not None and kj.features is not None:
            g = pnp_guess(ki.features, ki.depth, kj.features, intr, c.pnp_min_inliers)
            if g is not None:
                init = g.T_cur_to_kf
        v = verify_loop(kj.cloud, ki.cloud, init, tuple(c.max_correspondence_m), c.icp_iterations,
                        c.min_correspondences, c.min_fitness, c.max_rmse_m, c.min_constraint)
        reason = v.reason or odometry_consistency(v.transformation, T_odo, kj.path_m - ki.path_m, c.max_drift_m,
                                                  c.max_drift_per_m, c.max_drift_deg, c.max_drift_deg_per_m)
        if not reason and c.refine:
            T_ref, fit, rmse = refine_loop(kj.depth, ki.depth, intr, v.transformation, tsdf.depth_min_m,
                                           tsdf.depth_max_m)
            dt, da = _relative_error(T_ref, v.transformation)
            if not (dt <= c.refine_agree_m and da <= c.refine_agree_deg):
                reason = f"refinement disagrees ({dt * 100:.1f} cm, {da:.1f} deg)"
            elif not (fit >= c.min_fitness and rmse <= c.refine_max_rmse_m):
                reason = f"refinement residual (fitness {fit:.2f}, {rmse * 1000:.1f} mm)"
            else:
                v.transformation = T_ref
        if reason:
            rejected[_category(reason)] += 1
            continue
        loops.append((i, j, v))
    stats["candidates_rejected"] = int(sum(rejected.values()))
    stats["rejected_by"] = dict(sorted(rejected.items()))
    stats["closures_verified"] = len(loops)
    if loops:
        edges = []
        for k in range(len(kfs) - 1):
            a, b = kfs[k], kfs[k + 1]
            T = np.linalg.inv(b.pose) @ a.pose
            info = information_matrix(a.cloud, b.cloud, T, fine) + np.eye(6)   # never singular
            edges.append(GraphEdge(k, k + 1, T, info))
        for i, j, v in loops:
            edges.append(GraphEdge(j, i, v.transformation, v.information, loop=True))
        new_kf, kept = optimise_pose_graph([k.pose for k in kfs], edges, c.line_process_m, c.edge_prune_threshold,
                                           c.preference_loop_closure)
        kept_set = set(kept)
        kept_loops = [(i, j, v) for i, j, v in loops if (j, i) in kept_set]
        stats["closures"] = len(kept_loops)
        stats["closure_pairs"] = [{"timestamps": [kfs[i].timestamp, kfs[j].timestamp], "fitness": v.fitness,
                                   "inlier_rmse": v.inlier_rmse} for i, j, v in kept_loops]
        if kept_loops:
            corr = np.stack([n @ np.linalg.inv(k.pose) for n, k in zip(new_kf, kfs)])
            rows = [r for r, p in enumerate(P) if p is not None]
            C = interpolate_corrections(times[rows], np.array([k.timestamp for k in kfs]), corr)
            new_P = list(P)
            for r, Ck in zip(rows, C):
                new_P[r] = Ck @ P[r]
            stats["applied"] = True
        _ground_truth_stats(reader, records, P, new_P, kfs, kept_loops, c, stats, intr,
                            (tsdf.depth_min_m, tsdf.depth_max_m))
    else:
        _ground_truth_stats(reader, records, P, P, kfs, [], c, stats)
    return new_P
