"""The mystery sensor: a structured-light depth camera written apart from :mod:`synth.sensor`, whose
sequences hide one physical effect for the lab to find (``realgap demo``, ``bench_fit_recovery``).

It shares no code and few conventions with the simulator, so that a lab result on its data is not
the simulator recognising itself: its own intrinsics and baseline (drawn), raw 11-bit-style Kinect
disparity d with its own conversion z = 1 / (c0 + c1 d) (c1 = -1 / (8 f b): d counts 1/8 px as the
Kinect's does; c0 = d_inf / (8 f b)), its own scene family (a room box holding oriented boxes and
vertical cylinders, ray cast analytically in numpy) and its own file writer (TUM layout, depth scale
5000, ASCII PLY meshes in scene.json for the lab's ideal renders; see ../shared/FORMATS.md).

Always on: Gaussian disparity noise (so depth noise grows with z^2, Khoshelham & Elberink 2012) and
range limits. Hidden, one per sequence, each from its physics (parameters in ``answer.json``, in the
lab's effect names and units where both describe the same quantity):

* ``disparity_quantization``: the disparity snaps to a lattice of ``step_px`` with a phase;
* ``depth_bias``: a constant disparity offset ``offset_px`` (a miscalibrated d_inf);
* ``incidence_dropout``: pixels drop with probability logistic((theta - angle50) / width);
* ``low_reflectance``: pixels drop as the returned signal albedo / z^2 falls below a threshold;
* ``edge_fattening``: a block matcher's window spreads the nearer surface ``radius_px`` beyond depth edges;
* ``projector_shadow``: points the projector (``baseline`` to the right) cannot see give no depth;
* ``lens_distortion``: the depth image is radially distorted (k1).

The answer file is written beside the sequence and never read by the lab.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["MYSTERY_EFFECTS", "MysteryScene", "make_mystery_sequence"]

MYSTERY_EFFECTS = ("disparity_quantization", "depth_bias", "incidence_dropout", "low_reflectance",
                   "edge_fattening", "projector_shadow", "lens_distortion")
"""The effects a mystery sequence may hide (one each)."""

W, H = 320, 240
"""Image size, pixels."""
DEPTH_SCALE = 5000.0
"""Depth PNG units per metre (TUM's)."""


@dataclass
class _Box:
    """Oriented box: centre (3,), half sizes (3,), rotation world <- box (3, 3), albedo."""
    c: np.ndarray
    h: np.ndarray
    R: np.ndarray
    albedo: float
    inside: bool = False


@dataclass
class _Cylinder:
    """Vertical cylinder standing on z = 0: axis point (x, y), radius, height (m), albedo."""
    x: float
    y: float
    r: float
    top: float
    albedo: float


class MysteryScene:
    """A room (world z up, metres) with boxes and cylinders, ray cast analytically."""

    def __init__(self, rng: np.random.Generator):
        L = np.array([rng.uniform(2.6, 3.6), rng.uniform(2.4, 3.2), 2.5])
        self.prims: list = [_Box(np.array([0.0, 0.0, L[2] / 2]), L / 2 * np.array([1, 1, 1.0]), np.eye(3),
                                 float(rng.uniform(0.5, 0.8)), inside=True)]
        dark = int(rng.integers(1, 3))
        for k in range(int(rng.integers(3, 6))):
            a = float(rng.uniform(0, np.pi))
            R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
            if k == 0:                      # a slanted panel: tilted about its own x axis
                t = float(rng.uniform(0.5, 1.0))
                R = R @ np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
            hs = np.array([rng.uniform(0.12, 0.35), rng.uniform(0.12, 0.35), rng.uniform(0.15, 0.45)])
            if k == 0:
                hs[1] = 0.02
            c = np.array([rng.uniform(0.3, L[0] / 2 - 0.4), rng.uniform(-L[1] / 2 + 0.5, L[1] / 2 - 0.5), hs[2]])
            albedo = float(rng.uniform(0.02, 0.06)) if k < dark else float(rng.uniform(0.4, 0.9))
            self.prims.append(_Box(c, hs, R, albedo))
        for _ in range(int(rng.integers(1, 3))):
            self.prims.append(_Cylinder(float(rng.uniform(0.2, L[0] / 2 - 0.4)),
                                        float(rng.uniform(-L[1] / 2 + 0.5, L[1] / 2 - 0.5)),
                                        float(rng.uniform(0.08, 0.2)), float(rng.uniform(0.4, 1.1)),
                                        float(rng.uniform(0.4, 0.9))))

    def cast(self, o: np.ndarray, d: np.ndarray):
        """Rays from ``o`` (3,) along unit ``d`` (N, 3): distance t (N,) (inf = no hit), unit normals
        (N, 3) facing the ray, albedo (N,)."""
        n = len(d)
        t = np.full(n, np.inf)
        nrm = np.zeros((n, 3))
        alb = np.zeros(n)
        for p in self.prims:
            tp, npm = _box_hit(p, o, d) if isinstance(p, _Box) else _cyl_hit(p, o, d)
            closer = tp < t
            t[closer], nrm[closer], alb[closer] = tp[closer], npm[closer], p.albedo
        flip = np.einsum("ij,ij->i", nrm, d) > 0
        nrm[flip] *= -1
        return t, nrm, alb

    def meshes(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """(vertices (V, 3), triangles (F, 3), albedo) of every primitive, for scene.json."""
        out = []
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        for p in self.prims:
            if isinstance(p, _Box):
                V = (corners * p.h) @ p.R.T + p.c
                F = [(a, b, c) for q in quads for (a, b, c) in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]
                F = np.array(F)[:, ::-1] if p.inside else np.array(F)      # a room faces inwards
                out.append((V, F, p.albedo))
            else:
                m = 128
                a = 2 * np.pi * np.arange(m) / m
                ring = np.stack([p.x + p.r * np.cos(a), p.y + p.r * np.sin(a)], 1)
                V = np.concatenate([np.c_[ring, np.zeros(m)], np.c_[ring, np.full(m, p.top)], [[p.x, p.y, p.top]]])
                F = [(i, (i + 1) % m, m + (i + 1) % m) for i in range(m)] + \
                    [(i, m + (i + 1) % m, m + i) for i in range(m)] + [(m + i, m + (i + 1) % m, 2 * m) for i in range(m)]
                out.append((V, np.array(F), p.albedo))
        return out


def _box_hit(b: _Box, o, d):
    """Slab test in the box frame: entry distance (exit for the room seen from inside) and normal."""
    ol = (o - b.c) @ b.R
    dl = d @ b.R
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dl) < 1e-12, 1e-12, dl)
        t1, t2 = (-b.h - ol) * inv, (b.h - ol) * inv
    tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
    t_in, t_out = tn.max(1), tf.min(1)
    hit = t_out >= np.maximum(t_in, 0.0)
    if b.inside:
        t, axis = t_out, np.argmin(tf, 1)
    else:
        t, axis = t_in, np.argmax(tn, 1)
        hit &= t_in > 1e-6
    nl = np.zeros_like(dl)
    nl[np.arange(len(d)), axis] = 1.0
    return np.where(hit, t, np.inf), nl @ b.R.T


def _cyl_hit(c: _Cylinder, o, d):
    """Side (x - cx)^2 + (y - cy)^2 = r^2 for 0 <= z <= top, and the top cap."""
    ox, oy = o[0] - c.x, o[1] - c.y
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    bq = 2 * (ox * d[:, 0] + oy * d[:, 1])
    cq = ox ** 2 + oy ** 2 - c.r ** 2
    disc = bq ** 2 - 4 * a * cq
    with np.errstate(invalid="ignore", divide="ignore"):
        ts = (-bq - np.sqrt(np.maximum(disc, 0))) / (2 * np.maximum(a, 1e-12))
    z = o[2] + ts * d[:, 2]
    side = (disc > 0) & (ts > 1e-6) & (z >= 0) & (z <= c.top)
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = (c.top - o[2]) / np.where(np.abs(d[:, 2]) < 1e-12, 1e-12, d[:, 2])
    px, py = ox + tc * d[:, 0], oy + tc * d[:, 1]
    cap = (tc > 1e-6) & (px ** 2 + py ** 2 <= c.r ** 2)
    t = np.where(side, ts, np.inf)
    use_cap = cap & (tc < t)
    t = np.where(use_cap, tc, t)
    tt = np.where(np.isfinite(t), t, 0.0)
    n = np.stack([ox + tt * d[:, 0], oy + tt * d[:, 1], np.zeros(len(d))], 1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    n[use_cap] = [0.0, 0.0, 1.0]
    return t, n


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world 4x4, OpenCV optical axes (x right, y down, z forward), world z up."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def _quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (qx, qy, qz, qw) of a rotation matrix (Shepperd's method)."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2 * np.sqrt(tr + 1)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i], q[j], q[k] = s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q) * (1 if q[3] >= 0 else -1)


def _draw(rng: np.random.Generator, effect: str) -> dict:
    """The hidden effect's true parameters."""
    if effect == "disparity_quantization":
        return {"step_px": float(rng.uniform(0.1, 0.25)), "phase": float(rng.uniform(0, 1))}
    if effect == "depth_bias":
        return {"offset_px": float(rng.choice([-1, 1]) * rng.uniform(0.3, 0.8))}
    if effect == "incidence_dropout":
        return {"angle50_deg": float(rng.uniform(55, 72)), "width_deg": float(rng.uniform(2, 5))}
    if effect == "low_reflectance":
        return {"signal50": float(rng.uniform(0.012, 0.03)), "width_decades": float(rng.uniform(0.05, 0.2))}
    if effect == "edge_fattening":
        return {"radius_px": int(rng.integers(2, 5))}
    if effect == "projector_shadow":
        return {}
    if effect == "lens_distortion":
        return {"k1": float(rng.choice([-1, 1]) * rng.uniform(0.08, 0.2))}
    raise ValueError(f"unknown mystery effect {effect!r}; choose one of {', '.join(MYSTERY_EFFECTS)}")


def _pixel_rays(fx, cx, cy, k1: float) -> np.ndarray:
    """(H*W, 3) camera-frame ray directions of the (distorted) image pixels, z = 1: the undistorted
    normalised coordinates of each pixel (r_u from r_d = r_u (1 + k1 r_u^2), Newton steps)."""
    u, v = np.meshgrid(np.arange(W) + 0.0, np.arange(H) + 0.0)
    xd, yd = (u.ravel() - cx) / fx, (v.ravel() - cy) / fx
    if k1 == 0.0:
        return np.stack([xd, yd, np.ones_like(xd)], 1)
    rd = np.hypot(xd, yd)
    ru = rd.copy()
    for _ in range(20):
        ru -= (ru * (1 + k1 * ru ** 2) - rd) / (1 + 3 * k1 * ru ** 2)
    s = np.where(rd > 0, ru / np.maximum(rd, 1e-12), 1.0)
    return np.stack([xd * s, yd * s, np.ones_like(xd)], 1)


def _fatten(z: np.ndarray, radius: int) -> np.ndarray:
    """Every pixel takes the nearest depth in its disk of ``radius`` px when that one is > 4 % nearer
    (the matching window sees the nearer surface's texture beyond the edge)."""
    out = z.copy()
    zz = np.where(z > 0, z, np.inf)
    pad = np.pad(zz, radius, constant_values=np.inf)
    near = zz.copy()
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx * dx + dy * dy <= radius * radius:
                near = np.minimum(near, pad[radius + dy:radius + dy + H, radius + dx:radius + dx + W])
    take = np.isfinite(near) & (near < 0.96 * zz)
    out[take] = near[take]
    return out


def make_mystery_sequence(out: str | Path, *, seed: int = 0, frames: int = 6, effect: str | None = None,
                          answer: str | Path | None = None) -> dict:
    """Write a mystery sequence into ``out`` and its answer (hidden effect, true parameters, camera and
    raw-disparity conversion) to ``answer`` (default ``out/../<name>_answer.json``); returns the answer.
    ``effect`` None draws one of :data:`MYSTERY_EFFECTS` from the seed."""
    import cv2
    out = Path(out)
    rng = np.random.default_rng([seed, 7919])
    effect = effect or str(rng.choice(MYSTERY_EFFECTS))
    params = _draw(rng, effect)
    fx = float(rng.uniform(265, 300))
    cx, cy = W / 2 - 0.5 + rng.uniform(-4, 4), H / 2 - 0.5 + rng.uniform(-4, 4)
    b = float(rng.uniform(0.065, 0.085))
    d_inf = float(rng.uniform(1040, 1090))
    c1 = -1.0 / (8 * fx * b)
    c0 = -c1 * d_inf
    noise_px = float(rng.uniform(0.05, 0.09))
    zmin, zmax = float(rng.uniform(0.45, 0.6)), float(rng.uniform(3.6, 4.5))
    scene = MysteryScene(rng)
    eye = np.array([-rng.uniform(0.7, 1.1), rng.uniform(-0.3, 0.3), rng.uniform(0.9, 1.4)])
    target = np.array([rng.uniform(0.4, 0.9), rng.uniform(-0.3, 0.3), rng.uniform(0.1, 0.35)])
    moving = bool(rng.integers(0, 2))
    k1 = params["k1"] if effect == "lens_distortion" else 0.0
    rays_c = _pixel_rays(fx, cx, cy, k1)
    for sub in ("depth", "rgb", "meshes"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    lines = {"depth": [], "rgb": [], "gt": []}
    for k in range(frames):
        shift = np.array([0.0, 0.03 * k, 0.0]) if moving else np.zeros(3)
        T = _look_at(eye + shift, target + 0.5 * shift)
        d = rays_c @ T[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, nrm, alb = scene.cast(T[:3, 3], d)
        hit = np.isfinite(t)
        p = T[:3, 3] + d * np.where(hit, t, 0)[:, None]
        z = np.where(hit, (p - T[:3, 3]) @ T[:3, 2], 0.0).reshape(H, W)
        cos_i = np.clip(-np.einsum("ij,ij->i", nrm, d), 0, 1).reshape(H, W)
        albedo = alb.reshape(H, W)
        valid = z > 0
        if effect == "edge_fattening":
            z = _fatten(z, params["radius_px"])
        if effect == "projector_shadow":         # the point seen from the projector, b to the camera's right
            proj = T[:3, 3] + T[:3, 0] * b
            to_p = p - proj
            dist = np.linalg.norm(to_p, axis=1)
            tp, _, _ = scene.cast(proj, to_p / np.maximum(dist, 1e-12)[:, None])
            valid &= ~(tp < dist - 0.01).reshape(H, W)
        d_raw = d_inf - 8 * fx * b / np.where(valid, z, 1.0)          # raw units: 1/8 px
        d_raw += 8 * noise_px * rng.standard_normal((H, W))
        if effect == "depth_bias":
            d_raw -= 8 * params["offset_px"]
        if effect == "disparity_quantization":
            step = 8 * params["step_px"]
            d_raw = (np.round((d_inf - d_raw) / step - params["phase"]) + params["phase"]) * step
            d_raw = d_inf - d_raw
        zm = 1.0 / (c0 + c1 * d_raw)
        if effect == "incidence_dropout":
            theta = np.degrees(np.arccos(cos_i))
            valid &= rng.random((H, W)) >= 1 / (1 + np.exp(-(theta - params["angle50_deg"]) / params["width_deg"]))
        if effect == "low_reflectance":
            signal = albedo * cos_i / np.maximum(z, 0.1) ** 2
            ratio = np.log10(params["signal50"] / np.maximum(signal, 1e-9)) / params["width_decades"]
            valid &= rng.random((H, W)) >= 1 / (1 + np.exp(-np.clip(ratio, -50, 50)))
        valid &= (zm >= zmin) & (zm <= zmax) & np.isfinite(zm)
        depth = np.where(valid, np.round(zm * DEPTH_SCALE), 0).astype(np.uint16)
        ts = f"{k / 30.0:.6f}"
        cv2.imwrite(str(out / "depth" / f"{k:05d}.png"), depth)
        shade = (255 * np.clip(albedo * (0.3 + 0.7 * cos_i), 0, 1)).astype(np.uint8)
        cv2.imwrite(str(out / "rgb" / f"{k:05d}.png"), np.repeat(shade[:, :, None], 3, 2))
        lines["depth"].append(f"{ts} depth/{k:05d}.png")
        lines["rgb"].append(f"{ts} rgb/{k:05d}.png")
        q = _quat(T[:3, :3])
        lines["gt"].append(f"{ts} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)))
    for name, key in (("depth.txt", "depth"), ("rgb.txt", "rgb"), ("groundtruth.txt", "gt")):
        (out / name).write_text("# mystery sensor\n" + "\n".join(lines[key]) + "\n")
    meshes, mats = [], {}
    for i, (V, F, a) in enumerate(scene.meshes()):
        ply = out / "meshes" / f"part_{i:02d}.ply"
        ply.write_text(f"ply\nformat ascii 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\n"
                       f"property float z\nelement face {len(F)}\nproperty list uchar int vertex_indices\n"
                       "end_header\n" + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in V)
                       + "".join(f"3 {a_} {b_} {c_}\n" for a_, b_, c_ in F))
        meshes.append({"file": f"meshes/{ply.name}", "material": f"m{i:02d}"})
        mats[f"m{i:02d}"] = {"albedo": round(a, 4), "specular": 0.0}
    (out / "scene.json").write_text(json.dumps({"units": "m", "meshes": meshes, "materials": mats}, indent=1))
    (out / "camera.json").write_text(json.dumps({
        "width": W, "height": H, "fx": fx, "fy": fx, "cx": cx, "cy": cy, "depth_scale": DEPTH_SCALE,
        "sensor": {"type": "structured_light", "baseline_m": b, "projector_offset_m": [b, 0.0, 0.0]}}, indent=1))
    ans = {"effect": effect, "parameters": params, "seed": seed, "frames": frames, "moving_camera": moving,
           "camera": {"fx": fx, "cx": cx, "cy": cy, "baseline_m": b},
           "raw_disparity": {"c0": c0, "c1": c1, "d_inf": d_inf, "noise_px": noise_px},
           "range_m": [zmin, zmax]}
    answer = Path(answer) if answer else out.parent / f"{out.name}_answer.json"
    answer.parent.mkdir(parents=True, exist_ok=True)
    answer.write_text(json.dumps(ans, indent=1) + "\n")
    return ans
