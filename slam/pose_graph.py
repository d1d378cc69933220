"""Keyframe pose graph (Open3D's global optimisation) and the correction of every frame's pose.

Nodes are the keyframes' camera-to-world poses. Consecutive keyframes are joined by *odometry*
edges (the tracker's relative pose; certain), verified loops by *loop* edges (uncertain: Open3D's
line process weighs each loop edge and prunes those below ``edge_prune_threshold``, so a wrong
loop that slipped through verification is switched off instead of bending the map). Open3D's
edge convention: an edge (s, t) carries T with ``pose_t @ T ~= pose_s`` (T maps points of camera
s into camera t). The first keyframe is held fixed (it defines the world frame, as the first
tracked frame does).

After the optimisation every tracked frame between keyframes k and k + 1 is moved by the
correction C = pose_new @ pose_old^-1 interpolated between the two keyframes' corrections by
time (rotation by slerp, translation linearly); frames after the last keyframe take its
correction. At the keyframes this is exact; in between it assumes the drift accumulated smoothly.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.tsdf import o3d_quiet


@dataclass
class GraphEdge:
    """One constraint between keyframes ``source`` and ``target`` (indices into the node list)."""

    source: int
    target: int
    transformation: np.ndarray
    """(4, 4): points of camera ``source`` into camera ``target``."""
    information: np.ndarray
    """(6, 6) information matrix (rotation first, then translation, as Open3D)."""
    loop: bool = False
    """True for a loop edge (uncertain: weighed and possibly pruned by the line process)."""


def optimise_pose_graph(poses: list[np.ndarray], edges: list[GraphEdge], max_correspondence_m: float,
                        edge_prune_threshold: float, preference_loop_closure: float
                        ) -> tuple[list[np.ndarray], list[tuple[int, int]]]:
    """(optimised camera-to-world poses, (source, target) of the loop edges kept after pruning).

    ``max_correspondence_m`` and ``preference_loop_closure`` set the line process's scale (Open3D's
    ``GlobalOptimizationOption``); runs on one Open3D thread for bit-reproducible results."""
    o3d = o3d_quiet()
    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    for P in poses:
        graph.nodes.append(reg.PoseGraphNode(np.asarray(P, np.float64)))
    for e in edges:
        graph.edges.append(reg.PoseGraphEdge(e.source, e.target, np.asarray(e.transformation, np.float64),
                                             np.asarray(e.information, np.float64), uncertain=e.loop))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=float(max_correspondence_m),
                                          edge_prune_threshold=float(edge_prune_threshold),
                                          preference_loop_closure=float(preference_loop_closure),
                                          reference_node=0)
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    finally:
        o3d.utility.set_max_threads(before)
    new = [np.asarray(n.pose).copy() for n in graph.nodes]
    kept = [(int(e.source_node_id), int(e.target_node_id)) for e in graph.edges if e.uncertain]
    return new, kept


def interpolate_corrections(times: np.ndarray, kf_times: np.ndarray, corrections: np.ndarray) -> np.ndarray:
    """(N, 4, 4) corrections at ``times`` from the (K, 4, 4) keyframe ``corrections`` at the sorted
    ``kf_times``: slerp of the rotations and linear translations between the two keyframes around
    each time; the first/last keyframe's correction outside their range."""
    from scipy.spatial.transform import Rotation, Slerp
    times = np.asarray(times, np.float64)
    kf_times = np.asarray(kf_times, np.float64)
    out = np.repeat(np.eye(4)[None], len(times), axis=0)
    if len(kf_times) == 1:
        out[:] = corrections[0]
        return out
    t = np.clip(times, kf_times[0], kf_times[-1])
    rot = Slerp(kf_times, Rotation.from_matrix(corrections[:, :3, :3]))(t)
    out[:, :3, :3] = rot.as_matrix()
    for a in range(3):
        out[:, a, 3] = np.interp(t, kf_times, corrections[:, a, 3])
    return out
