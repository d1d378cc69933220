"""A structured-light depth camera written blind: a third hidden-effect generator for the sensor lab.

Why: the sensor lab reads a measured sequence, says which physical effect of a depth sensor is
missing from its base model and fits it. Generators written by the people who wrote the lab share
its conventions; this one was written WITHOUT reading the lab, the project's simulator or the
other generators - only ``../shared/FORMATS.md`` (the on-disk contracts), ch. 3 of the thesis
(structured-light physics) and the lab's user-facing help (``realgap sensor effects NAME``, which
fixes the UNITS of the answer). It is numpy/scipy only and imports nothing of the project.

What it makes: a Kinect-v1 / PrimeSense-class camera - an IR projector beside an IR camera on a
horizontal baseline, disparity -> depth - looking at a furnished room, with an always-on base and
at most ONE hidden effect on top; every number is drawn from a range by ``seed``.

Sensor (per seed)
    A native sensor of 1280x960, 800x600 or 640x480 pixels (horizontal field of view 54-63 deg,
    fy = fx (1 +- 0.3-1.2 %), principal point up to 4 % of the size off-centre) scaled to the
    output ``width x height`` (each axis on its own; pixel centres at integer coordinates). Baseline
    5-10 cm; the projector sits to the LEFT (-x) or RIGHT (+x) of the camera (camera.json says it:
    ``sensor.projector_offset_m``). Depth PNG scale 5000 or 10000 units per metre.

Disparity (own convention)
    The device measures a PrimeSense-style *shift* ``s = s0 - D`` (native pixels, ``s0`` a
    per-device reference shift of 100-160 native px) and reports ``z = b f / (s0 - s)``. In the
    OUTPUT image's pixels the disparity is ``D = fx b / z`` (fx of the output image, the baseline
    is horizontal); every disparity number below (noise, steps, offsets, jumps) is in these
    output pixels.

Base (always on)
    * Noise: Gaussian in disparity, ``D + sigma_d n`` with sigma_d 0.04-0.10 output px, i.i.d. per
      pixel and frame -> depth std ~ z^2 sigma_d / (fx b). ``noise2m`` is the exact std of the
      measured depth of a surface at z = 2 m (Gauss-Hermite over the noise, no other effect).
    * Range limits: measured depth outside [near, far] is a hole (0); near 0.4-0.9 m, far 3-5 m.

Scene (per seed; world frame z UP, metres)
    A closed room (floor, ceiling, four walls) with the camera near one wall looking towards a
    corner, plus some of: a staircase of step boxes along the side wall, a table (oriented top on
    four legs, sometimes carrying a sphere), spheres on the floor, a tilted ramp board (an oriented
    thin box), a partition wall with a doorway. Albedo per object (dark 0.04-0.15 or bright
    0.3-0.9), specular 0 everywhere. The depth is ray-cast on the analytic surfaces (planes,
    oriented boxes, spheres); the meshes of scene.json are the same surfaces (exact for planes and
    boxes, a level-5 icosphere for spheres: < 0.1 mm from the sphere). Camera static or moving
    (a bounded smooth path: sinusoids in position, yaw, pitch; poses at 30 fps).

Hidden effects (``EFFECTS``; parameters in ``answer["params"]``, the reviewer's keys in the lab's
units as ``realgap sensor effects NAME`` documents them)
    * ``depth_bias``: the device's calibration is off: it converts with ``fb (1 + scale_error)`` and
      a reference shift wrong by ``disparity_offset_px``: ``z' = fb (1 + e) / (D + delta)``
      (e +-0.2-2 %, delta from a disparity-offset bias of 0.5-4 cm at 2 m). Scored by
      ``bias_at_m`` = E[z'] - z at 1, 2, 3 m (the mean over the base noise, no range limits).
    * ``disparity_quantization``: the shift is reported in integer steps: measured disparity
      ``D = s0 - step round((s0 - D_noisy) / step)``; ``step_px`` = step / sigma_d of 1.5-8
      (at most 0.9 px); levels sit at ``(k + level_phase) step_px`` in absolute disparity.
    * ``edge_fattening``: the block-matching window locks onto a nearer surface: a pixel whose
      square window (2 r + 1)^2 holds a foreground edge pixel (the near side of a depth
      discontinuity of the ideal view, a disparity jump > ``min_jump_px`` beyond what both
      pixels' tangent planes explain) with a disparity larger than its own by ``min_jump_px``
      takes the largest such disparity. ``radius_px`` = r, 2-5 px: how far foreground spreads
      (the lab's square-window radius).
    * ``incidence_dropout``: a pixel drops with probability
      ``1 - exp(-ln 2 (tan(theta) / tan(angle50))^k)`` (Weibull in tan theta), theta the angle
      between the analytic surface normal and the CAMERA ray; angle50 55-80 deg, k 3-9
      (``angle50_deg`` = the 50 % angle; ``equiv_width_deg`` the lab's logistic width with the same
      slope there).
    * ``low_reflectance``: returned signal ``S = albedo (1 - specular) cos(theta) / r^2`` (r the
      distance from the camera centre, metres: the lab's definition); a pixel drops with
      probability ``exp(-ln 2 (S / signal50)^m)`` (m 1.5-4); ``signal50`` drawn log-uniformly
      between the 12 % and 45 % quantiles of S in the first frame's in-range pixels.
    * ``projector_shadow``: a pixel is a hole when the segment from its surface point to the
      projector centre is blocked (a shadow ray cast on the analytic scene, ``eps_m`` free at the
      start) or the projector lies behind the surface's tangent plane.
    * ``lens_distortion``: the IR lens has OpenCV radial distortion ``k1`` (+-0.04-0.25, k2 = 0) on
      normalised coordinates of the OUTPUT camera: pixel (u, v) is the distorted image of the ray
      through the undistorted normalised point; camera.json still says no distortion. Pixels
      whose ray leaves the pinhole image still see the scene (the lab's ``outside = seen``).
    * ``rolling_shutter``: row v is exposed at ``t + (v / (H - 1) - reference_row) readout_time_s``
      (readout 10-35 ms, reference_row 0, 0.5 or 1); the camera always moves (peak yaw rate
      0.6-1.2 rad/s, speed up to ~0.4 m/s); groundtruth.txt holds the pose at t.

Randomness: the scene and sensor come from ``seed``; the effect's parameters from ``(seed,
effect)``; the per-pixel noise and dropout draws from ``noise_seed`` (default: derived from seed)
and the frame index. Same arguments -> byte-identical files.

Helpers the tests use: :func:`build` (sensor, scene, path, parameters), :func:`cast` (the ideal view
of a frame: z-depth, points, normals, signal), :func:`measure` (the measured depth),
:func:`shadow_mask`, :func:`fatten`, :func:`camera_rays`, :func:`row_times`. Seeds are non-negative
integers. Run it: ``python tests/blind_sensor.py OUT --effect lens_distortion --seed 3``.
"""
from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy import ndimage

EFFECTS = ("depth_bias", "disparity_quantization", "edge_fattening", "incidence_dropout",
           "low_reflectance", "projector_shadow", "lens_distortion", "rolling_shutter")
FPS = 30.0
"""Frame rate of the sequence, frames per second."""
SHADOW_EPS_M = 5e-4
"""Free length at the start of a shadow ray (no self-hit of the surface it leaves), metres."""
_SALT_SCENE, _SALT_EFFECT, _SALT_NOISE = 0x5EB1, 0xEFFC, 0x401E


# ----------------------------------------------------------------------------- primitives
@dataclass
class Rect:
    """A planar rectangle ``o + s a + w b`` (s, w in [0, 1]); two-sided; ``a x b`` is its front normal."""
    o: np.ndarray
    a: np.ndarray
    b: np.ndarray

    def intersect(self, O, D, tmin):
        n = np.cross(self.a, self.b)
        n = n / np.linalg.norm(n)
        den = D @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.o - O) @ n) / den
        p = O + t[:, None] * D
        q = p - self.o
        s = q @ self.a / (self.a @ self.a)
        w = q @ self.b / (self.b @ self.b)
        ok = np.isfinite(t) & (t > tmin) & (s >= 0) & (s <= 1) & (w >= 0) & (w <= 1)
        return np.where(ok, t, np.inf)

    def normal(self, p, D):
        n = np.cross(self.a, self.b)
        n = n / np.linalg.norm(n)
        s = np.where(D @ n > 0, -1.0, 1.0)            # facing the ray
        return s[:, None] * n[None, :]


@dataclass
class Box:
    """A closed oriented box: centre ``c``, half sizes ``h``, rotation ``R`` (columns: its axes in the world)."""
    c: np.ndarray
    h: np.ndarray
    R: np.ndarray

    def intersect(self, O, D, tmin):
        Ol = (O - self.c) @ self.R
        Dl = D @ self.R
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / Dl
            t1 = (-self.h - Ol) * inv
            t2 = (self.h - Ol) * inv
        # a ray parallel to a slab: inside the slab = no constraint, outside = miss
        par = Dl == 0
        inside = np.abs(Ol) <= self.h
        lo = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        hi = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        tn = lo.max(axis=1)
        tf = hi.min(axis=1)
        hit = (tn <= tf) & (tf > tmin)
        t = np.where(tn > tmin, tn, tf)
        return np.where(hit, t, np.inf)

    def normal(self, p, D):
        q = (p - self.c) @ self.R
        ax = np.argmax(np.abs(q) / self.h, axis=1)
        sgn = np.sign(q[np.arange(len(q)), ax])
        sgn[sgn == 0] = 1.0
        return (self.R[:, ax] * sgn).T


@dataclass
class Sphere:
    """A sphere: centre ``c``, radius ``r`` (metres)."""
    c: np.ndarray
    r: float

    def intersect(self, O, D, tmin):
        oc = O - self.c
        b = np.einsum("ij,ij->i", oc, D)
        cc = np.einsum("ij,ij->i", oc, oc) - self.r ** 2
        disc = b * b - cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        t = -b - sq
        t = np.where(t > tmin, t, -b + sq)
        return np.where((disc >= 0) & (t > tmin), t, np.inf)

    def normal(self, p, D):
        return (p - self.c) / self.r


@dataclass
class Part:
    """One named object of the scene: its analytic primitives, one mesh file, one material."""
    name: str
    albedo: float
    prims: list


# ----------------------------------------------------------------------------- meshes
@lru_cache(maxsize=None)
def _icosphere(level: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere (vertices on the sphere, outward counter-clockwise triangles)."""
    g = (1 + 5 ** 0.5) / 2
    v = [(-1, g, 0), (1, g, 0), (-1, -g, 0), (1, -g, 0), (0, -1, g), (0, 1, g), (0, -1, -g), (0, 1, -g),
         (g, 0, -1), (g, 0, 1), (-g, 0, -1), (-g, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    V = np.array(v, float)
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    F = np.array(f, np.int64)
    for _ in range(level):
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        ue, inv = np.unique(e, axis=0, return_inverse=True)
        mid = V[ue[:, 0]] + V[ue[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(V)              # midpoints of edges 01, 12, 20
        V = np.concatenate([V, mid])
        a, b, c = F[:, 0], F[:, 1], F[:, 2]
        m01, m12, m20 = m[:, 0], m[:, 1], m[:, 2]
        F = np.concatenate([np.stack([a, m01, m20], 1), np.stack([b, m12, m01], 1),
                            np.stack([c, m20, m12], 1), np.stack([m01, m12, m20], 1)])
    return V, _orient_out(V, F, np.zeros(3))


def _orient_out(V, F, centre):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.einsum("ij,ij->i", n, V[F].mean(1) - centre) < 0
    F = F.copy()
    F[flip] = F[flip][:, ::-1]
    return F


def _mesh_of(prim) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(prim, Rect):
        nu = max(1, int(math.ceil(np.linalg.norm(prim.a) / 0.5)))
        nv = max(1, int(math.ceil(np.linalg.norm(prim.b) / 0.5)))
        s, w = np.meshgrid(np.arange(nu + 1) / nu, np.arange(nv + 1) / nv, indexing="ij")
        V = prim.o + s.reshape(-1, 1) * prim.a + w.reshape(-1, 1) * prim.b
        idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
        p00, p10, p11, p01 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        F = np.concatenate([np.stack([p00, p10, p11], -1).reshape(-1, 3),
                            np.stack([p00, p11, p01], -1).reshape(-1, 3)])
        return V, F                                     # (a x b) side is counter-clockwise
    if isinstance(prim, Box):
        bits = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float) * 2 - 1
        V = prim.c + (bits * prim.h) @ prim.R.T
        F = np.array([[0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5]], np.int64)
        return V, _orient_out(V, F, prim.c)
    V, F = _icosphere(5)
    return prim.c + prim.r * V, F


def _ply_bytes(V: np.ndarray, F: np.ndarray) -> bytes:
    head = (f"ply\nformat binary_little_endian 1.0\ncomment blind_sensor\nelement vertex {len(V)}\n"
            "property double x\nproperty double y\nproperty double z\n"
            f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    faces = np.zeros(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = F
    return head + np.ascontiguousarray(V, "<f8").tobytes() + faces.tobytes()


# ----------------------------------------------------------------------------- files
def _png(img: np.ndarray) -> bytes:
    """Minimal PNG encoder (grey 16-bit or RGB 8-bit; filter 0, zlib level 6): deterministic bytes."""
    if img.dtype == np.uint16:
        raw, ctype, bits = img.astype(">u2"), 0, 16
    else:
        raw, ctype, bits = img.astype(np.uint8), 2, 8
    H, W = img.shape[:2]
    rows = np.ascontiguousarray(raw).view(np.uint8).reshape(H, -1)
    data = np.concatenate([np.zeros((H, 1), np.uint8), rows], axis=1).tobytes()

    def chunk(k, d):
        return struct.pack(">I", len(d)) + k + d + struct.pack(">I", zlib.crc32(k + d) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, bits, ctype, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(data, 6)) + chunk(b"IEND", b""))


def _quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> (qx, qy, qz, qw), qw >= 0."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


# ----------------------------------------------------------------------------- set-up
@dataclass
class Rig:
    """The sensor of one seed, at the output resolution."""
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    native: tuple[int, int]
    baseline_m: float
    side: int                      # +1: projector at +x (right) of the camera, -1: left
    sigma_d: float                 # disparity noise, output px
    near_m: float
    far_m: float
    depth_scale: float
    s0_px: float                   # reference shift, output px
    x_scale: float                 # output px per native px along x

    @property
    def fb(self) -> float:
        return self.fx * self.baseline_m

    @property
    def projector(self) -> np.ndarray:
        return np.array([self.side * self.baseline_m, 0.0, 0.0])


@dataclass
class Motion:
    """Camera path: camera-to-world pose as a smooth bounded function of time."""
    t0: float
    p0: np.ndarray
    yaw0: float
    pitch0: float
    roll0: float
    moving: bool
    amp_p: np.ndarray = field(default_factory=lambda: np.zeros(3))
    per_p: np.ndarray = field(default_factory=lambda: np.ones(3))
    ph_p: np.ndarray = field(default_factory=lambda: np.zeros(3))
    amp_a: np.ndarray = field(default_factory=lambda: np.zeros(3))   # yaw, pitch, roll amplitudes
    per_a: np.ndarray = field(default_factory=lambda: np.ones(3))
    ph_a: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R (N, 3, 3), C (N, 3)) at times t (N,)."""
        t = np.atleast_1d(np.asarray(t, float)) - self.t0
        if self.moving:
            w = 2 * np.pi * t[:, None]
            C = self.p0 + self.amp_p * (np.sin(w / self.per_p + self.ph_p) - np.sin(self.ph_p))
            ang = np.array([self.yaw0, self.pitch0, self.roll0]) + self.amp_a * (
                np.sin(w / self.per_a + self.ph_a) - np.sin(self.ph_a))
        else:
            C = np.repeat(self.p0[None], len(t), 0)
            ang = np.repeat(np.array([[self.yaw0, self.pitch0, self.roll0]]), len(t), 0)
        return _rotation(ang[:, 0], ang[:, 1], ang[:, 2]), C


def _rotation(yaw, pitch, roll):
    """Camera-to-world rotation: OpenCV camera (x right, y down, z forward), world z up; yaw 0 looks
    along +y, pitch > 0 looks down, roll about the optical axis."""
    cy_, sy_, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    fwd = np.stack([sy_ * cp, cy_ * cp, -sp], -1)
    right = np.stack([cy_, -sy_, np.zeros_like(yaw)], -1)
    down = np.cross(fwd, right)
    cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
    r2 = cr * right + sr * down
    d2 = -sr * right + cr * down
    return np.stack([r2, d2, fwd], -1)


@dataclass
class Setup:
    """Everything one (seed, effect) fixes before the noise: sensor, scene, path, effect parameters."""
    seed: int
    effect: str | None
    rig: Rig
    parts: list[Part]
    motion: Motion
    timestamps: np.ndarray
    params: dict
    room: dict

    @property
    def prims(self):
        return [(i, p) for i, part in enumerate(self.parts) for p in part.prims]


def _draw_rig(rng, width, height) -> Rig:
    Wn, Hn = [(1280, 960), (800, 600), (640, 480)][int(rng.integers(3))]
    hfov = math.radians(rng.uniform(54, 63))
    fxn = Wn / 2 / math.tan(hfov / 2)
    fyn = fxn * (1 + rng.choice([-1, 1]) * rng.uniform(0.003, 0.012))
    cxn = (Wn - 1) / 2 + rng.uniform(-0.04, 0.04) * Wn
    cyn = (Hn - 1) / 2 + rng.uniform(-0.04, 0.04) * Hn
    sx, sy = width / Wn, height / Hn
    return Rig(width=width, height=height, fx=fxn * sx, fy=fyn * sy, cx=(cxn + 0.5) * sx - 0.5,
               cy=(cyn + 0.5) * sy - 0.5, native=(Wn, Hn), baseline_m=float(rng.uniform(0.05, 0.10)),
               side=int(rng.choice([-1, 1])), sigma_d=float(rng.uniform(0.04, 0.10)),
               near_m=float(rng.uniform(0.4, 0.9)), far_m=float(rng.uniform(3.0, 5.0)),
               depth_scale=float(rng.choice([5000.0, 10000.0])), s0_px=float(rng.uniform(100, 160) * sx),
               x_scale=sx)


def _albedo(rng, dark_p=0.35):
    return float(rng.uniform(0.04, 0.15) if rng.random() < dark_p else rng.uniform(0.3, 0.9))


def _yaw_R(yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _draw_scene(rng):
    """The room and its furniture; returns (parts, room dict)."""
    Wr, Lr, Hr = rng.uniform(3.6, 5.0), rng.uniform(3.8, 5.2), rng.uniform(2.4, 3.0)
    parts = []
    X, Y, Z = np.eye(3)
    parts.append(Part("floor", float(rng.uniform(0.2, 0.6)), [Rect(np.zeros(3), Wr * X, Lr * Y)]))
    parts.append(Part("ceiling", float(rng.uniform(0.7, 0.9)), [Rect(np.array([0, 0, Hr]), Lr * Y, Wr * X)]))
    walls = {"wall_left": Rect(np.zeros(3), Lr * Y, Hr * Z), "wall_right": Rect(np.array([Wr, 0, 0]), Hr * Z, Lr * Y),
             "wall_back": Rect(np.array([0, Lr, 0]), Hr * Z, Wr * X), "wall_front": Rect(np.zeros(3), Wr * X, Hr * Z)}
    for name, r in walls.items():
        parts.append(Part(name, float(rng.uniform(0.45, 0.85)), [r]))
    return parts, dict(W=Wr, L=Lr, H=Hr)


def _furnish(rng, parts, room, C, yaw, corner):
    """Add furniture in front of the camera at C (x, y) looking along yaw; corner = +1 (x = W side) or -1."""
    Wr, Lr = room["W"], room["L"]
    fwd = np.array([math.sin(yaw), math.cos(yaw)])
    right = np.array([math.cos(yaw), -math.sin(yaw)])
    taken: list[tuple[np.ndarray, np.ndarray]] = []        # xy footprints (lo, hi)

    def free(lo, hi, margin=0.08, wall=0.05):
        if lo[0] < wall or lo[1] < wall or hi[0] > Wr - wall or hi[1] > Lr - wall:
            return False
        return all(np.any(lo > h + margin) or np.any(hi < l - margin) for l, h in taken)

    def spot(dmin, dmax, lat):
        d = rng.uniform(dmin, dmax)
        return C + d * fwd + rng.uniform(-lat, lat) * d * right

    groups = {"stairs": rng.random() < 0.7, "table": rng.random() < 0.7, "ramp": rng.random() < 0.6,
              "doorway": rng.random() < 0.5}
    while sum(groups.values()) < 3:
        groups[["stairs", "table", "ramp", "doorway"][int(rng.integers(4))]] = True
    Z = np.array([0.0, 0.0, 1.0])
    if groups["doorway"]:                      # a partition parallel to the back wall, from the far side wall
        yp = C[1] + rng.uniform(2.4, 3.2)
        th = rng.uniform(0.08, 0.14)
        if yp + th < Lr - 0.5:
            length = rng.uniform(0.5, 0.7) * Wr
            x0, x1 = (0.0, length) if corner > 0 else (Wr - length, Wr)
            dw, dh = rng.uniform(0.8, 0.95), rng.uniform(1.95, 2.1)
            xd = rng.uniform(x0 + 0.3, x1 - 0.3 - dw)
            Hr = room["H"]
            boxes = []
            for a, b, z0, z1 in ((x0, xd, 0, Hr), (xd + dw, x1, 0, Hr), (xd, xd + dw, dh, Hr)):
                boxes.append(Box(np.array([(a + b) / 2, yp + th / 2, (z0 + z1) / 2]),
                                 np.array([(b - a) / 2, th / 2, (z1 - z0) / 2]), np.eye(3)))
            parts.append(Part("partition", _albedo(rng, 0.25), boxes))
            taken.append((np.array([x0, yp]), np.array([x1, Lr])))
    if groups["stairs"]:
        n, run, rise, width = int(rng.integers(3, 6)), rng.uniform(0.25, 0.32), rng.uniform(0.16, 0.2), rng.uniform(0.7, 1.0)
        y0 = C[1] + rng.uniform(1.6, 2.6)
        n = min(n, int((Lr - 0.05 - y0) // run))
        xa, xb = (Wr - width, Wr) if corner > 0 else (0.0, width)
        if n >= 2 and free(np.array([xa, y0]), np.array([xb, y0 + n * run]), 0.02, -1e-9):
            steps = [Box(np.array([(xa + xb) / 2, y0 + (i + 0.5) * run, (i + 1) * rise / 2]),
                         np.array([(xb - xa) / 2, run / 2, (i + 1) * rise / 2]), np.eye(3)) for i in range(n)]
            parts.append(Part("stairs", _albedo(rng), steps))
            taken.append((np.array([xa, y0]), np.array([xb, y0 + n * run])))
    if groups["ramp"]:
        for _ in range(30):
            foot = spot(1.4, 2.6, 0.35)
            ry = yaw + rng.uniform(-0.6, 0.6)
            alpha = math.radians(rng.uniform(15, 40))
            length, width, th = rng.uniform(0.8, 1.2), rng.uniform(0.6, 1.0), rng.uniform(0.02, 0.035)
            u = np.array([math.sin(ry), math.cos(ry), 0.0])
            a = math.cos(alpha) * u + math.sin(alpha) * Z
            w = np.array([math.cos(ry), -math.sin(ry), 0.0])
            nrm = np.cross(w, a)
            if nrm[2] < 0:
                nrm = -nrm
            R = np.stack([w, a, nrm], 1)
            if np.linalg.det(R) < 0:
                R[:, 0] = -R[:, 0]
            ctr = np.array([foot[0], foot[1], 0.0]) + a * length / 2 + nrm * th / 2
            ext = np.abs(R[:2, :2]) @ np.array([width / 2, length / 2]) + 0.02
            if free(ctr[:2] - ext, ctr[:2] + ext):
                parts.append(Part("ramp", _albedo(rng), [Box(ctr, np.array([width / 2, length / 2, th / 2]), R)]))
                taken.append((ctr[:2] - ext, ctr[:2] + ext))
                break
    table_top = None
    if groups["table"]:
        for _ in range(30):
            c = spot(1.6, 2.8, 0.3)
            L_, W_, h = rng.uniform(0.8, 1.4), rng.uniform(0.55, 0.9), rng.uniform(0.68, 0.8)
            ty = yaw + rng.uniform(-0.7, 0.7)
            R = _yaw_R(-ty)
            ext = np.abs(R[:2, :2]) @ np.array([W_ / 2, L_ / 2])
            if free(c - ext, c + ext):
                t_, leg = rng.uniform(0.03, 0.05), rng.uniform(0.04, 0.06)
                top = Box(np.array([c[0], c[1], h - t_ / 2]), np.array([W_ / 2, L_ / 2, t_ / 2]), R)
                legs = [Box(np.array([*(c + R[:2, :2] @ np.array([sx * (W_ / 2 - leg), sy * (L_ / 2 - leg)])),
                                      (h - t_) / 2]), np.array([leg / 2, leg / 2, (h - t_) / 2]), R)
                        for sx in (-1, 1) for sy in (-1, 1)]
                parts.append(Part("table", _albedo(rng), [top, *legs]))
                taken.append((c - ext, c + ext))
                table_top = (c, h, min(W_, L_))
                break
    balls = []
    if table_top is not None and rng.random() < 0.5:
        c, h, size = table_top
        r = rng.uniform(0.08, min(0.18, size / 2 - 0.02))
        balls.append(Sphere(np.array([c[0], c[1], h + r]), float(r)))
    n_floor, placed = int(rng.integers(1, 4)), 0
    for _ in range(60):
        if placed >= n_floor:
            break
        c = spot(1.2, 3.2, 0.42)
        r = rng.uniform(0.1, 0.28)
        if free(c - r, c + r):
            balls.append(Sphere(np.array([c[0], c[1], r]), float(r)))
            taken.append((c - r, c + r))
            placed += 1
    for i, b in enumerate(balls):
        parts.append(Part(f"sphere{i}", _albedo(rng), [b]))


def build(seed: int, effect: str | None, n_frames: int = 4, width: int = 160, height: int = 120) -> Setup:
    """Draw the sensor, scene, camera path and effect parameters of ``(seed, effect)``."""
    if effect is not None and effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; one of {', '.join(EFFECTS)} or None")
    rng = np.random.default_rng([_SALT_SCENE, int(seed)])
    rig = _draw_rig(rng, int(width), int(height))
    parts, room = _draw_scene(rng)
    corner = int(rng.choice([-1, 1]))
    C = np.array([room["W"] * rng.uniform(0.35, 0.65), rng.uniform(0.3, 0.7)])
    cx_, cy_ = (room["W"] if corner > 0 else 0.0), room["L"]
    yaw_c = math.atan2(cx_ - C[0], cy_ - C[1])
    yaw = yaw_c * rng.uniform(0.5, 0.9)
    _furnish(rng, parts, room, C, yaw, corner)
    for part in parts:                                  # the albedo scene.json says is the one used
        part.albedo = round(float(part.albedo), 6)
    z = rng.uniform(1.0, 1.6)
    moving = bool(rng.random() < 0.5) or effect == "rolling_shutter"
    t0 = round(float(rng.uniform(1000.0, 2000.0)), 3)
    motion = Motion(t0=t0, p0=np.array([C[0], C[1], z]), yaw0=yaw, pitch0=math.radians(rng.uniform(8, 22)),
                    roll0=math.radians(rng.uniform(-3, 3)), moving=moving)
    if moving:
        fast = effect == "rolling_shutter"
        motion.per_p = rng.uniform(2.5, 5.0, 3)
        speed = rng.uniform(0.15, 0.4, 3) * np.array([1, 1, 0.3])
        motion.amp_p = np.minimum(speed * motion.per_p / (2 * np.pi), 0.2)
        motion.ph_p = rng.uniform(-0.5, 0.5, 3)
        motion.per_a = rng.uniform(3.0, 6.0, 3)
        rate = np.array([rng.uniform(0.6, 1.2) if fast else rng.uniform(0.1, 0.4),
                         rng.uniform(0.05, 0.2), rng.uniform(0.0, 0.08)]) * rng.choice([-1, 1], 3)
        motion.amp_a = rate * motion.per_a / (2 * np.pi)
        motion.ph_a = rng.uniform(-0.4, 0.4, 3)
    timestamps = np.round(t0 + np.arange(int(n_frames)) / FPS, 6)
    setup = Setup(int(seed), effect, rig, parts, motion, timestamps, {}, room)
    setup.params = _draw_params(setup)
    return setup


def _draw_params(s: Setup) -> dict:
    if s.effect is None:
        return {}
    rng = np.random.default_rng([_SALT_EFFECT, s.seed, EFFECTS.index(s.effect)])
    r = s.rig
    e = s.effect
    if e == "depth_bias":
        scale = float(rng.choice([-1, 1]) * rng.uniform(0.002, 0.02))
        b2 = float(rng.choice([-1, 1]) * rng.uniform(0.005, 0.04))      # disparity-offset part at 2 m, m
        delta = -b2 * r.fb / 4.0
        return {"scale_error": scale, "disparity_offset_px": delta,
                "shift_offset_native_px": delta / r.x_scale}
    if e == "disparity_quantization":
        ratio = float(rng.uniform(1.5, 8.0))
        step = min(ratio * r.sigma_d, 0.9)
        return {"step_px": step, "step_to_noise": step / r.sigma_d, "level_phase": (r.s0_px / step) % 1.0,
                "step_native_px": step / r.x_scale}
    if e == "edge_fattening":
        return {"radius_px": int(rng.integers(2, 6)), "min_jump_px": float(rng.uniform(0.2, 0.45)),
                "window": "square"}
    if e == "incidence_dropout":
        a50 = float(rng.uniform(55, 80))
        k = float(rng.uniform(3, 9))
        th = math.radians(a50)
        slope = math.log(2) * 0.5 * k / (math.sin(th) * math.cos(th))   # dp/dtheta at angle50, 1/rad
        return {"angle50_deg": a50, "weibull_k": k, "equiv_width_deg": math.degrees(1 / (4 * slope)),
                "reference": "camera"}
    if e == "low_reflectance":
        m = float(rng.uniform(1.5, 4.0))
        c = cast(s, 0)
        ok = c["hit"] & (c["z"] >= r.near_m) & (c["z"] <= r.far_m)
        S = c["signal"][ok]
        lo, hi = np.quantile(S, [0.12, 0.45])
        s50 = float(np.clip(math.exp(rng.uniform(math.log(lo), math.log(hi))), 0.002, 0.2))
        return {"signal50": s50, "weibull_m": m, "signal": "irradiance"}
    if e == "projector_shadow":
        return {"eps_m": SHADOW_EPS_M, "projector_side": "right" if r.side > 0 else "left"}
    if e == "lens_distortion":
        return {"k1": float(rng.choice([-1, 1]) * rng.uniform(0.04, 0.25)), "k2": 0.0, "outside": "seen"}
    if e == "rolling_shutter":
        return {"readout_time_s": float(rng.uniform(0.010, 0.035)),
                "reference_row": float(rng.choice([0.0, 0.5, 1.0]))}
    raise AssertionError(e)


# ----------------------------------------------------------------------------- rendering
def _bound(p) -> tuple[np.ndarray, float]:
    """A bounding sphere (centre, radius) of a primitive."""
    if isinstance(p, Rect):
        return p.o + (p.a + p.b) / 2, float(np.linalg.norm(p.a + p.b) / 2) * 1.001 + 1e-9
    if isinstance(p, Box):
        return p.c, float(np.linalg.norm(p.h)) * 1.001 + 1e-9
    return p.c, p.r * 1.001 + 1e-9


def _nearest(prims, O, D, tmin=1e-9, tmax=None):
    """Nearest hit: (t (N,), primitive index (N,), -1 = none) over [(part, prim), ...]; only rays that pass
    a primitive's bounding sphere are intersected with it."""
    best = np.full(len(O), np.inf) if tmax is None else np.array(tmax, float)
    idx = np.full(len(O), -1)
    for k, (_, p) in enumerate(prims):
        c, R = _bound(p)
        oc = c - O
        tca = np.einsum("ij,ij->i", oc, D)
        d2 = np.einsum("ij,ij->i", oc, oc) - tca * tca
        cand = np.flatnonzero((d2 <= R * R) & (tca + R > tmin) & (tca - R < best))
        if not len(cand):
            continue
        with np.errstate(all="ignore"):
            t = p.intersect(O[cand], D[cand], tmin)
        closer = t < best[cand]
        best[cand[closer]] = t[closer]
        idx[cand[closer]] = k
    return best, idx


def camera_rays(s: Setup) -> np.ndarray:
    """(H, W, 3) ray directions in the camera frame (z component 1) of every pixel, through the lens."""
    r = s.rig
    u, v = np.meshgrid(np.arange(r.width, dtype=float), np.arange(r.height, dtype=float))
    xd, yd = (u - r.cx) / r.fx, (v - r.cy) / r.fy
    if s.effect == "lens_distortion":
        k1, k2 = s.params["k1"], s.params["k2"]
        xu, yu = xd.copy(), yd.copy()
        for _ in range(60):                           # fixed point of x_d = x_u (1 + k1 r^2 + k2 r^4)
            r2 = xu * xu + yu * yu
            f = 1 + k1 * r2 + k2 * r2 * r2
            xu, yu = xd / f, yd / f
        xd, yd = xu, yu
    return np.stack([xd, yd, np.ones_like(xd)], -1)


def row_times(s: Setup, k: int) -> np.ndarray:
    """(H,) exposure time of every row of frame k, seconds."""
    H = s.rig.height
    t = np.full(H, s.timestamps[k])
    if s.effect == "rolling_shutter":
        t = t + (np.arange(H) / (H - 1) - s.params["reference_row"]) * s.params["readout_time_s"]
    return t


def cast(s: Setup, k: int) -> dict:
    """The ideal view of frame k: per-pixel hit, z-depth (m), point, normal, part index, signal..."""
    r = s.rig
    H, W = r.height, r.width
    dcam = camera_rays(s)
    Rr, Cr = s.motion.pose(row_times(s, k))           # per row
    dw = np.einsum("hij,hwj->hwi", Rr, dcam)
    norm = np.linalg.norm(dw, axis=-1, keepdims=True)
    Dn = (dw / norm).reshape(-1, 3)
    O = np.repeat(Cr, W, axis=0)
    prims = s.prims
    t, idx = _nearest(prims, O, Dn)
    hit = idx >= 0
    P = O + np.where(hit, t, 0.0)[:, None] * Dn
    N = np.zeros_like(P)
    part = np.full(len(O), -1)
    for k_, (pi, p) in enumerate(prims):
        m = idx == k_
        if m.any():
            N[m] = p.normal(P[m], Dn[m])
            part[m] = pi
    flip = np.einsum("ij,ij->i", N, Dn) > 0
    N[flip] = -N[flip]
    cosi = np.clip(-np.einsum("ij,ij->i", N, Dn), 0.0, 1.0)
    z = np.where(hit, t / norm.reshape(-1), 0.0)      # dcam has z = 1: z-depth = t / |dcam|
    albedo = np.array([p.albedo for p in s.parts])[np.maximum(part, 0)]
    rng_m = np.where(hit, t, np.inf)
    signal = np.where(hit, albedo * cosi / rng_m ** 2, 0.0)
    proj = Cr + np.einsum("hij,j->hi", Rr, r.projector)
    return {"hit": hit.reshape(H, W), "z": z.reshape(H, W), "point": P.reshape(H, W, 3),
            "normal": N.reshape(H, W, 3), "part": part.reshape(H, W), "cos": cosi.reshape(H, W),
            "albedo": albedo.reshape(H, W), "signal": signal.reshape(H, W), "dir": Dn.reshape(H, W, 3),
            "R_rows": Rr, "C_rows": Cr, "projector_rows": proj, "dcam": dcam}


def shadow_mask(s: Setup, c: dict) -> np.ndarray:
    """(H, W) True where the projector cannot see the pixel's surface point (blocked shadow ray, or the
    projector behind the surface's tangent plane)."""
    H, W = c["z"].shape
    hit = c["hit"].reshape(-1)
    P = c["point"].reshape(-1, 3)
    Pj = np.repeat(c["projector_rows"], W, axis=0)
    v = Pj - P
    L = np.linalg.norm(v, axis=1)
    u = v / np.maximum(L, 1e-12)[:, None]
    n = c["normal"].reshape(-1, 3)
    behind = np.einsum("ij,ij->i", n, u) <= 0
    out = np.zeros(len(P), bool)
    sel = np.flatnonzero(hit & ~behind)
    t, idx = _nearest(s.prims, P[sel] + SHADOW_EPS_M * u[sel], u[sel], 0.0, L[sel] - SHADOW_EPS_M)
    out[sel] = idx >= 0
    out |= hit & behind
    return out.reshape(H, W)


def disparity_gradient(s: Setup, c: dict) -> tuple[np.ndarray, np.ndarray]:
    """dD/du, dD/dv (output px per px) of every pixel's tangent plane (pinhole rays)."""
    r = s.rig
    H, W = c["z"].shape
    rows = np.arange(H)
    Rr, Cr = c["R_rows"], c["C_rows"]
    n_cam = np.einsum("hji,hwj->hwi", Rr, c["normal"])   # R^T n
    p_cam = np.einsum("hji,hwj->hwi", Rr, c["point"] - Cr[rows][:, None, :])
    cpl = np.einsum("hwi,hwi->hw", n_cam, p_cam)         # plane n.X = cpl in the camera frame
    with np.errstate(divide="ignore", invalid="ignore"):
        gx = r.baseline_m * n_cam[..., 0] / cpl
        gy = r.fx * r.baseline_m * n_cam[..., 1] / (cpl * r.fy)
    return np.nan_to_num(gx), np.nan_to_num(gy)


def foreground_edges(s: Setup, c: dict, D0: np.ndarray, jump: float) -> np.ndarray:
    """(H, W) True on the near side of a depth discontinuity of the ideal disparity D0: a 4-neighbour
    pair whose disparity differs by more than ``jump`` (output px) from what EITHER pixel's tangent
    plane predicts (so slopes and creases are not edges); the pixel with the larger disparity."""
    gx, gy = disparity_gradient(s, c)
    fg = np.zeros(D0.shape, bool)
    for axis, g in ((1, gx), (0, gy)):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        Da, Db, ga, gb = D0[a], D0[b], g[a], g[b]
        disc = (np.abs(Db - (Da + ga)) > jump) & (np.abs(Da - (Db - gb)) > jump)
        fg[a] |= disc & (Da > Db)
        fg[b] |= disc & (Db > Da)
    return fg


def fatten(s: Setup, c: dict, D0: np.ndarray) -> np.ndarray:
    """Edge fattening on the ideal disparity D0 (output px): a pixel whose (2 r + 1)^2 window holds a
    foreground edge pixel with a disparity above its own by more than ``min_jump_px`` takes the
    largest such disparity (the block matcher locks onto the nearer surface)."""
    rad, jump = s.params["radius_px"], s.params["min_jump_px"]
    DF = np.where(foreground_edges(s, c, D0, jump), D0, -np.inf)
    M = ndimage.maximum_filter(DF, size=2 * rad + 1, mode="constant", cval=-np.inf)
    return np.where(M > D0 + jump, M, D0)


def measure(s: Setup, k: int, noise_seed: int, c: dict | None = None) -> np.ndarray:
    """Measured z-depth (m, 0 = hole) of frame k."""
    r = s.rig
    c = cast(s, k) if c is None else c
    H, W = c["z"].shape
    nrng = np.random.default_rng([_SALT_NOISE, int(noise_seed), int(k)])
    gauss = nrng.standard_normal((H, W))
    unif = nrng.random((H, W))
    hit = c["hit"]
    with np.errstate(divide="ignore"):
        D0 = np.where(hit, r.fb / np.where(hit, c["z"], 1.0), 0.0)
    e, p = s.effect, s.params
    if e == "edge_fattening":
        D0 = fatten(s, c, D0)
    D = D0 + r.sigma_d * gauss
    fb = r.fb
    if e == "disparity_quantization":
        D = r.s0_px - p["step_px"] * np.round((r.s0_px - D) / p["step_px"])
    if e == "depth_bias":
        D = D + p["disparity_offset_px"]
        fb = fb * (1 + p["scale_error"])
    valid = hit & (D > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(valid, fb / np.where(valid, D, 1.0), 0.0)
    if e == "incidence_dropout":
        th = np.arccos(np.clip(c["cos"], 0, 1))
        x = np.tan(np.minimum(th, math.radians(89.9))) / math.tan(math.radians(p["angle50_deg"]))
        valid &= unif >= 1 - np.exp(-math.log(2) * x ** p["weibull_k"])
    if e == "low_reflectance":
        with np.errstate(over="ignore"):
            valid &= unif >= np.exp(-math.log(2) * (c["signal"] / p["signal50"]) ** p["weibull_m"])
    if e == "projector_shadow":
        valid &= ~shadow_mask(s, c)
    valid &= (z >= r.near_m) & (z <= r.far_m)
    return np.where(valid, z, 0.0)


def _gauss_mean_std(fn, sigma):
    x, w = np.polynomial.hermite_e.hermegauss(80)
    w = w / w.sum()
    vals = fn(sigma * x)
    m = float(vals @ w)
    return m, float(np.sqrt(max(((vals - m) ** 2) @ w, 0.0)))


def truth(s: Setup) -> dict:
    """The answer: effect, seed, noise2m, bias_at_m, params (see the module docstring)."""
    r = s.rig
    D2 = r.fb / 2.0
    _, noise2m = _gauss_mean_std(lambda n: r.fb / (D2 + n), r.sigma_d)
    bias = None
    if s.effect == "depth_bias":
        p = s.params
        bias = {}
        for zt in (1.0, 2.0, 3.0):
            m, _ = _gauss_mean_std(lambda n: r.fb * (1 + p["scale_error"]) / (r.fb / zt + n + p["disparity_offset_px"]),
                                   r.sigma_d)
            bias[zt] = m - zt
        s.params["bias_noise_free_at_m"] = {
            str(zt): r.fb * (1 + p["scale_error"]) / (r.fb / zt + p["disparity_offset_px"]) - zt for zt in (1.0, 2.0, 3.0)}
    return {"effect": s.effect, "seed": s.seed, "noise2m": noise2m, "bias_at_m": bias, "params": s.params}


def _camera_json(r: Rig) -> dict:
    return {"width": r.width, "height": r.height, "fx": r.fx, "fy": r.fy, "cx": r.cx, "cy": r.cy,
            "depth_scale": r.depth_scale, "distortion": [0.0, 0.0, 0.0, 0.0, 0.0],
            "sensor": {"type": "structured_light", "baseline_m": r.baseline_m,
                       "projector_offset_m": [r.side * r.baseline_m, 0.0, 0.0]}}


def _write(path: Path, data: bytes | str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    path.write_bytes(data)


def generate(out: str | Path, effect: str | None, seed: int, n_frames: int = 4, width: int = 160,
             height: int = 120, noise_seed: int | None = None) -> dict:
    """Write the sequence of ``(seed, effect)`` to ``out`` (TUM layout + camera.json + scene.json +
    answer.json) and return the answer (see the module docstring)."""
    out = Path(out)
    s = build(seed, effect, n_frames, width, height)
    ns = int(seed) * 1_000_003 + 7 if noise_seed is None else int(noise_seed)
    r = s.rig
    mats, meshes = {}, []
    for part in s.parts:
        Vs, Fs, off = [], [], 0
        for p in part.prims:
            V, F = _mesh_of(p)
            Vs.append(V)
            Fs.append(F + off)
            off += len(V)
        _write(out / "meshes" / f"{part.name}.ply", _ply_bytes(np.concatenate(Vs), np.concatenate(Fs)))
        mats[f"mat_{part.name}"] = {"albedo": part.albedo, "specular": 0.0}
        meshes.append({"file": f"meshes/{part.name}.ply", "name": part.name, "material": f"mat_{part.name}"})
    _write(out / "scene.json", json.dumps({"units": "m", "meshes": meshes, "materials": mats}, indent=1))
    _write(out / "camera.json", json.dumps(_camera_json(r), indent=1))
    d_lines = ["# depth maps (blind_sensor)", "# timestamp filename"]
    c_lines = ["# colour images (blind_sensor)", "# timestamp filename"]
    g_lines = ["# ground truth trajectory (camera-to-world)", "# timestamp tx ty tz qx qy qz qw"]
    Rg, Cg = s.motion.pose(s.timestamps)
    for k, ts in enumerate(s.timestamps):
        c = cast(s, k)
        z = measure(s, k, ns, c)
        dv = np.rint(z * r.depth_scale)
        dv = np.where((dv > 0) & (dv <= 65535), dv, 0).astype(np.uint16)
        grey = np.where(c["hit"], c["albedo"] * (0.25 + 0.75 * c["cos"]), 0.0)
        rgb = np.repeat((np.clip(grey, 0, 1) * 255).round().astype(np.uint8)[..., None], 3, -1)
        name = f"{ts:.6f}"
        _write(out / "depth" / f"{name}.png", _png(dv))
        _write(out / "rgb" / f"{name}.png", _png(rgb))
        d_lines.append(f"{name} depth/{name}.png")
        c_lines.append(f"{name} rgb/{name}.png")
        q = _quat(Rg[k])
        g_lines.append(f"{name} " + " ".join(f"{x:.9f}" for x in (*Cg[k], *q)))
    _write(out / "depth.txt", "\n".join(d_lines) + "\n")
    _write(out / "rgb.txt", "\n".join(c_lines) + "\n")
    _write(out / "groundtruth.txt", "\n".join(g_lines) + "\n")
    ans = truth(s)
    js = dict(ans)
    if js["bias_at_m"] is not None:
        js["bias_at_m"] = {str(k): v for k, v in js["bias_at_m"].items()}
    _write(out / "answer.json", json.dumps(js, indent=1))
    return ans


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(description="write one blind structured-light sequence")
    ap.add_argument("out")
    ap.add_argument("--effect", default=None, choices=[*EFFECTS, "none"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--noise-seed", type=int, default=None)
    a = ap.parse_args()
    eff = None if a.effect in (None, "none") else a.effect
    print(json.dumps(generate(a.out, eff, a.seed, a.frames, a.width, a.height, a.noise_seed), indent=1,
                     default=str))
