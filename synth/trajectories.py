"""Camera trajectory generators for synthetic sequences.

Every generator returns a :class:`data_tools.trajectory.Trajectory`: camera-to-world poses
(OpenCV axes: x right, y down, z forward; world z up), timestamps ``t0 + i / fps`` seconds.
Random choices come from ``numpy.random.default_rng(seed)``, so a trajectory is replayable
from its arguments.

* :func:`walkthrough` - a smooth hand-held-like path through a room at eye height that stays
  clear of all geometry and keeps looking at furniture/objects.
* :func:`orbit` - a circle (or arc) around a point, always looking at it.
* :func:`loop` - a closed walk around the room that comes back to its start and looks over the
  start again (a sequence for loop closure).
* :func:`planar` - a ground robot's path: the camera at a fixed height and pitch, moving on the
  floor plane with yaw turns (the setting of the neural memory, thesis 4.4.3).
* :func:`handheld_jitter` - smooth, temporally correlated pose noise added to a trajectory.

:data:`TRAJECTORY_KINDS` is the registry used by ``realgap synth sequence --trajectory``:
``f(scene, n_frames, seed, fps) -> Trajectory``.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from data_tools.errors import ConfigError, RealgapError
from data_tools.geometry import look_at
from data_tools.scene_spec import SceneSpec
from data_tools.trajectory import Trajectory

DEFAULT_FPS = 30.0
"""Frame rate of generated trajectories, frames per second."""

CONTENT_MAX_SIZE_M = 3.0
"""Meshes whose bounding-box diagonal is below this (metres) count as scene *content*
(furniture, objects) that cameras look at; larger ones (floor, walls, ceiling) are structure."""

FLAT_RATIO = 0.03
"""A mesh whose smallest bounding-box extent is below this fraction of its largest is *flat*
(posters, a table top alone); walkthroughs do not aim at flat content, whose views are nearly
planar and degenerate for geometric tracking."""


def _timestamps(n: int, fps: float, t0: float) -> np.ndarray:
    if n < 1:
        raise ConfigError(f"a trajectory needs at least 1 frame, got {n}")
    if not (fps > 0 and math.isfinite(fps)):
        raise ConfigError(f"fps must be positive, got {fps}")
    return t0 + np.arange(n) / float(fps)


def content_meshes(scene: SceneSpec, max_size_m: float = CONTENT_MAX_SIZE_M,
                   exclude_flat: bool = False) -> list[int]:
    """Indices of the meshes that are content (see :data:`CONTENT_MAX_SIZE_M`), optionally
    without flat ones (:data:`FLAT_RATIO`). Falls back to including flat content, then to all
    meshes, when nothing qualifies."""
    ext = [np.ptp(m.vertices, axis=0) for m in scene.meshes]
    small = [k for k, e in enumerate(ext) if np.linalg.norm(e) < max_size_m]
    if exclude_flat:
        solid = [k for k in small if ext[k].min() >= FLAT_RATIO * ext[k].max()]
        if solid:
            return solid
    return small or list(range(len(scene.meshes)))


def sample_surface_points(scene: SceneSpec, mesh_indices: list[int], n: int,
                          rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points drawn uniformly (by area) on the given meshes, metres."""
    tris = np.concatenate([scene.meshes[k].vertices[scene.meshes[k].triangles] for k in mesh_indices])
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    if area.sum() <= 0:
        raise RealgapError("scene content has zero surface area")
    pick = rng.choice(len(tris), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    return np.einsum("nk,nkd->nd", w, tris[pick])


def content_center(scene: SceneSpec) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), size (3,)) of the bounding box of the content meshes, metres."""
    idx = content_meshes(scene)
    v = np.concatenate([scene.meshes[k].vertices for k in idx])
    lo, hi = v.min(0), v.max(0)
    return (lo + hi) / 2, hi - lo


def _scene_bounds(scene: SceneSpec) -> tuple[np.ndarray, np.ndarray]:
    v = np.concatenate([m.vertices for m in scene.meshes])
    return v.min(0), v.max(0)


# --------------------------------------------------------------------------- orbit

def orbit(center, radius: float, height: float, n_frames: int, fps: float = DEFAULT_FPS,
          start_angle_rad: float = 0.0, arc_rad: float = 2 * math.pi, target=None,
          t0: float = 0.0) -> Trajectory:
    """Camera on a horizontal circle around ``center`` looking at ``target`` (default ``center``).

    The eye of frame i is ``center + (radius cos a_i, radius sin a_i, height)`` (``height``
    metres above ``center``), with a_i going from ``start_angle_rad`` over ``arc_rad``
    (counter-clockwise seen from above). A full circle (``arc_rad`` = 2 pi) does not repeat
    its first pose at the end; a partial arc includes both ends.
    """
    if not radius > 0:
        raise ConfigError(f"orbit radius must be positive, got {radius}")
    ts = _timestamps(n_frames, fps, t0)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    tgt = c if target is None else np.asarray(target, dtype=np.float64).reshape(3)
    full = abs(abs(arc_rad) - 2 * math.pi) < 1e-9
    steps = n_frames if full else max(n_frames - 1, 1)
    a = start_angle_rad + arc_rad * np.arange(n_frames) / steps
    eyes = c + np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n_frames, float(height))], axis=1)
    poses = np.stack([look_at(e, tgt) for e in eyes])
    return Trajectory(ts, poses)


# --------------------------------------------------------------------------- walkthrough

class _Clearance:
    """Distance from points to the scene's geometry (Open3D ``compute_distance``)."""

    def __init__(self, scene: SceneSpec):
        from synth.render import build_raycasting_scene
        self.rs, _ = build_raycasting_scene(scene)

    def distance(self, pts: np.ndarray) -> np.ndarray:
        import open3d as o3d
        p = np.ascontiguousarray(np.asarray(pts, dtype=np.float32).reshape(-1, 3))
        return self.rs.compute_distance(o3d.core.Tensor(p)).numpy()

    def enclosed(self, pts: np.ndarray) -> np.ndarray:
        """(N,) bool: rays towards +-x, +-y and +z from each point all hit geometry (the point
        is inside a room rather than outside its walls or in open space)."""
        import open3d as o3d
        p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=np.float64)
        rays = np.concatenate([np.repeat(p, 5, axis=0), np.tile(dirs, (len(p), 1))], axis=1).astype(np.float32)
        t = self.rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(-1, 5)
        return np.all(np.isfinite(t), axis=1)

    def ray_length(self, eye: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(N,) distance from ``eye`` to the first hit along unit ``dirs`` (N, 3), inf when none."""
        import open3d as o3d
        rays = np.concatenate([np.broadcast_to(eye, dirs.shape), dirs], axis=1).astype(np.float32)
        return self.rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()

    def visible(self, eye: np.ndarray, pts: np.ndarray, eps: float = 0.02) -> np.ndarray:
        """(N,) bool: nothing lies between ``eye`` and each point (bar the last ``eps`` m)."""
        import open3d as o3d
        d = pts - eye
        L = np.linalg.norm(d, axis=1)
        u = d / np.maximum(L, 1e-9)[:, None]
        rays = np.concatenate([np.broadcast_to(eye, d.shape), u], axis=1).astype(np.float32)
        t = self.rs.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        return t >= L - eps


def walkthrough(scene: SceneSpec, n_frames: int, seed: int = 0, fps: float = DEFAULT_FPS,
                height_range_m: tuple[float, float] = (1.2, 1.6), speed_mps: float = 0.35,
                clearance_m: float = 0.35, segment_s: float = 2.0, min_view_dist_m: float = 0.8,
                t0: float = 0.0, max_attempts: int = 30, max_turn_deg_s: float = 45.0) -> Trajectory:
    """A smooth walk through ``scene`` at eye height, looking at its content.

    The camera centre follows a natural cubic spline through control points ``segment_s``
    seconds apart, drawn as a random walk (steps of about ``speed_mps * segment_s`` metres,
    heading changes of ~45 deg) inside the scene's bounding box at heights
    ``height_range_m`` above the floor (the lowest scene point). Every sampled camera centre
    keeps ``clearance_m`` from all geometry (so no wall or furniture is crossed). The look-at
    target follows a second spline through points on non-flat content meshes
    (:func:`content_meshes`) that are visible from the matching control point and at least
    ``min_view_dist_m`` away. A path that fails the clearance test is redrawn (up to
    ``max_attempts`` times, then RealgapError). Consecutive look-at targets are preferably
    within 60 deg of each other as seen from the control point; a walk shorter than one
    ``segment_s`` (a few frames) limits that turn to ``max_turn_deg_s`` times its duration
    (turning towards a target by that much when none is within it), so it turns no faster
    than a long walk does. Longer walks are not affected by ``max_turn_deg_s``.
    """
    if not max_turn_deg_s > 0:
        raise ConfigError(f"walkthrough: max_turn_deg_s must be > 0, got {max_turn_deg_s}")
    ts = _timestamps(n_frames, fps, t0)
    rng = np.random.default_rng(seed)
    clear = _Clearance(scene)
    lo, hi = _scene_bounds(scene)
    floor = lo[2]
    z_lo = floor + height_range_m[0]
    z_hi = min(floor + height_range_m[1], hi[2] - clearance_m)
    if z_hi < z_lo:
        raise ConfigError(f"scene is too low ({hi[2] - floor:.2f} m) for camera heights {height_range_m}")
    xy_lo, xy_hi = lo[:2] + clearance_m, hi[:2] - clearance_m
    if np.any(xy_hi <= xy_lo):
        raise ConfigError("scene is too small for a walkthrough with this clearance")
    targets_pool = sample_surface_points(scene, content_meshes(scene, exclude_flat=True), 4000, rng)
    duration = ts[-1] - ts[0]
    n_ctrl = max(2, int(math.ceil(duration / segment_s)) + 1) if n_frames > 1 else 1
    step = speed_mps * (duration / max(n_ctrl - 1, 1))

    def free(p: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(p)
        inside = np.all((p[:, :2] >= xy_lo) & (p[:, :2] <= xy_hi), axis=1) & (p[:, 2] >= z_lo - 1e-9) \
            & (p[:, 2] <= z_hi + 1e-9)
        return inside & (clear.distance(p) >= clearance_m)

    def segment_free(a: np.ndarray, b: np.ndarray) -> bool:
        n = max(2, int(np.linalg.norm(b - a) / 0.05) + 1)
        s = np.linspace(0, 1, n)[:, None]
        return bool(np.all(free(a + s * (b - a))))

    for _attempt in range(max_attempts):
        # start: the free point among random candidates with the most room around it
        cand = np.column_stack([rng.uniform(xy_lo[0], xy_hi[0], 400), rng.uniform(xy_lo[1], xy_hi[1], 400),
                                rng.uniform(z_lo, z_hi, 400)])
        ok = free(cand)
        if not ok.any():
            raise RealgapError("walkthrough: no free space for the camera in this scene")
        cand = cand[ok]
        ctrl = [cand[np.argmax(clear.distance(cand))] if _attempt == 0 else cand[rng.integers(len(cand))]]
        heading = rng.uniform(0, 2 * math.pi)
        for _ in range(n_ctrl - 1):
            placed = False
            for trial in range(60):
                h = heading + rng.normal(0.0, 0.8 if trial < 30 else 2.0)
                L = step * rng.uniform(0.7, 1.3) * (1.0 if trial < 40 else 0.5)
                z = float(np.clip(ctrl[-1][2] + rng.normal(0.0, 0.1), z_lo, z_hi))
                p = np.array([ctrl[-1][0] + L * math.cos(h), ctrl[-1][1] + L * math.sin(h), z])
                if free(p)[0] and segment_free(ctrl[-1], p):
                    ctrl.append(p)
                    heading = h
                    placed = True
                    break
            if not placed:  # boxed in: stand still for this segment, turn around
                ctrl.append(ctrl[-1].copy())
                heading += math.pi
        ctrl = np.asarray(ctrl)
        # look-at targets: content points visible from each control point, not too close
        tg = []
        for k, e in enumerate(ctrl):
            d = np.linalg.norm(targets_pool - e, axis=1)
            cand_idx = np.flatnonzero((d >= min_view_dist_m) & (d <= 6.0))
            if len(cand_idx) == 0:
                cand_idx = np.arange(len(targets_pool))
            sub = rng.choice(cand_idx, size=min(200, len(cand_idx)), replace=False)
            vis = sub[clear.visible(e, targets_pool[sub])]
            pool = vis if len(vis) else sub
            if tg:  # prefer targets in a direction close to the previous one (smooth turning)
                prev = (tg[-1] - e) / max(np.linalg.norm(tg[-1] - e), 1e-9)
                dirs = targets_pool[pool] - e
                cosang = dirs @ prev / np.maximum(np.linalg.norm(dirs, axis=1), 1e-9)
                short = duration < segment_s
                max_turn = math.radians(min(60.0, max_turn_deg_s * duration) if short else 60.0)
                good = pool[cosang > math.cos(max_turn)]
                if len(good) == 0 and max_turn < math.radians(60.0):
                    # nothing within a short walk's turn: turn towards a target by the limit only
                    t = targets_pool[rng.choice(pool)]
                    dist = max(float(np.linalg.norm(tg[-1] - e)), min_view_dist_m)
                    tg.append(e + _turn_towards(prev, t - e, max_turn) * dist)
                    continue
                pool = good if len(good) else pool
            tg.append(targets_pool[rng.choice(pool)])
        tg = np.asarray(tg)
        eyes, looks = _spline(ctrl, ts), _spline(tg, ts)
        if not np.all(free(eyes)):
            continue
        if np.any(np.linalg.norm(looks - eyes, axis=1) < 0.3):
            continue
        poses = np.stack([look_at(e, t) for e, t in zip(eyes, looks)])
        return Trajectory(ts, poses)
    raise RealgapError(f"walkthrough: no collision-free path found in {max_attempts} attempts "
                       f"(try another seed or a smaller clearance)")


# --------------------------------------------------------------------------- loop

def loop(scene: SceneSpec, n_frames: int, seed: int = 0, fps: float = DEFAULT_FPS, turns: float = 1.15,
         outward_deg: float = -30.0, look_around_deg: float = 20.0, pitch_deg: float = -20.0,
         clearance_m: float = 0.35, height_m: float = 1.5, t0: float = 0.0) -> Trajectory:
    """A closed walk around the content centre (:func:`content_center`) that returns to its start.

    The eye goes ``turns`` times counter-clockwise around an ellipse (the last ``turns - 1`` of a
    turn revisits the start, so the views of the first frames are seen again); the ellipse is the
    largest one, up to 0.8 of the free half-extents of the scene's bounding box, whose every point
    keeps ``clearance_m`` from all geometry (inside a room it must also stay enclosed). The camera
    looks ``outward_deg`` away from the direction of travel towards the outside of the loop (walls
    and furniture at the walls, not the centre an orbit looks at: long views of nearly planar walls
    are what makes a tracker drift) plus a smooth +-``look_around_deg`` sway, ``pitch_deg`` down,
    ``height_m`` above the floor (the lowest scene point, capped under the ceiling). The seed sets
    the start angle, the aspect of the ellipse (+-10 %) and the sway's phase.
    """
    ts = _timestamps(n_frames, fps, t0)
    if not turns >= 1.0:
        raise ConfigError(f"loop: turns must be >= 1 (the walk must come back to its start), got {turns}")
    rng = np.random.default_rng(seed)
    clear = _Clearance(scene)
    center, _size = content_center(scene)
    lo, hi = _scene_bounds(scene)
    z = min(lo[2] + height_m, hi[2] - clearance_m) if hi[2] - lo[2] > 2 * clearance_m else lo[2] + height_m
    in_room = bool(clear.enclosed(np.array([center[0], center[1], z]))[0])
    half = np.minimum(center[:2] - lo[:2], hi[:2] - center[:2]) - clearance_m
    if np.any(half <= 0.1):
        raise ConfigError("loop: the scene is too small for a loop with this clearance")
    aspect = rng.uniform(0.9, 1.1, 2)
    start = float(rng.uniform(0, 2 * math.pi))
    phase = float(rng.uniform(0, 2 * math.pi))
    a = start + 2 * math.pi * turns * np.arange(n_frames) / max(n_frames - 1, 1)
    ring_a = np.linspace(0, 2 * math.pi, 240, endpoint=False)
    for s in np.linspace(0.8, 0.2, 25):
        r = np.minimum(half * aspect * s, half)
        ring = np.stack([center[0] + r[0] * np.cos(ring_a), center[1] + r[1] * np.sin(ring_a),
                         np.full_like(ring_a, z)], axis=1)
        if np.all(clear.distance(ring) >= clearance_m) and (not in_room or np.all(clear.enclosed(ring))):
            break
    else:
        raise RealgapError("loop: no collision-free closed path around the scene content")
    eyes = np.stack([center[0] + r[0] * np.cos(a), center[1] + r[1] * np.sin(a), np.full(n_frames, z)], axis=1)
    heading = np.arctan2(r[1] * np.cos(a), -r[0] * np.sin(a))      # direction of travel (d eye / d a)
    sway = math.radians(look_around_deg) * np.sin(3 * (a - start) + phase)
    yaw = heading - math.radians(outward_deg) + sway                # counter-clockwise: outside is right
    pitch = math.radians(pitch_deg)
    fwd = np.stack([np.cos(yaw) * math.cos(pitch), np.sin(yaw) * math.cos(pitch),
                    np.full(n_frames, math.sin(pitch))], axis=1)
    poses = np.stack([look_at(e, e + f) for e, f in zip(eyes, fwd)])
    return Trajectory(ts, poses)


def planar(scene: SceneSpec, n_frames: int, seed: int = 0, fps: float = DEFAULT_FPS, height_m: float = 1.0,
           pitch_deg: float = -10.0, speed_mps: float = 0.3, clearance_m: float = 0.4, segment_s: float = 2.0,
           look_around_deg: float = 40.0, t0: float = 0.0, max_attempts: int = 30) -> Trajectory:
    """A ground robot's path: the camera ``height_m`` above the floor (the lowest scene point) with a
    fixed ``pitch_deg`` (negative = looking down) and no roll, moving on the floor plane.

    The position follows a natural cubic spline through control points ``segment_s`` seconds apart,
    a random walk of steps ~``speed_mps * segment_s`` metres that keeps ``clearance_m`` from all
    geometry (as :func:`walkthrough`). The yaw is the direction of travel plus a smooth look-around
    offset (a spline through one offset per control point: the most open of 8 drawn uniformly in
    +-``look_around_deg``, i.e. the longest free view); where the robot stands still it turns by the
    offsets only. Poses differ from frame to frame only in x, y and yaw:
    height, pitch and roll are those of the first frame (what the neural backend assumes).
    """
    ts = _timestamps(n_frames, fps, t0)
    if not -89.0 < pitch_deg < 89.0:
        raise ConfigError(f"planar: pitch_deg must be within +-89, got {pitch_deg}")
    rng = np.random.default_rng(seed)
    clear = _Clearance(scene)
    lo, hi = _scene_bounds(scene)
    z = lo[2] + height_m
    if not lo[2] < z < hi[2] - 0.05 and hi[2] - lo[2] > 0.5:
        raise ConfigError(f"planar: camera height {height_m} m is outside the scene ({hi[2] - lo[2]:.2f} m tall)")
    xy_lo, xy_hi = lo[:2] + clearance_m, hi[:2] - clearance_m
    if np.any(xy_hi <= xy_lo):
        raise ConfigError("scene is too small for a planar path with this clearance")
    duration = ts[-1] - ts[0]
    n_ctrl = max(2, int(math.ceil(duration / segment_s)) + 1) if n_frames > 1 else 1
    step = speed_mps * (duration / max(n_ctrl - 1, 1))

    def free(p: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(p)
        inside = np.all((p[:, :2] >= xy_lo) & (p[:, :2] <= xy_hi), axis=1)
        return inside & (clear.distance(p) >= clearance_m)

    for _attempt in range(max_attempts):
        cand = np.column_stack([rng.uniform(xy_lo[0], xy_hi[0], 400), rng.uniform(xy_lo[1], xy_hi[1], 400),
                                np.full(400, z)])
        ok = free(cand)
        if not ok.any():
            raise RealgapError(f"planar: no free space {height_m} m above the floor in this scene")
        cand = cand[ok]
        ctrl = [cand[np.argmax(clear.distance(cand))] if _attempt == 0 else cand[rng.integers(len(cand))]]
        heading = rng.uniform(0, 2 * math.pi)
        for _ in range(n_ctrl - 1):
            for trial in range(60):
                h = heading + rng.normal(0.0, 0.8 if trial < 30 else 2.0)
                L = step * rng.uniform(0.7, 1.3) * (1.0 if trial < 40 else 0.5)
                p = np.array([ctrl[-1][0] + L * math.cos(h), ctrl[-1][1] + L * math.sin(h), z])
                n_s = max(2, int(np.linalg.norm(p - ctrl[-1]) / 0.05) + 1)
                seg = ctrl[-1] + np.linspace(0, 1, n_s)[:, None] * (p - ctrl[-1])
                if np.all(free(seg)):
                    ctrl.append(p)
                    heading = h
                    break
            else:       # boxed in: stand still for this segment, turn around
                ctrl.append(ctrl[-1].copy())
                heading += math.pi
        ctrl = np.asarray(ctrl)
        eyes = _spline(ctrl, ts)
        eyes[:, 2] = z
        if not np.all(free(eyes)):
            continue
        # yaw: direction of travel (kept while standing) + look-around offsets
        vel = np.gradient(eyes[:, :2], axis=0) if n_frames > 1 else np.zeros((1, 2))
        travel = np.full(n_frames, heading)
        moving = np.linalg.norm(vel, axis=1) > 1e-4
        if moving.any():
            yaw_m = np.unwrap(np.arctan2(vel[moving, 1], vel[moving, 0]))
            travel = np.interp(np.arange(n_frames), np.flatnonzero(moving), yaw_m)
        # look-around: at each control point the most open of 8 random offsets (the longest free
        # view along the camera's pitch, up to 4 m), so the robot looks into the room more than at walls
        pitch = math.radians(pitch_deg)
        knots = np.linspace(ts[0], ts[-1], len(ctrl)) if len(ctrl) > 1 else ts[:1]
        look = []
        for e, tk in zip(ctrl, knots):
            base = float(np.interp(tk, ts, travel))
            cand = np.radians(rng.uniform(-look_around_deg, look_around_deg, 8))
            a = base + cand
            dirs = np.stack([np.cos(a) * math.cos(pitch), np.sin(a) * math.cos(pitch), np.full(8, math.sin(pitch))], 1)
            look.append(cand[int(np.argmax(np.minimum(clear.ray_length(e, dirs), 4.0)))])
        yaw = travel + _spline(np.asarray(look)[:, None], ts)[:, 0]
        fwd = np.stack([np.cos(yaw) * math.cos(pitch), np.sin(yaw) * math.cos(pitch),
                        np.full(n_frames, math.sin(pitch))], axis=1)
        poses = np.stack([look_at(e, e + f) for e, f in zip(eyes, fwd)])
        return Trajectory(ts, poses)
    raise RealgapError(f"planar: no collision-free path found in {max_attempts} attempts (try another seed)")


def _turn_towards(a: np.ndarray, b: np.ndarray, max_angle_rad: float) -> np.ndarray:
    """Unit vector from unit ``a`` towards direction ``b``, turned by at most ``max_angle_rad``
    (in the plane of the two; ``b`` itself, normalised, when it is within the limit)."""
    b = b / max(np.linalg.norm(b), 1e-12)
    ang = math.acos(float(np.clip(a @ b, -1.0, 1.0)))
    if ang <= max_angle_rad:
        return b
    perp = b - (a @ b) * a
    n = np.linalg.norm(perp)
    if n < 1e-12:  # opposite directions: any perpendicular
        perp = np.cross(a, [0.0, 0.0, 1.0] if abs(a[2]) < 0.9 else [1.0, 0.0, 0.0])
        n = np.linalg.norm(perp)
    return math.cos(max_angle_rad) * a + math.sin(max_angle_rad) * perp / n


def _spline(ctrl: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """Natural cubic spline through control points evenly spaced over [ts[0], ts[-1]]."""
    if len(ctrl) == 1 or len(ts) == 1:
        return np.repeat(ctrl[:1], len(ts), axis=0)
    from scipy.interpolate import CubicSpline
    knots = np.linspace(ts[0], ts[-1], len(ctrl))
    return CubicSpline(knots, ctrl, axis=0, bc_type="natural")(ts)


# --------------------------------------------------------------------------- jitter

def handheld_jitter(traj: Trajectory, seed: int = 0, trans_sigma_m: float = 0.003,
                    rot_sigma_rad: float = 0.003, correlation_s: float = 0.25) -> Trajectory:
    """``traj`` with smooth hand-held shake: each pose is right-multiplied by a small motion
    (rotation vector, translation) expressed in the camera frame.

    The six components are white Gaussian noise low-pass filtered with a Gaussian kernel of
    ``correlation_s`` seconds (standard deviation) and rescaled so that their expected
    standard deviation is ``trans_sigma_m`` metres / ``rot_sigma_rad`` radians per axis.
    The frame rate comes from the median timestamp spacing.
    """
    from scipy.ndimage import gaussian_filter1d
    from scipy.spatial.transform import Rotation
    n = len(traj)
    if trans_sigma_m < 0 or rot_sigma_rad < 0 or correlation_s < 0:
        raise ConfigError("jitter sigmas and correlation time must be >= 0")
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((n, 6))
    dt = float(np.median(np.diff(traj.timestamps))) if n > 1 else 1.0 / DEFAULT_FPS
    sig = correlation_s / dt if dt > 0 else 0.0
    if sig > 0:
        noise = gaussian_filter1d(white, sig, axis=0, mode="reflect")
        # std of filtered unit white noise = sqrt(sum of squared kernel weights)
        impulse = np.zeros(8 * int(math.ceil(sig)) + 1)
        impulse[len(impulse) // 2] = 1.0
        k = gaussian_filter1d(impulse, sig, mode="constant")
        noise /= math.sqrt(float((k ** 2).sum()))
    else:
        noise = white
    d = np.zeros((n, 4, 4))
    d[:, :3, :3] = Rotation.from_rotvec(noise[:, :3] * rot_sigma_rad).as_matrix()
    d[:, :3, 3] = noise[:, 3:] * trans_sigma_m
    d[:, 3, 3] = 1.0
    return Trajectory(traj.timestamps.copy(), traj.poses @ d)


# --------------------------------------------------------------------------- registry

TrajectoryKind = Callable[[SceneSpec, int, int, float], Trajectory]

TRAJECTORY_KINDS: dict[str, TrajectoryKind] = {}
"""Trajectory generators by name for sequence generation: ``f(scene, n_frames, seed, fps)``."""


def register_trajectory_kind(name: str) -> Callable[[TrajectoryKind], TrajectoryKind]:
    """Decorator adding a generator to :data:`TRAJECTORY_KINDS`."""
    def deco(fn: TrajectoryKind) -> TrajectoryKind:
        TRAJECTORY_KINDS[name] = fn
        return fn
    return deco


def make_trajectory(kind: str, scene: SceneSpec, n_frames: int, seed: int = 0,
                    fps: float = DEFAULT_FPS) -> Trajectory:
    """Generate a trajectory of a registered kind; unknown kinds raise ConfigError."""
    if kind not in TRAJECTORY_KINDS:
        raise ConfigError(f"unknown trajectory kind {kind!r}; known: {', '.join(sorted(TRAJECTORY_KINDS))}")
    return TRAJECTORY_KINDS[kind](scene, n_frames, seed, fps)


@register_trajectory_kind("walkthrough")
def _walkthrough_kind(scene: SceneSpec, n_frames: int, seed: int, fps: float) -> Trajectory:
    return walkthrough(scene, n_frames, seed=seed, fps=fps)


@register_trajectory_kind("loop")
def _loop_kind(scene: SceneSpec, n_frames: int, seed: int, fps: float) -> Trajectory:
    return loop(scene, n_frames, seed=seed, fps=fps)


@register_trajectory_kind("planar")
def _planar_kind(scene: SceneSpec, n_frames: int, seed: int, fps: float) -> Trajectory:
    return planar(scene, n_frames, seed=seed, fps=fps)


@register_trajectory_kind("orbit")
def _orbit_kind(scene: SceneSpec, n_frames: int, seed: int, fps: float) -> Trajectory:
    """Orbit the centre of the content's bounding box (:func:`content_center`).

    Inside a room (the centre is enclosed by geometry): eye 0.6 m above the centre but at
    least 1.0 m above the floor and 0.3 m under the ceiling; the circle must stay inside the
    walls. In open scenes (an object on a ground plane): eye at 0.5 x radius above the centre
    (27 deg elevation). The radius is the largest collision-free one (0.25 m clearance) up to
    1.5 x the diagonal of the content's bounding box (at least 0.8 m, a typical minimum range
    of structured-light sensors). The start angle comes from the seed.
    """
    center, size = content_center(scene)
    lo, hi = _scene_bounds(scene)
    clear = _Clearance(scene)
    in_room = bool(clear.enclosed(center)[0])
    want = max(1.5 * float(np.linalg.norm(size)), 0.8)
    start = float(np.random.default_rng(seed).uniform(0, 2 * math.pi))
    a = np.linspace(0, 2 * math.pi, 180, endpoint=False)
    for radius in np.linspace(want, 0.5, 40):
        if in_room:
            eye_z = min(max(center[2] + 0.6, lo[2] + 1.0), hi[2] - 0.3)
            height = eye_z - center[2]
        else:
            height = 0.5 * radius
        ring = center + np.stack([radius * np.cos(a), radius * np.sin(a), np.full_like(a, height)], axis=1)
        if np.all(clear.distance(ring) >= 0.25) and (not in_room or np.all(clear.enclosed(ring))):
            return orbit(center, float(radius), float(height), n_frames, fps=fps, start_angle_rad=start)
    raise RealgapError("orbit: no collision-free circle around the scene content")
