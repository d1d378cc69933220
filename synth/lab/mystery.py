"""The "mystery sensor": an independent hidden-effect generator for checking the sensor lab.

Written from the literature (Khoshelham & Elberink 2012, the Kinect v1 depth model; thesis ch. 3),
sharing no code with the project's simulator: every ray is cast analytically in numpy and every
effect is implemented here from its physics. A sequence is a Kinect-v1-like structured-light
camera looking at a floor with boxes, vertical cylinders and slanted panels in front of a back wall,
static or moving, with one hidden effect drawn from the lab's catalog on top of an always-on base.

The sensor (all drawn per seed):

* intrinsics: horizontal field of view 54-64 deg at a native 640 px width (``f_native``), fy within
  +-1 % of fx, principal point within +-6 native px of the centre; the output image is the native one
  scaled to ``width`` (f_out = f_native width / 640);
* raw 11-bit disparity ``d`` in 1/8 native pixel units and its conversion ``z = 1 / (c0 + c1 d)``
  (c1 < 0: d grows with depth, as in the Kinect): c0 in [2.85, 3.35] 1/m, c1 in
  [-0.0031, -0.0027] 1/m; the baseline follows, b = -1 / (8 f_native c1) (0.067-0.083 m), and
  camera.json holds that b and the projector at (b, 0, 0);
* base, always on: disparity noise, i.i.d. Gaussian per pixel with std ``sigma_raw`` in
  [0.35, 0.65] raw units (0.044-0.081 native px; depth std z^2 sigma_raw |c1|: axial noise growing
  with z^2) and range limits (min depth 0.45-0.8 m, max depth 3.0-4.5 m: pixels outside report
  the invalid code 2047, written as 0);
* ONE hidden effect (or none), parameters drawn from ranges (see :data:`EFFECTS`):

  - ``depth_bias``: the converter's calibration is off (c0 by 0.15-0.6 native px of disparity, c1 by
    up to +-1 % in half the seeds) - it uses c0' = c0 + dc0 and optionally
    c1' = c1 (1 + kappa), so 1/z' = c0' + c1' d (a disparity offset, and a depth scale when kappa != 0);
  - ``disparity_quantization``: the device reports integer multiples of ``m`` raw units
    (m in 1..4); without it the raw disparity keeps its sub-unit fraction (a device with finer
    sub-pixel refinement);
  - ``edge_fattening``: the square matching window (2r+1)^2 (r 2-4 output px) sees a surface within r
    pixels whose disparity is 0.8-2 output px larger and locks onto it (foreground fattening);
  - ``incidence_dropout``: dots lose contrast on grazing surfaces; the pixel drops with probability
    Phi((theta - theta50) / s), theta the angle between the ideal normal and the camera ray;
  - ``low_reflectance``: returned signal albedo cos(theta) / r^2 (r the ray length, m); drop with
    probability Phi(log10(s50 / signal) / w) (w in decades);
  - ``projector_shadow``: pixels the projector cannot see (an analytic shadow ray to the projector)
    are holes;
  - ``lens_distortion``: the IR lens distorts by k1 (OpenCV: x_d = x (1 + k1 r^2)); camera.json
    says nothing about it;
  - ``rolling_shutter``: row v is exposed readout v / (H - 1) after the first row (readout
    0.015-0.033 s), which is exposed at the frame's timestamp; the camera always moves.

``answer.json`` beside the sequence (the lab never reads it) names the effect and its true parameters
in the lab's units (``python -m app sensor effects NAME``): the depth_bias offset in px of f b / z at
the OUTPUT resolution, step_px and level_phase of f b / z = (k + phase) step, logistic widths matched
to the Gaussian CDF's slope at the midpoint (s_logistic = s_gauss sqrt(2 pi) / 4).

Approximations: cylinders are written to the mesh file as 128-gons (a chord error <= 0.1 mm on the
largest, which the lab's ideal render sees, the analytic cast does not); noise is i.i.d. per pixel
(a real Kinect's is spatially correlated over the matching window); no speckle, IR image or
correlation is simulated - each effect is its closed-form outcome.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

NATIVE_WIDTH = 640
"""The sensor's native image width, pixels; raw disparity units are 1/8 of a native pixel."""
SUBPIXEL = 8
"""Raw disparity units per native pixel (the Kinect v1's 1/8 px)."""
INVALID_RAW = 2047
"""The 11-bit code of 'no measurement'."""
EFFECTS = ("depth_bias", "disparity_quantization", "edge_fattening", "incidence_dropout", "low_reflectance",
           "projector_shadow", "lens_distortion", "rolling_shutter")
"""The hidden effects this generator can hide, by the lab's catalog names."""
CYLINDER_SEGMENTS = 128
"""Facets of a cylinder in the mesh written for the lab."""


def raw_to_depth(d: np.ndarray, c0: float, c1: float) -> np.ndarray:
    """Kinect raw disparity -> z-depth, metres: z = 1 / (c0 + c1 d); the invalid code 2047 and
    non-positive 1/z give 0."""
    d = np.asarray(d, np.float64)
    inv = c0 + c1 * d
    with np.errstate(divide="ignore"):
        z = np.where((inv > 0) & (d < INVALID_RAW), 1.0 / np.where(inv > 0, inv, 1.0), 0.0)
    return z


def depth_to_raw(z: np.ndarray, c0: float, c1: float) -> np.ndarray:
    """z-depth (m, > 0) -> raw disparity (float, not rounded): d = (1/z - c0) / c1; 0 depth -> 2047."""
    z = np.asarray(z, np.float64)
    with np.errstate(divide="ignore"):
        return np.where(z > 0, (1.0 / np.where(z > 0, z, 1.0) - c0) / c1, float(INVALID_RAW))


# ---------------------------------------------------------------------------------------------- scene
@dataclass
class Solid:
    """One analytic object: ``kind`` 'rect' (a finite plane: centre, two unit axes, half extents),
    'box' (centre, yaw rad, half sizes) or 'cyl' (vertical: base centre x y, radius, height)."""

    kind: str
    """'rect', 'box' or 'cyl'."""
    p: dict
    """The shape's parameters (metres, radians)."""
    albedo: float
    """Diffuse IR reflectance in [0, 1]."""
    name: str
    """Unique name (mesh file name)."""


def _phi(x):
    """Standard normal CDF (numpy only: erf via math on a vectorised call)."""
    return 0.5 * (1.0 + _erf(np.asarray(x, np.float64) / math.sqrt(2.0)))


_erf = np.vectorize(math.erf, otypes=[np.float64])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def draw_scene(rng: np.random.Generator) -> list[Solid]:
    """Floor (z = 0, world z up), a back wall at y = 5-7 m, 2-4 boxes, 1-3 cylinders and 1-2 slanted panels
    in x in [-1.6, 1.6], y in [1.4, 4.2] (the camera stands near y = -0.5 looking along +y)."""
    u = rng.uniform
    wall_y = u(5.0, 7.0)
    out = [Solid("rect", {"c": np.array([0.0, (wall_y - 3.0) / 2, 0.0]), "a1": np.array([1.0, 0, 0]),
                          "a2": np.array([0, 1.0, 0]), "h": (5.0, (wall_y + 3.0) / 2)}, u(0.3, 0.7), "floor"),
           Solid("rect", {"c": np.array([0.0, wall_y, 1.5]), "a1": np.array([1.0, 0, 0]),
                          "a2": np.array([0, 0, 1.0]), "h": (5.0, 1.5)}, u(0.4, 0.9), "wall")]
    for i in range(int(rng.integers(2, 5))):
        hs = np.array([u(0.12, 0.4), u(0.12, 0.4), u(0.1, 0.45)])
        out.append(Solid("box", {"c": np.array([u(-1.6, 1.6), u(1.4, 4.2), hs[2]]), "yaw": u(0, math.pi / 2),
                                 "h": hs}, u(0.08, 0.9), f"box{i}"))
    for i in range(int(rng.integers(1, 4))):
        out.append(Solid("cyl", {"c": np.array([u(-1.6, 1.6), u(1.4, 4.2)]), "r": u(0.08, 0.3),
                                 "H": u(0.3, 1.3)}, u(0.08, 0.9), f"cyl{i}"))
    for i in range(int(rng.integers(1, 3))):
        yaw, tilt = u(-0.9, 0.9), u(0.35, 1.2)          # panel leaning back by tilt from vertical
        a1 = _rot_z(yaw) @ np.array([1.0, 0, 0])
        back = _rot_z(yaw) @ np.array([0, 1.0, 0])
        a2 = math.cos(tilt) * np.array([0, 0, 1.0]) + math.sin(tilt) * back
        hh = (u(0.25, 0.6), u(0.25, 0.55))
        c = np.array([u(-1.4, 1.4), u(1.6, 4.0), 0.0]) + a2 * hh[1] + np.array([0, 0, 0.02])
        out.append(Solid("rect", {"c": c, "a1": a1, "a2": a2, "h": hh}, u(0.08, 0.9), f"panel{i}"))
    return out


def cast(solids: list[Solid], o: np.ndarray, D: np.ndarray, eps: float = 1e-6):
    """Nearest hit of rays o + t D (o (3,) or (N, 3), D (N, 3), not normalised) with ``solids``:
    (t (N,), inf where none; unit normals (N, 3); index of the solid (N,), -1 where none)."""
    n = D.shape[0]
    o = np.broadcast_to(np.asarray(o, np.float64), D.shape)
    best = np.full(n, np.inf)
    nrm = np.zeros((n, 3))
    idx = np.full(n, -1)
    for k, s in enumerate(solids):
        t, nn = _hit(s, o, D, eps)
        better = t < best
        best[better] = t[better]
        nrm[better] = nn[better]
        idx[better] = k
    return best, nrm, idx


def _hit(s: Solid, o, D, eps):
    n = D.shape[0]
    t = np.full(n, np.inf)
    nn = np.zeros((n, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        if s.kind == "rect":
            a1, a2, c = s.p["a1"], s.p["a2"], s.p["c"]
            nv = np.cross(a1, a2)
            den = D @ nv
            tt = ((c - o) @ nv) / den
            P = o + tt[:, None] * D
            ok = (np.abs((P - c) @ a1) <= s.p["h"][0]) & (np.abs((P - c) @ a2) <= s.p["h"][1]) & (tt > eps)
            t[ok] = tt[ok]
            nn[:] = nv
        elif s.kind == "box":
            R = _rot_z(s.p["yaw"])
            ol, Dl, h = (o - s.p["c"]) @ R, D @ R, s.p["h"]
            t1, t2 = (-h - ol) / Dl, (h - ol) / Dl
            tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
            tn = np.where(np.isnan(tn), -np.inf, tn)
            tf = np.where(np.isnan(tf), np.inf, tf)
            tmin, tmax = tn.max(1), tf.min(1)
            ok = (tmin <= tmax) & (tmin > eps)
            ax = tn.argmax(1)
            nl = np.zeros((n, 3))
            nl[np.arange(n), ax] = -np.sign(Dl[np.arange(n), ax])
            t[ok] = tmin[ok]
            nn = nl @ R.T
        else:
            cx, cy = s.p["c"]
            r, H = s.p["r"], s.p["H"]
            ox, oy = o[:, 0] - cx, o[:, 1] - cy
            a = D[:, 0] ** 2 + D[:, 1] ** 2
            b = 2 * (ox * D[:, 0] + oy * D[:, 1])
            cc = ox * ox + oy * oy - r * r
            disc = b * b - 4 * a * cc
            ts = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
            zs = o[:, 2] + ts * D[:, 2]
            side = (disc >= 0) & (ts > eps) & (zs >= 0) & (zs <= H)
            tc = (H - o[:, 2]) / D[:, 2]
            px, py = ox + tc * D[:, 0], oy + tc * D[:, 1]
            cap = (tc > eps) & (px * px + py * py <= r * r)
            tcap = np.where(cap, tc, np.inf)
            tside = np.where(side, ts, np.inf)
            t = np.minimum(tcap, tside)
            use_side = tside <= tcap
            nn[:, 2] = 1.0
            sx, sy = ox + ts * D[:, 0], oy + ts * D[:, 1]
            nn[use_side] = np.stack([sx / r, sy / r, np.zeros(n)], 1)[use_side]
    return t, nn


def solid_mesh(s: Solid):
    """(vertices (V, 3), triangles (F, 3)) of a solid, wound counter-clockwise from outside
    (rects: from the side their normal a1 x a2 points to)."""
    if s.kind == "rect":
        c, a1, a2, (h1, h2) = s.p["c"], s.p["a1"], s.p["a2"], s.p["h"]
        V = np.array([c - h1 * a1 - h2 * a2, c + h1 * a1 - h2 * a2, c + h1 * a1 + h2 * a2, c - h1 * a1 + h2 * a2])
        return V, np.array([[0, 1, 2], [0, 2, 3]])
    if s.kind == "box":
        h = s.p["h"]
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * h
        V = corners @ _rot_z(s.p["yaw"]).T + s.p["c"]
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        F = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    else:
        m = CYLINDER_SEGMENTS
        a = 2 * np.pi * np.arange(m) / m
        ring = np.stack([s.p["c"][0] + s.p["r"] * np.cos(a), s.p["c"][1] + s.p["r"] * np.sin(a)], 1)
        V = np.concatenate([np.c_[ring, np.zeros(m)], np.c_[ring, np.full(m, s.p["H"])],
                            [[*s.p["c"], 0.0], [*s.p["c"], s.p["H"]]]])
        F = []
        for i in range(m):
            j = (i + 1) % m
            F += [[i, j, m + j], [i, m + j, m + i], [2 * m, j, i], [2 * m + 1, m + i, m + j]]
        F = np.array(F)
    cen = V.mean(0)          # convex solids: wind every face outward
    tri = V[F]
    nv = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", nv, tri.mean(1) - cen) < 0
    F[flip] = F[flip][:, [0, 2, 1]]
    return V, F


# ---------------------------------------------------------------------------------------------- sensor
@dataclass
class Mystery:
    """Everything drawn for one sequence (see the module docstring for the ranges)."""

    width: int
    """Output image width, pixels."""
    height: int
    """Output image height, pixels."""
    f_native: float
    """fx at the native 640 px width, pixels."""
    fy_ratio: float
    """fy / fx."""
    pp_offset: tuple
    """Principal point offset from the image centre, native pixels (x, y)."""
    c0: float
    """Raw-to-depth constant, 1/m."""
    c1: float
    """Raw-to-depth slope, 1/m per raw unit (< 0)."""
    sigma_raw: float
    """Disparity noise std, raw units."""
    min_depth: float
    """Nearest reported depth, m."""
    max_depth: float
    """Farthest reported depth, m."""
    effect: str | None
    """The hidden effect (a name of :data:`EFFECTS`) or None."""
    hidden: dict = field(default_factory=dict)
    """The hidden effect's own parameters in this generator's terms."""

    @property
    def baseline(self) -> float:
        """b = -1 / (8 f_native c1), metres."""
        return -1.0 / (SUBPIXEL * self.f_native * self.c1)

    @property
    def scale(self) -> float:
        return self.width / NATIVE_WIDTH

    @property
    def intrinsics(self) -> tuple:
        """(fx, fy, cx, cy) at the output resolution."""
        f = self.f_native * self.scale
        return (f, f * self.fy_ratio, (self.width - 1) / 2 + self.pp_offset[0] * self.scale,
                (self.height - 1) / 2 + self.pp_offset[1] * self.scale)

    @property
    def fb(self) -> float:
        """f_out b, px m: the lab's f b (its disparity f b / z in output pixels)."""
        return self.intrinsics[0] * self.baseline

    @property
    def raw_px(self) -> float:
        """One raw unit in output pixels of disparity."""
        return self.scale / SUBPIXEL


def draw_sensor(rng: np.random.Generator, effect: str | None, width: int, height: int) -> Mystery:
    """Draw the sensor and the hidden effect's parameters (ranges in the module docstring)."""
    u = rng.uniform
    fov = math.radians(u(54.0, 64.0))
    m = Mystery(width, height, (NATIVE_WIDTH / 2) / math.tan(fov / 2), 1.0 + u(-0.01, 0.01),
                (u(-6, 6), u(-6, 6)), u(2.85, 3.35), u(-0.0031, -0.0027), u(0.35, 0.65), u(0.45, 0.8),
                u(3.0, 4.5), effect)
    sgn = 1.0 if rng.random() < 0.5 else -1.0
    if effect == "depth_bias":
        e_px = sgn * u(0.15, 0.6) * SUBPIXEL * m.raw_px    # a c0 error of 0.15-0.6 native px, in output px
        m.hidden = {"dc0": e_px / m.fb, "kappa": u(-0.01, 0.01) if rng.random() < 0.5 else 0.0}
    elif effect == "disparity_quantization":
        m.hidden = {"m_raw": int(rng.integers(1, 5))}
    elif effect == "edge_fattening":
        m.hidden = {"radius_px": int(rng.integers(2, 5)), "jump_px": u(0.8, 2.0)}
    elif effect == "incidence_dropout":
        m.hidden = {"theta50_deg": u(55.0, 75.0), "sigma_deg": u(0.8, 4.0)}
    elif effect == "low_reflectance":
        m.hidden = {"signal50": float(np.exp(u(math.log(0.003), math.log(0.02)))), "sigma_dec": u(0.05, 0.3)}
    elif effect == "projector_shadow":
        m.hidden = {"eps_m": u(0.001, 0.004)}
    elif effect == "lens_distortion":
        m.hidden = {"k1": sgn * u(0.06, 0.22)}
    elif effect == "rolling_shutter":
        m.hidden = {"readout_s": u(0.015, 0.033)}
    elif effect is not None:
        raise ValueError(f"unknown hidden effect {effect!r}; choose from {', '.join(EFFECTS)}")
    return m


def answer(m: Mystery) -> dict:
    """The hidden effect's true parameters in the lab's units (the module docstring says how)."""
    fb = m.fb
    slope = math.sqrt(2 * math.pi) / 4
    h = m.hidden
    e = m.effect
    if e == "depth_bias":
        # 1/z' = c0 + dc0 + c1 (1 + k) d = (1 + k)/z - k c0 + dc0  ->  z' = (1 + scale) / (1/z + e/fb)
        k = h["kappa"]
        scale = 1.0 / (1.0 + k) - 1.0
        e_px = fb * (h["dc0"] - k * m.c0) / (1.0 + k)
        p = {"disparity_offset_px": e_px, "scale": scale, "offset_m": 0.0, "radial_disparity_px": 0.0}
    elif e == "disparity_quantization":
        step = h["m_raw"] * m.raw_px
        p = {"step_px": step, "level_phase": float((fb * m.c0 / step) % 1.0)}
    elif e == "edge_fattening":
        p = {"radius_px": h["radius_px"], "window": "square", "jump_px": h["jump_px"]}
    elif e == "incidence_dropout":
        p = {"angle50_deg": h["theta50_deg"], "width_deg": h["sigma_deg"] * slope, "reference": "camera"}
    elif e == "low_reflectance":
        p = {"signal50": h["signal50"], "width_decades": h["sigma_dec"] * slope, "signal": "irradiance"}
    elif e == "projector_shadow":
        p = {"eps_m": h["eps_m"]}
    elif e == "lens_distortion":
        p = {"k1": h["k1"]}
    elif e == "rolling_shutter":
        p = {"readout_time_s": h["readout_s"], "reference_row": 0.0}   # the timestamp is the first row's
    else:
        p = {}
    return p


def depth_bias_at(m: Mystery, z: float) -> float:
    """The reported minus the true depth at true depth z (noise-free), metres (0 without depth_bias)."""
    if m.effect != "depth_bias":
        return 0.0
    d = float(depth_to_raw(np.array(z), m.c0, m.c1))
    zz = float(raw_to_depth(np.array(d), m.c0 + m.hidden["dc0"], m.c1 * (1 + m.hidden["kappa"])))
    return zz - z


# ---------------------------------------------------------------------------------------------- frames
def look_at(pos: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world (4, 4), OpenCV axes (x right, y down, z forward), world z up."""
    z = (target - pos) / np.linalg.norm(target - pos)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], 1)
    c, s = math.cos(roll), math.sin(roll)
    R = R @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, pos
    return T


def draw_motion(rng: np.random.Generator, moving: bool):
    """The camera's pose as a function of time t (s, 0 = the sequence's middle): 0.7-1.5 m high near
    y = -0.5, aimed at a point 2-3.2 m ahead; moving: a hand-held sideways walk at 0.1-0.5 m/s
    rising 0.02-0.1 m/s, the aim point drifting 0-0.3 m/s (speeds: the motion per frame does not depend
    on the number of frames). Returns ``pose(t) -> (4, 4)`` camera-to-world."""
    u = rng.uniform
    p0 = np.array([u(-0.4, 0.4), u(-0.9, -0.2), u(0.7, 1.5)])
    t0 = np.array([u(-0.4, 0.4), u(2.0, 3.2), u(0.1, 0.5)])
    roll = math.radians(u(-3, 3))
    if not moving:
        T = look_at(p0, t0, roll)
        return lambda t: T
    v = np.array([u(0.1, 0.5) * (1 if rng.random() < 0.5 else -1), u(-0.05, 0.05), u(0.02, 0.1)])
    drift = np.array([u(-0.3, 0.3), 0.0, 0.0])
    return lambda t: look_at(p0 + v * t, t0 + drift * t, roll)


def frame_times(n: int) -> np.ndarray:
    """Frame times of :func:`draw_motion`, 30 Hz centred on 0, seconds (timestamps are 1 s later)."""
    return (np.arange(n) - (n - 1) / 2) / 30.0


def draw_trajectory(rng: np.random.Generator, n: int, moving: bool) -> list[np.ndarray]:
    """The poses of ``n`` frames of :func:`draw_motion`."""
    pose = draw_motion(rng, moving)
    return [pose(t) for t in frame_times(n)]


def pixel_rays(m: Mystery, k1: float = 0.0) -> np.ndarray:
    """(H, W, 3) camera-frame ray directions with z = 1 of every pixel centre; with k1 the device's
    image is distorted (x_d = x (1 + k1 r^2)), inverted by fixed-point iteration."""
    fx, fy, cx, cy = m.intrinsics
    v, u = np.mgrid[0:m.height, 0:m.width].astype(np.float64)
    xd, yd = (u - cx) / fx, (v - cy) / fy
    x, y = xd.copy(), yd.copy()
    if k1:
        for _ in range(30):
            f = 1.0 + k1 * (x * x + y * y)
            x, y = xd / f, yd / f
    return np.stack([x, y, np.ones_like(x)], -1)


def _max_filter(a: np.ndarray, r: int) -> np.ndarray:
    """Max over the (2r+1)^2 square window (separable; borders padded with -inf)."""
    out = a
    for ax in (0, 1):
        p = np.pad(out, [(r, r) if i == ax else (0, 0) for i in range(2)], constant_values=-np.inf)
        n = out.shape[ax]
        out = np.max([np.take(p, np.arange(k, k + n), axis=ax) for k in range(2 * r + 1)], axis=0)
    return out


def render_frame(m: Mystery, solids: list[Solid], T: np.ndarray, rng: np.random.Generator, pose_at=None,
                 t: float = 0.0):
    """One measured depth frame (H, W) float32 metres (0 = hole), and (ideal z, |cos incidence|, albedo
    per pixel) for shading. ``rng`` draws this frame's noise and dropouts. With rolling_shutter hidden,
    ``pose_at(time)`` gives the pose of row v at t + v / (H - 1) readout (the timestamp is the first
    row's exposure; T is the pose at t)."""
    H, W = m.height, m.width
    k1 = m.hidden.get("k1", 0.0) if m.effect == "lens_distortion" else 0.0
    rays = pixel_rays(m, k1).reshape(-1, 3)
    R, o = T[:3, :3], T[:3, 3]
    D = rays @ R.T
    if m.effect == "rolling_shutter" and pose_at is not None:
        rows = [pose_at(t + v / (H - 1) * m.hidden["readout_s"]) for v in range(H)]
        Rr = np.repeat(np.stack([P[:3, :3] for P in rows]), W, axis=0)          # (H W, 3, 3)
        o = np.repeat(np.stack([P[:3, 3] for P in rows]), W, axis=0)
        D = np.einsum("nij,nj->ni", Rr, rays)
    t_hit, nrm, idx = cast(solids, o, D)
    hit = np.isfinite(t_hit)
    z = np.where(hit, t_hit, 0.0)                                    # rays have z = 1: t is z-depth
    ray_len = z * np.linalg.norm(rays, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", nrm, D)) / np.linalg.norm(rays, axis=1)
    albedo = np.array([s.albedo for s in solids] + [0.0])[idx]
    keep = hit.copy()
    e, h = m.effect, m.hidden
    if e == "incidence_dropout":
        theta = np.degrees(np.arccos(np.clip(cos, 0, 1)))
        keep &= rng.random(z.size) >= _phi((theta - h["theta50_deg"]) / h["sigma_deg"])
    elif e == "low_reflectance":
        sig = albedo * cos / np.maximum(ray_len, 1e-6) ** 2
        keep &= rng.random(z.size) >= _phi(np.log10(h["signal50"] / np.maximum(sig, 1e-12)) / h["sigma_dec"])
    elif e == "projector_shadow":
        proj = o + R @ np.array([m.baseline, 0.0, 0.0])
        P = o + D * z[:, None]
        sel = np.flatnonzero(hit)
        ts, _, _ = cast(solids, proj, P[sel] - proj)
        dist = np.linalg.norm(P[sel] - proj, axis=1)
        keep[sel[ts < 1.0 - h["eps_m"] / dist]] = False
    d_ideal = depth_to_raw(z, m.c0, m.c1)                           # float raw disparity
    if e == "edge_fattening":
        disp = np.where(hit, m.fb / np.where(hit, z, 1.0), -np.inf).reshape(H, W)   # output px
        near = _max_filter(disp, h["radius_px"])
        with np.errstate(invalid="ignore"):                         # -inf - -inf where both see nothing
            grab = (near - disp > h["jump_px"]) & np.isfinite(near)
        zf = np.where(grab, m.fb / np.where(grab, near, 1.0), z.reshape(H, W)).ravel()
        keep |= grab.ravel()
        d_ideal = depth_to_raw(zf, m.c0, m.c1)
    d = d_ideal + m.sigma_raw * rng.standard_normal(z.size)
    c0c, c1c = m.c0, m.c1
    if e == "disparity_quantization":
        d = h["m_raw"] * np.round(d / h["m_raw"])
    elif e == "depth_bias":
        c0c, c1c = m.c0 + h["dc0"], m.c1 * (1.0 + h["kappa"])
    d = np.where(keep, d, float(INVALID_RAW))
    zm = raw_to_depth(d, c0c, c1c)
    zm[(zm < m.min_depth) | (zm > m.max_depth)] = 0.0
    return (zm.reshape(H, W).astype(np.float32), z.reshape(H, W), cos.reshape(H, W), albedo.reshape(H, W))


def generate(path, effect: str | None = None, seed: int = 0, n_frames: int = 6, width: int = 320,
             height: int = 240, moving: bool | None = None, noise_seed: int | None = None) -> dict:
    """Write one mystery-sensor sequence to ``path`` (TUM layout + camera.json + scene.json) and
    ``answer.json`` beside the frames; returns the answer. ``effect``: a name of :data:`EFFECTS`, None
    (base only) or 'random' (drawn from the seed); ``moving`` None = drawn (half the seeds move).
    ``noise_seed`` (default ``seed``) draws only the per-frame noise and dropouts: the same sensor,
    scene and poses measured again. Deterministic per (seed, effect, size, n_frames, noise_seed)."""
    from data_tools.camera import Camera, Intrinsics, SensorSpec
    from data_tools.mesh import TriMesh
    from data_tools.scene_spec import Material, SceneSpec
    from data_tools.sequence import Frame, SequenceWriter
    rng = np.random.default_rng([int(seed), 4242])
    if effect == "random":
        effect = EFFECTS[int(rng.integers(len(EFFECTS)))]
    m = draw_sensor(rng, effect, int(width), int(height))
    solids = draw_scene(rng)
    if moving is None:
        moving = bool(rng.random() < 0.5) or effect == "rolling_shutter"     # a still camera hides it
    pose_at = draw_motion(rng, moving)
    times = frame_times(int(n_frames))
    fx, fy, cx, cy = m.intrinsics
    cam = Camera(Intrinsics(m.width, m.height, fx, fy, cx, cy), 5000.0,
                 SensorSpec("structured_light", m.baseline, (m.baseline, 0.0, 0.0)))
    meshes, mats = [], {}
    for s in solids:
        V, F = solid_mesh(s)
        meshes.append(TriMesh(V, F, s.name, f"mat_{s.name}"))
        mats[f"mat_{s.name}"] = Material(float(s.albedo), 0.0)
    path = Path(path)
    ns = int(seed if noise_seed is None else noise_seed)
    with SequenceWriter(path, cam, SceneSpec(meshes, mats), overwrite=True) as w:
        for i, t in enumerate(times):
            T = pose_at(t)
            depth, _, cos, alb = render_frame(m, solids, T, np.random.default_rng([ns, 77, i]), pose_at, t)
            g = np.clip(255 * alb * (0.25 + 0.75 * cos), 0, 255).astype(np.uint8)
            w.write(Frame(1.0 + t - times[0], depth, np.repeat(g[:, :, None], 3, 2), T, i))
    ans = {"generator": "synth.lab.mystery", "seed": int(seed), "effect": effect, "params": answer(m),
           "base": {"axial_noise": {"sigma2_per_m": m.sigma_raw * abs(m.c1), "sigma_raw": m.sigma_raw},
                    "range_limits": {"min_depth_m": m.min_depth, "max_depth_m": m.max_depth}},
           "sensor": {"c0": m.c0, "c1": m.c1, "baseline_m": m.baseline, "f_native": m.f_native, "fb": m.fb,
                      "raw_unit_px": m.raw_px, "moving": moving},
           "generator_params": m.hidden,
           "bias_at_m": {str(z): depth_bias_at(m, z) for z in (1.0, 2.0, 3.0)}}
    (path / "answer.json").write_text(json.dumps(ans, indent=1, default=float))
    return ans
