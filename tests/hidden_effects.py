"""An independent generator of "measured" depth sequences with one hidden sensor effect (or a pair).

The sensor lab must find effects in data that did NOT come from our simulator, so this module
re-implements every effect its own way, from the ideal geometry only (``synth.render``'s
ray caster, ``data_tools`` I/O, numpy/scipy): it never imports ``synth.sensor``. Formulas and
parameterisations deliberately differ from ``synth/sensor/effects``:

==========================  ====================================================================
base noise                  Gaussian noise in the ABSOLUTE disparity d = f b / z (sigma_d px),
                            z' = f b / (d + sigma_d n)  (the model has axial noise in depth)
base range                  z' outside [range_min_m, range_max_m] -> hole
projector_shadow            own shadow rays: first hit from the projector centre towards each
                            surface point shorter than the distance (minus a relative
                            tolerance), or the point faces away from the projector -> hole
disparity_quantization      absolute disparity rounded to multiples of ``step_px`` (the model
                            quantises the disparity relative to a reference plane)
incidence_dropout           hole with probability 1 / (1 + exp((cos(theta) - cos50) / width_cos))
                            (a logistic in the cosine, not in the angle)
lens_distortion             Brown-Conrady k1, k2 (+ p1, p2): every distorted pixel takes the
                            depth of the pinhole pixel it sees, found by fixed-point inversion
                            (not OpenCV), nearest neighbour
depth_bias                  polynomial in z: z' = z + c0 + c1 (z - 2) + c2 (z - 2)^2
edge_fattening              foreground dilated by a DISK of radius r px: a pixel whose disk
                            holds a surface nearer by more than 4 % takes the nearest depth
low_reflectance             hole with probability clip((a_hi - albedo) / (a_hi - a_lo), 0, 1):
                            a soft ramp in the material albedo only (no distance, no angle)
==========================  ====================================================================

The default scene is a compact "studio": floor, back and side walls, boxes and a column of
different albedos in front (projector shadows, depth edges, grazing floor and side wall, dark
materials), seen by a 320x240 structured-light camera (f = 290 px, b = 7.5 cm, projector at
+x) moving along a short arc; ``scene="room"`` uses the project's furnished room instead. :func:`generate` writes a real sequence folder (TUM layout,
camera.json with the sensor block, scene.json with meshes) and returns the drawn parameters.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from data_tools.camera import Camera, Intrinsics, SensorSpec
from data_tools.geometry import look_at
from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material, SceneSpec
from data_tools.sequence import Frame, SequenceWriter

HIDDEN_EFFECTS = ("projector_shadow", "disparity_quantization", "incidence_dropout", "lens_distortion",
                  "depth_bias", "edge_fattening", "low_reflectance")
"""Effects the generator can hide (names match the simulator's registry)."""

WIDTH, HEIGHT, FOCAL, BASELINE = 320, 240, 290.0, 0.075


def _box(name, material, lo, hi, color) -> TriMesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    # vertices: index = x + 2 y + 4 z (bits); outward counter-clockwise faces
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = []
    for a, b, cc, d in faces:
        tris += [(a, b, cc), (a, cc, d)]
    return TriMesh(c, np.array(tris), name, material, np.tile(color, (8, 1)))


def _quad(name, material, corners, color) -> TriMesh:
    return TriMesh(np.asarray(corners, float), np.array([(0, 1, 2), (0, 2, 3)]), name, material,
                   np.tile(color, (4, 1)))


def studio_scene() -> SceneSpec:
    """The test scene (z up, metres): room corner with boxes of four albedos in front."""
    mats = {"white_wall": Material(0.85, 0.0), "grey_floor": Material(0.35, 0.0),
            "white_box": Material(0.8, 0.0), "cardboard": Material(0.55, 0.0),
            "dark_plastic": Material(0.10, 0.0), "black_fabric": Material(0.03, 0.0)}
    m = [
        _quad("floor", "grey_floor", [[-2.5, -2, 0], [2.5, -2, 0], [2.5, 3, 0], [-2.5, 3, 0]], (0.35,) * 3),
        _quad("back_wall", "white_wall", [[-2.5, 2.6, 0], [2.5, 2.6, 0], [2.5, 2.6, 2.6], [-2.5, 2.6, 2.6]], (0.85,) * 3),
        _quad("side_wall", "white_wall", [[-1.6, -2, 0], [-1.6, 3, 0], [-1.6, 3, 2.6], [-1.6, -2, 2.6]], (0.8,) * 3),
        _box("box_white", "white_box", (-0.15, 0.9, 0.0), (0.35, 1.3, 0.55), (0.8,) * 3),
        _box("box_black", "black_fabric", (-1.0, 1.3, 0.0), (-0.45, 1.8, 0.7), (0.05,) * 3),
        _box("column", "dark_plastic", (0.65, 1.5, 0.0), (0.95, 1.8, 1.6), (0.1,) * 3),
        _box("box_card", "cardboard", (-0.35, 0.3, 0.0), (0.0, 0.6, 0.35), (0.55, 0.42, 0.3)),
        _box("shelf", "cardboard", (0.5, 2.2, 0.8), (1.5, 2.6, 0.9), (0.55, 0.42, 0.3)),
    ]
    return SceneSpec(m, mats)


def room_scene() -> SceneSpec:
    """The project's furnished ``room`` scene (synth.scenes), for a second, more cluttered layout."""
    from synth.scenes import build_scene
    return build_scene("room", seed=0)


def room_trajectory(n_frames: int, sweep: float = 1.0) -> np.ndarray:
    """Poses in the room looking at the table, chairs and the dark pouf/bin."""
    poses = []
    for s in np.linspace(-1.0, 1.0, n_frames) * sweep:
        eye = np.array([-0.2 + 0.5 * s, -1.8, 1.5])
        target = np.array([0.1 + 0.4 * s, 0.3, 0.5])
        poses.append(look_at(eye, target))
    return np.asarray(poses)


def camera(width: int = WIDTH, height: int = HEIGHT) -> Camera:
    f = FOCAL * width / WIDTH
    intr = Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
    return Camera(intr, 5000.0, SensorSpec("structured_light", BASELINE, (BASELINE, 0.0, 0.0),
                                           {"device": "hidden-effect generator (tests/hidden_effects.py)"}))


def trajectory(n_frames: int, sweep: float = 1.0) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses on a short arc in front of the scene (``sweep`` = 1: 0.9 m
    from side to side, i.e. a fast camera at 30 Hz whose motion the simulator treats as cuts;
    ~0.05 gives hand-held speeds where rolling shutter / motion blur are in play)."""
    poses = []
    for s in np.linspace(-1.0, 1.0, n_frames) * sweep:
        eye = np.array([0.45 * s, -1.0 + 0.1 * s * s, 1.25 + 0.1 * s])
        target = np.array([0.1 * s, 1.5, 0.55])
        poses.append(look_at(eye, target))
    return np.asarray(poses)


SCENES = {"studio": (studio_scene, trajectory), "room": (room_scene, room_trajectory)}
"""Scene builders and their trajectories."""


def hidden_set(effect: str | None) -> tuple[str, ...]:
    """The hidden effects named by ``effect``: None (base effects only), one name, or several joined
    by ``+`` (``"depth_bias+lens_distortion"``: both hidden in the same frames)."""
    if effect is None:
        return ()
    names = tuple(e for e in str(effect).split("+") if e)
    unknown = [e for e in names if e not in HIDDEN_EFFECTS]
    if unknown or len(set(names)) != len(names):
        raise ValueError(f"unknown or repeated hidden effect in {effect!r}; known: {', '.join(HIDDEN_EFFECTS)}")
    return names


def draw_params(effect: str | None, rng: np.random.Generator) -> dict:
    """Random parameters of the base effects and of the hidden one(s) (see :func:`hidden_set`; the
    draws of a single effect are the same whether or not pairs exist: each effect draws in turn)."""
    p = {"sigma_d_px": float(rng.uniform(0.05, 0.09)), "range_min_m": 0.5, "range_max_m": float(rng.uniform(4.5, 6.0))}
    for e in hidden_set(effect):
        p.update(_draw_effect(e, rng))
    return p


def _draw_effect(effect: str, rng: np.random.Generator) -> dict:
    """Random true parameters of one hidden effect."""
    p = {}
    if effect == "projector_shadow":
        p["tolerance_rel"] = float(rng.uniform(0.002, 0.01))
    elif effect == "disparity_quantization":
        p["step_px"] = float(rng.uniform(0.3, 0.5))
    elif effect == "incidence_dropout":
        p["cos50"] = float(np.cos(np.radians(rng.uniform(58.0, 70.0))))
        p["width_cos"] = float(rng.uniform(0.02, 0.05))
    elif effect == "lens_distortion":
        p["k1"] = float(rng.choice([-1, 1]) * rng.uniform(0.12, 0.22))
        p["k2"] = float(rng.uniform(-0.05, 0.05))
        p["p1"] = float(rng.uniform(-0.002, 0.002))
        p["p2"] = float(rng.uniform(-0.002, 0.002))
    elif effect == "depth_bias":
        p["c0_m"] = float(rng.choice([-1, 1]) * rng.uniform(0.012, 0.025))
        p["c1"] = float(rng.uniform(-0.004, 0.004))
        p["c2_per_m"] = float(rng.choice([-1, 1]) * rng.uniform(0.003, 0.008))
    elif effect == "edge_fattening":
        p["radius_px"] = int(rng.integers(3, 7))
    elif effect == "low_reflectance":
        lo = float(rng.uniform(0.03, 0.07))
        p["albedo_lo"] = lo
        p["albedo_hi"] = lo + float(rng.uniform(0.06, 0.12))
    return p


# ------------------------------------------------------------------------------------------
# The effects, each its own way
# ------------------------------------------------------------------------------------------

def _shadow(renderer, r, pose, proj_cam, tol_rel) -> np.ndarray:
    """Holes where the segment projector -> surface point hits something first."""
    hit = r.hit
    P = r.points_world[hit].astype(np.float64)
    O = pose[:3, :3] @ np.asarray(proj_cam) + pose[:3, 3]
    d = P - O
    dist = np.linalg.norm(d, axis=1)
    out = renderer.cast_rays(np.broadcast_to(O, P.shape), d)
    blocked = out["t_hit"] < dist * (1.0 - tol_rel) - 1e-3
    n_w = r.normals_cam[hit].astype(np.float64) @ pose[:3, :3].T
    away = np.einsum("ij,ij->i", n_w, O - P) <= 0
    m = np.zeros(hit.shape, bool)
    m[hit] = blocked | away
    return m


def _undistort_map(intr: Intrinsics, k1, k2, p1, p2) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole pixel (float) seen by every distorted pixel (fixed-point Brown-Conrady inversion)."""
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    xd, yd = (u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    x, y = xd.copy(), yd.copy()
    for _ in range(50):
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x, y = (xd - dx) / rad, (yd - dy) / rad
    return x * intr.fx + intr.cx, y * intr.fy + intr.cy


def _disk(radius: int) -> np.ndarray:
    yy, xx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    return (xx * xx + yy * yy) <= radius * radius + 0.5


def sense(effect: str | None, params: dict, renderer, r, pose, intr: Intrinsics, albedo_of_id: np.ndarray,
          rng: np.random.Generator) -> np.ndarray:
    """The measured depth (H, W) float32 of one frame from its ideal render ``r``; ``effect`` as
    in :func:`hidden_set` (several effects act in the fixed order of the device's path below)."""
    from scipy import ndimage
    hidden = hidden_set(effect)
    z = np.where(r.hit, r.depth, 0.0).astype(np.float64)
    fb = intr.fx * BASELINE
    holes = ~r.hit
    if "edge_fattening" in hidden:
        far = np.where(r.hit, z, np.inf)
        zmin = ndimage.minimum_filter(far, footprint=_disk(params["radius_px"]), mode="nearest")
        fat = np.isfinite(zmin) & (zmin < far * 0.96)
        z = np.where(fat, zmin, z)
        holes &= ~fat
    if "projector_shadow" in hidden:
        holes |= _shadow(renderer, r, pose, (BASELINE, 0.0, 0.0), params["tolerance_rel"])
    if "incidence_dropout" in hidden:
        cos_t = np.abs(np.einsum("hwk,hwk->hw", r.normals_cam, r.ray_dirs_cam))
        p = 1.0 / (1.0 + np.exp(np.clip((cos_t - params["cos50"]) / params["width_cos"], -50, 50)))
        holes |= rng.random(z.shape) < p
    if "low_reflectance" in hidden:
        a = albedo_of_id[r.instance_ids]
        p = np.clip((params["albedo_hi"] - a) / (params["albedo_hi"] - params["albedo_lo"]), 0.0, 1.0)
        holes |= r.hit & (rng.random(z.shape) < p)
    # base noise in the absolute disparity
    with np.errstate(divide="ignore"):
        d = np.where(z > 0, fb / np.maximum(z, 1e-9), 0.0)
    d = d + params["sigma_d_px"] * rng.standard_normal(z.shape)
    if "disparity_quantization" in hidden:
        d = params["step_px"] * np.round(d / params["step_px"])
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where((d > 0) & ~holes, fb / d, 0.0)
    if "depth_bias" in hidden:
        zz = z - 2.0
        z = np.where(z > 0, z + params["c0_m"] + params["c1"] * zz + params["c2_per_m"] * zz * zz, 0.0)
    z[(z < params["range_min_m"]) | (z > params["range_max_m"])] = 0.0
    if "lens_distortion" in hidden:
        mu, mv = _undistort_map(intr, params["k1"], params["k2"], params["p1"], params["p2"])
        ui, vi = np.rint(mu).astype(int), np.rint(mv).astype(int)
        inside = (ui >= 0) & (ui < intr.width) & (vi >= 0) & (vi < intr.height)
        out = np.zeros_like(z)
        out[inside] = z[vi[inside], ui[inside]]
        z = out
    return z.astype(np.float32)


def generate(out_dir, effect: str | None, seed: int = 0, n_frames: int = 8, width: int = WIDTH,
             height: int = HEIGHT, sweep: float = 1.0, scene: str = "studio", noise_seed: int | None = None) -> dict:
    """Write a measured sequence with ``effect`` hidden (None: base effects only) to ``out_dir``.

    ``noise_seed``: draw the noise (and random dropouts) of the frames from this seed instead of
    ``seed`` - the same sensor (parameters from ``seed``) measuring the same scene again.
    Returns the drawn parameters (``{"effect", "seed", ...}``).
    """
    from synth.render import IdealRenderer
    rng = np.random.default_rng([seed, 7919])
    params = draw_params(effect, rng)
    build, traj = SCENES[scene]
    scene_name, scene = scene, build()
    cam = camera(width, height)
    intr = cam.intrinsics
    renderer = IdealRenderer(scene)
    albedo_of_id = np.array([0.0] + [scene.material_of(m).albedo for m in scene.meshes])
    poses = traj(n_frames, sweep)
    out_dir = Path(out_dir)
    with SequenceWriter(out_dir, cam, scene, overwrite=True) as w:
        for i, T in enumerate(poses):
            r = renderer.render(T, intr, with_rgb=True)
            z = sense(effect, params, renderer, r, T, intr, albedo_of_id,
                      np.random.default_rng([seed if noise_seed is None else noise_seed, i]))
            w.write(Frame(1.0 + i / 30.0, z, r.rgb, T, i))
    return {"effect": effect, "seed": seed, "scene": scene_name, **params}


# ------------------------------------------------------------------------------------------
# Planar-target captures with a Herrera-style per-pixel disparity distortion
# ------------------------------------------------------------------------------------------

HERRERA_C0, HERRERA_C1 = 3.1121, -0.0028525
"""z = 1 / (c1 k + c0) for the raw disparity code k (Kinect-like values, 1/m and 1/m per code)."""


def herrera_beta(width: int = WIDTH, height: int = HEIGHT, amplitude: float = 4.0, stripes: float = 1.5,
                 period_px: float | None = None) -> np.ndarray:
    """(H, W) beta map in RAW CODES (Herrera's units): a bowl growing to ``amplitude`` codes in the
    corners plus vertical stripes of ``stripes`` codes (Smisek et al.'s columns)."""
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = ((uu - (width - 1) / 2) ** 2 + (vv - (height - 1) / 2) ** 2) / (((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2)
    period = period_px or width / 5.0
    return amplitude * r2 + stripes * np.sin(2 * np.pi * uu / period)


def herrera_beta_px_at(beta_raw: np.ndarray, z_m: float, alpha: tuple[float, float], fb: float) -> np.ndarray:
    """The disparity error in PIXELS (measured - true, realgap's d = f b / z) that ``beta_raw`` with
    Herrera's ``alpha = (a0, a1)`` causes on a surface at depth ``z_m``."""
    k = (1.0 / z_m - HERRERA_C0) / HERRERA_C1
    codes_per_px = 1.0 / (fb * HERRERA_C1)                 # dk/dd (negative: codes fall as d rises)
    return -beta_raw * np.exp(alpha[0] - alpha[1] * k) / codes_per_px


def generate_plane_capture(out_dir, distances, beta_raw: np.ndarray | None, alpha=(2.22, 0.003), seed: int = 0,
                           sigma_k: float = 0.6, width: int = WIDTH, height: int = HEIGHT, tilt_deg: float = 12.0) -> dict:
    """A hand-held capture of a large flat wall (6 x 6 m) at ``distances`` (m, one frame each, the
    camera tilted up to ``tilt_deg``), measured through Herrera et al.'s RAW-CODE model, which
    shares no code with ``synth.sensor``: the true raw code k of each pixel gets Gaussian noise of
    ``sigma_k`` codes, the distortion makes the device report ``k_meas = k - beta(u, v) exp(a0 -
    a1 k)`` (the inverse of Herrera's correction ``k + beta exp(a0 - a1 k)``), the code is rounded
    to an integer (11-bit device) and converted with ``z = 1 / (c1 k + c0)`` (Kinect-like c0, c1).
    The default alpha makes exp(a0 - a1 k) = 1 at 1 m (k = 740), 0.59 at 2 m, 1.57 at 0.7 m.
    Writes the TUM layout with poses and scene.json; returns the parameters."""
    from synth.render import IdealRenderer
    cam = camera(width, height)
    intr = cam.intrinsics
    fb = intr.fx * BASELINE
    scene = SceneSpec([_quad("wall", "wall", [[-3, 3, -1.5], [3, 3, -1.5], [3, 3, 4.5], [-3, 3, 4.5]],
                             (0.7, 0.7, 0.7))], {"wall": Material(0.6, 0.0)})
    renderer = IdealRenderer(scene)
    rng = np.random.default_rng([seed, 4242])
    out_dir = Path(out_dir)
    with SequenceWriter(out_dir, cam, scene, overwrite=True) as w:
        for i, dist in enumerate(distances):
            yaw, pitch = np.radians(rng.uniform(-tilt_deg, tilt_deg, size=2))
            eye = np.array([rng.uniform(-0.3, 0.3), 3.0 - dist, 1.4 + rng.uniform(-0.2, 0.2)])
            target = eye + np.array([np.sin(yaw), np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
            T = look_at(eye, target)
            r = renderer.render(T, intr, with_rgb=True)
            z = np.where(r.hit, r.depth, 0.0).astype(np.float64)
            with np.errstate(divide="ignore"):
                k = np.where(z > 0, (1.0 / np.maximum(z, 1e-9) - HERRERA_C0) / HERRERA_C1, 0.0)
            k = k + sigma_k * rng.standard_normal(z.shape)
            if beta_raw is not None:
                k = k - beta_raw * np.exp(alpha[0] - alpha[1] * k)
            k = np.round(k)
            with np.errstate(divide="ignore", invalid="ignore"):
                zm = np.where(z > 0, 1.0 / (HERRERA_C1 * k + HERRERA_C0), 0.0)
            zm[(zm < 0.4) | (zm > 6.0) | ~np.isfinite(zm)] = 0.0
            w.write(Frame(1.0 + i / 30.0, zm.astype(np.float32), r.rgb, T, i))
    return {"distances": list(map(float, distances)), "alpha": list(alpha), "sigma_k": sigma_k, "fb": fb}
