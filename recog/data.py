"""Training data: simulated depth views of every object, cut into patches, in three variants.

For each object the viewpoints are the vertices of a subdivided icosahedron on the upper
hemisphere (:func:`synth.sensor.views.hemisphere_viewpoints`, as in ``realgap synth views`` and
thesis section 3.4.3) times a set of in-plane rotations of the camera; every viewpoint is
jittered by a few degrees and its look-at point by a tenth of the object's size ("small pose
perturbations"), and its distance is drawn from a range that keeps the object at the size it
will have at test time. The object stands on a ground plane among random clutter boxes.

Every view is simulated ``draws`` times (the *pairs* of the pair loss: the same view under
different sensor noise) with one of three sensor models, the *variants* of the thesis'
comparison:

* ``clean``: ideal depth (the renderer alone; both draws are identical);
* ``gaussian``: ideal depth + Nguyen et al. 2012's axial noise, sigma(z) = 1.2 mm + 1.9 mm/m^2
  (z - 0.4 m)^2 (the "simple simulator" baseline: ``axial_noise`` with those parameters);
* ``physical``: the full structured-light pipeline of the preset (projector, IR capture, block
  matching, ...), with its parameters randomised per chunk of views and per draw within
  :data:`PHYSICAL_RANDOMISATION` (domain randomisation around the device), so that the pair
  loss teaches invariance to exactly what varies between devices.

Views are generated in chunks of ``chunk_views``: each chunk has its own clutter layout,
object albedo and (physical) sensor parameters, is simulated in a worker process and saved as
``DATA/<variant>/<object>/chunk_NNN.npz`` (atomically), so a killed run continues with the
missing chunks and the result does not depend on the number of workers.

The simulated image is a centred crop of the sensor (same optics, fewer pixels): views are
object-centred, so pixels far from the object only cost time.
"""
from __future__ import annotations

import math
import os
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError
from recog.objects import RecogObject
from recog.patches import PatchConfig, bbox_from_mask, extract_patch, resample_nearest, to_ray_frame

__all__ = ["DataConfig", "VARIANTS", "PHYSICAL_RANDOMISATION", "NGUYEN_AXIAL", "sensor_config", "view_grid",
           "generate_training_data", "load_training_data", "TrainingData", "object_scene", "distance_range",
           "chunk_scene", "ChunkScene"]

VARIANTS = ("clean", "gaussian", "physical")

NGUYEN_AXIAL = {"axial_noise.sigma0_m": 0.0012, "axial_noise.sigma1": 0.0, "axial_noise.sigma2_per_m": 0.0019,
                "axial_noise.z_offset_m": 0.4}
"""Nguyen, Izadi & Lovell 2012, Kinect v1 axial noise: sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m."""

PHYSICAL_RANDOMISATION: dict[str, tuple[float, float, str]] = {
    "pattern_projection.power": (0.5, 2.0, "log"),
    "pattern_projection.dot_sigma_px": (0.35, 0.7, "lin"),
    "ir_capture.read_noise_e": (2.0, 12.0, "lin"),
    "ir_capture.speckle_contrast": (0.15, 0.45, "lin"),
    "ir_capture.psf_sigma_px": (0.4, 0.9, "lin"),
    "ambient_light.level": (0.0, 0.01, "lin"),
    "block_matching.uniqueness_ratio": (5.0, 15.0, "lin"),
}
"""'effect.param' -> (low, high, lin|log): the physical variant's randomisation ranges, around the
kinect_v1 preset's values (projector power 1, dot sigma 0.5 px, read noise 5 e-, speckle 0.3,
PSF 0.6 px, no ambient light, uniqueness 10); a parameter the preset's model lacks is skipped.
Ambient light stays indoors (0 - 0.01, the effect's "indoors ~0.01"): up to 0.2 it was, and at the
chairs' 2.3-3.3 m a level above ~0.05 with the projector at half power leaves no measurement at all
(the dots are 1/9 as bright as at 1 m) - half of the chairs' physical training patches were empty."""

MIN_MEASURED_FRACTION = 0.1
"""A view whose simulated depth has fewer of the object's pixels measured (in any draw) is left out
of training (``ok`` False): an empty window teaches nothing about the object, and as one side of a
pair it teaches the network that an empty window looks like every view."""


@dataclass
class DataConfig:
    """How the training views are made (saved with the recogniser)."""

    variant: str = "physical"
    """clean, gaussian or physical (see the module docstring)."""
    preset: str = "kinect_v1"
    """Sensor preset whose optics (and, for physical, pipeline) the views use."""
    subdivisions: int = 2
    """Icosahedron subdivisions of the viewpoint sphere (2: 162 vertices, 65 at or above 10 deg elevation)."""
    inplane_deg: tuple[float, ...] = (-45.0, -30.0, -15.0, 0.0, 15.0, 30.0, 45.0)
    """In-plane rotations of the camera about its optical axis, degrees."""
    min_elevation_deg: float = 10.0
    """Lowest viewpoint elevation above the ground, degrees."""
    distance_m: tuple[float, float] = (0.5, 0.9)
    """Camera distance range to the object centre, metres (widened for large objects, see
    :func:`distance_range`)."""
    jitter_deg: float = 3.0
    """Random tilt of each viewpoint direction, degrees."""
    clutter: int = 4
    """Random clutter boxes around the object (one layout per chunk)."""
    albedo: tuple[float, float] = (0.3, 0.9)
    """Range of the object's albedo (one draw per chunk)."""
    draws: int = 2
    """Simulations of every view (>= 2: the pairs of the pair loss)."""
    chunk_views: int = 64
    """Views per chunk (the unit of work, resumption and randomisation)."""
    seed: int = 0
    """Seed of everything random here."""

    def validate(self) -> "DataConfig":
        if self.variant not in VARIANTS:
            raise ConfigError(f"--variant must be one of {', '.join(VARIANTS)}, got {self.variant!r}")
        if self.draws < 2:
            raise ConfigError(f"draws must be >= 2 (pairs), got {self.draws}")
        if not 0 <= self.subdivisions <= 4:
            raise ConfigError(f"subdivisions must be in 0..4, got {self.subdivisions}")
        if not self.inplane_deg:
            raise ConfigError("give at least one in-plane angle")
        if not (0 < self.distance_m[0] <= self.distance_m[1]):
            raise ConfigError(f"distance_m must be 0 < low <= high, got {self.distance_m}")
        if self.chunk_views < 1:
            raise ConfigError(f"chunk_views must be >= 1, got {self.chunk_views}")
        return self


def distance_range(obj: RecogObject, config: DataConfig) -> tuple[float, float]:
    """Camera distance range for ``obj``: ``config.distance_m``, moved out to 1.6-2.3 object
    diameters for objects too large to fit the image at that range (the chairs: 2.3-3.3 m)."""
    d = obj.diameter_m
    return max(config.distance_m[0], 1.6 * d), max(config.distance_m[1], 2.3 * d)


def view_grid(config: DataConfig) -> tuple[np.ndarray, np.ndarray]:
    """(directions (V, 3) object->camera unit vectors, in-plane angles (V,) degrees): the views,
    viewpoint-major."""
    from synth.sensor.views import hemisphere_viewpoints
    dirs = hemisphere_viewpoints(config.subdivisions, config.min_elevation_deg)
    a = np.asarray(config.inplane_deg, float)
    return np.repeat(dirs, len(a), axis=0), np.tile(a, len(dirs))


def sensor_config(variant: str, preset: str = "kinect_v1", width: int | None = None, height: int | None = None,
                  rng: np.random.Generator | None = None):
    """The :class:`~synth.sensor.config.SensorConfig` of a variant (physical randomised with ``rng``)."""
    from synth.sensor.config import SensorConfig
    if variant == "clean":
        return SensorConfig.from_spec(preset, [], width, height)
    if variant == "gaussian":
        return SensorConfig.from_spec(preset, "axial_noise", width, height).with_params(NGUYEN_AXIAL)
    if variant != "physical":
        raise ConfigError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    cfg = SensorConfig.from_spec(preset, "physical", width, height)
    if rng is None:
        return cfg
    have = cfg.fittable()
    vals = {}
    for key, (lo, hi, kind) in PHYSICAL_RANDOMISATION.items():
        if key in have:
            vals[key] = float(math.exp(rng.uniform(math.log(lo), math.log(hi)))) if kind == "log" \
                else float(rng.uniform(lo, hi))
    return cfg.with_params(vals)


def object_scene(obj: RecogObject, clutter: int, rng: np.random.Generator, albedo: float | None = None):
    """(SceneSpec, object-to-world 4x4, object mesh indices, centre above the ground (3,)): the
    object standing on a ground plane (lowest point at z = 0, bounding-box centre over the
    origin) with ``clutter`` random boxes around it."""
    from data_tools.scene_spec import Material, SceneSpec
    from synth.sensor.testscenes import quad_mesh
    from synth.sensor.views import clutter_meshes
    lo, hi = obj.bounds
    c = (lo + hi) / 2
    T = np.eye(4)
    T[:3, 3] = [-c[0], -c[1], -lo[2]]
    meshes, mats = [], {}
    for m in obj.meshes:
        mm = m.transformed(T)
        mm.name, mm.material = m.name, m.material
        meshes.append(mm)
        base = obj.materials[m.material]
        mats[m.material] = Material(float(albedo), base.specular) if albedo is not None else base
    radius = obj.diameter_m / 2
    ground = max(20 * radius, 3.0)
    meshes.append(quad_mesh([0, 0, 0], [ground, 0, 0], [0, ground, 0], "ground", "ground", 4))
    mats["ground"] = Material(0.45, 0.05)
    for m in clutter_meshes(rng, clutter, radius, keep_out=radius * 1.2):
        mats[m.material] = Material(float(rng.uniform(0.1, 0.9)), float(rng.choice([0.0, 0.0, 0.3, 0.7])))
        meshes.append(m)
    centre = np.array([0.0, 0.0, (hi[2] - lo[2]) / 2])
    return SceneSpec(meshes, mats), T, list(range(len(obj.meshes))), centre


def _look_at(eye: np.ndarray, target: np.ndarray, roll_deg: float) -> np.ndarray:
    from data_tools.geometry import look_at
    T = look_at(eye, target, up=(0.0, 0.0, 1.0))
    a = math.radians(roll_deg)
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    T[:3, :3] = T[:3, :3] @ Rz
    return T


def jittered_pose(rng: np.random.Generator, direction: np.ndarray, roll_deg: float, centre: np.ndarray,
                  dist_range: tuple[float, float], jitter_deg: float, target_jitter_m: float) -> np.ndarray:
    """Camera-to-world pose looking at ``centre`` (+ jitter) from ``direction`` (tilted by up to
    ``jitter_deg``) at a distance drawn from ``dist_range``, rolled by ``roll_deg``."""
    d = np.asarray(direction, float)
    if jitter_deg > 0:
        axis = np.cross(d, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        from recog.symmetry import _rot
        d = _rot(axis, math.radians(rng.uniform(0, jitter_deg))) @ d
        if d[2] < 0.05:                              # never below the ground
            d[2] = 0.05
        d /= np.linalg.norm(d)
    dist = rng.uniform(*dist_range)
    target = centre + rng.uniform(-1, 1, 3) * target_jitter_m
    return _look_at(target + d * dist, target, roll_deg)


def crop_size(obj: RecogObject, preset: str, dist_range: tuple[float, float]) -> tuple[int, int]:
    """Width, height of the centred sensor crop that holds the object at the nearest distance
    (with margin for the jitter), multiples of 16, at most the full image."""
    from synth.sensor.presets import get_preset
    pre = get_preset(preset)
    px = pre.fx * obj.diameter_m / max(dist_range[0] - obj.diameter_m / 2, 0.1)
    side = int(math.ceil((1.5 * px + 48) / 16) * 16)
    return min(side, pre.width), min(side, pre.height)


@dataclass
class ChunkJob:
    variant: str
    object_index: int
    chunk: int
    views: list[int]
    out: str


def _chunk_seed(config: DataConfig, obj_name: str, chunk: int, salt: str) -> int:
    return zlib.crc32(f"{config.seed}/{obj_name}/{chunk}/{salt}".encode()) & 0x7FFFFFFF


@dataclass
class ChunkScene:
    """The scene set-up of one chunk of views (:func:`chunk_scene`)."""

    dirs: np.ndarray
    """(V, 3) viewpoint directions of the grid (:func:`view_grid`)."""
    rolls: np.ndarray
    """(V,) in-plane angles, degrees."""
    dist: tuple[float, float]
    """Camera distance range, metres (:func:`distance_range`)."""
    width: int
    """Sensor crop width, pixels (:func:`crop_size`)."""
    height: int
    """Sensor crop height, pixels."""
    scene: object
    """The :class:`~data_tools.scene_spec.SceneSpec`: object, ground, clutter."""
    T_place: np.ndarray
    """(4, 4) object-to-world pose."""
    obj_ids: list[int]
    """Mesh indices of the object (instance ids - 1)."""
    centre: np.ndarray
    """(3,) the object's centre above the ground, world frame."""


def chunk_scene(obj: RecogObject, config: DataConfig, chunk: int, seed_fn) -> ChunkScene:
    """The scene set-up of one chunk of views, shared by the recogniser's (:func:`simulate_chunk`) and SynDA's
    (:func:`recog.synda.data.simulate_views`) view simulation: the view grid, the object's distance range, the
    sensor crop, one clutter layout and albedo. ``seed_fn(key, salt) -> int`` seeds it (called with ``chunk``,
    ``"scene"``); the two callers prefix their seeds differently on purpose (SynDA's scenes are not the
    recogniser's training scenes)."""
    dirs, rolls = view_grid(config)
    dist = distance_range(obj, config)
    w, h = crop_size(obj, config.preset, dist)
    rng_scene = np.random.default_rng(seed_fn(chunk, "scene"))
    albedo = float(rng_scene.uniform(*config.albedo))
    scene, T_place, obj_ids, centre = object_scene(obj, config.clutter, rng_scene, albedo)
    return ChunkScene(dirs, rolls, dist, w, h, scene, T_place, obj_ids, centre)


def simulate_chunk(obj: RecogObject, config: DataConfig, patch: PatchConfig, chunk: int, views: list[int]) -> dict:
    """Simulate the views ``views`` of the grid for one object (one chunk): patches and labels."""
    from synth.sensor.simulator import SensorSimulator
    cs = chunk_scene(obj, config, chunk, lambda key, salt: _chunk_seed(config, obj.name, key, salt))
    dirs, rolls, dist, w, h = cs.dirs, cs.rolls, cs.dist, cs.width, cs.height
    scene, T_place, obj_ids, centre = cs.scene, cs.T_place, cs.obj_ids, cs.centre
    sims = []
    for d in range(config.draws):
        if config.variant == "clean" and d > 0:
            sims.append(sims[0])
            continue
        rng_s = np.random.default_rng(_chunk_seed(config, obj.name, chunk, f"sensor{d}"))
        sims.append(SensorSimulator(sensor_config(config.variant, config.preset, w, h, rng_s), None, scene))
    intr = sims[0].preset.intrinsics
    n, D, S = len(views), config.draws, patch.size
    out = {"patches": np.zeros((n, D, S, S), np.float16), "view": np.asarray(views, np.int32),
           "R_local": np.zeros((n, 3, 3), np.float32), "offset": np.zeros((n, D, 3), np.float32),
           "R": np.zeros((n, 3, 3), np.float32), "t": np.zeros((n, 3), np.float32),
           "ok": np.zeros(n, bool), "visible_px": np.zeros(n, np.int32), "mask": np.zeros((n, S, S), bool)}
    from data_tools.geometry import invert_pose
    for k, v in enumerate(views):
        rng_v = np.random.default_rng(_chunk_seed(config, obj.name, v, "pose"))
        T_c2w = jittered_pose(rng_v, dirs[v], rolls[v], centre, dist, config.jitter_deg, 0.1 * obj.diameter_m)
        T_o2c = invert_pose(T_c2w) @ T_place
        out["R"][k], out["t"][k] = T_o2c[:3, :3], T_o2c[:3, 3]
        res0 = None
        for d in range(D):
            if config.variant == "clean" and d > 0:
                out["patches"][k, d] = out["patches"][k, 0]
                out["offset"][k, d] = out["offset"][k, 0]
                continue
            res = sims[d].simulate(T_c2w, seed=_chunk_seed(config, obj.name, v, f"noise{d}"), with_rgb=False)
            if d == 0:
                res0 = res
                mask = np.isin(res.instance_ids, np.asarray(obj_ids) + 1)
                out["visible_px"][k] = int(mask.sum())
                box = bbox_from_mask(mask)
                if box is None or mask.sum() < 50:
                    break
            if np.mean(res.depth[mask] > 0) < MIN_MEASURED_FRACTION:
                break                                   # the sensor saw (almost) nothing of the object
            try:
                p = extract_patch(res.depth, intr, box, patch)
            except Exception:
                break
            R_local, off = to_ray_frame(T_o2c, p)
            out["patches"][k, d] = p.image
            out["offset"][k, d] = off
            if d == 0:
                out["R_local"][k] = R_local
                out["mask"][k] = resample_nearest(mask, intr, p.R_ray, p.z_ref_m, patch) > 0.5
        else:
            out["ok"][k] = res0 is not None
    return out


def _run_chunk(args) -> str:
    obj, config, patch, job = args
    data = simulate_chunk(obj, config, patch, job.chunk, job.views)
    from data_tools.results import atomic_write_bytes
    import io
    buf = io.BytesIO()
    np.savez_compressed(buf, **data)
    atomic_write_bytes(job.out, buf.getvalue())
    return job.out


def _init_worker() -> None:
    from data_tools.workers import exit_with_parent
    exit_with_parent()
    import cv2
    import synth.jit
    cv2.setNumThreads(1)
    synth.jit.THREADS = 1


def generate_training_data(objects: list[RecogObject], config: DataConfig, patch: PatchConfig,
                           out_dir: str | os.PathLike, workers: int = 1, progress: bool = True) -> int:
    """Simulate every missing chunk into ``out_dir/<variant>/<object>/``; returns chunks made now."""
    config.validate()
    out = Path(out_dir) / config.variant
    dirs, _ = view_grid(config)
    n_views = len(dirs)
    jobs = []
    for i, obj in enumerate(objects):
        for c, start in enumerate(range(0, n_views, config.chunk_views)):
            f = out / obj.name / f"chunk_{c:03d}.npz"
            if not f.is_file():
                jobs.append(ChunkJob(config.variant, i, c, list(range(start, min(start + config.chunk_views, n_views))),
                                     str(f)))
    total = len(objects) * math.ceil(n_views / config.chunk_views)
    if not jobs:
        return 0
    for j in jobs:
        Path(j.out).parent.mkdir(parents=True, exist_ok=True)
    args = [(objects[j.object_index], config, patch, j) for j in jobs]
    run_chunks(_run_chunk, args, workers, progress, total, f"simulating {config.variant} views")
    return len(jobs)


def run_chunks(fn, args: list, workers: int, progress: bool, total: int, desc: str) -> None:
    """``fn(a)`` for every ``a`` of ``args`` (chunks still to simulate), on ``workers`` spawned
    processes when there is more than one chunk, with a progress bar counting ``total`` chunks (the
    ones already on disk count as done). Shared by the recogniser's and SynDA's view simulation."""
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=total, initial=total - len(args), desc=desc, unit="chunk")
    try:
        if workers > 1 and len(args) > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor
            with ProcessPoolExecutor(min(workers, len(args)), mp_context=multiprocessing.get_context("spawn"),
                                     initializer=_init_worker) as ex:
                for _ in ex.map(fn, args):
                    if bar is not None:
                        bar.update(1)
        else:
            for a in args:
                fn(a)
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()


@dataclass
class TrainingData:
    """Every usable view of every object, in memory."""

    patches: np.ndarray
    """(N, D, S, S) float16 patches, D draws per view."""
    obj: np.ndarray
    """(N,) int object index."""
    view: np.ndarray
    """(N,) int view index in the grid."""
    R_local: np.ndarray
    """(N, 3, 3) rotation in the patch's virtual camera."""
    offset: np.ndarray
    """(N, D, 3) object centre minus reference point, virtual camera frame, metres."""
    names: list[str] = field(default_factory=list)
    """Object names by index."""
    mask: np.ndarray | None = None
    """(N, S, S) bool object pixels in the first draw's patch (SynDA's augmentation A composes backgrounds and
    occluders around them: ``recog train --synda-augment``); None when a chunk predates them."""

    def __len__(self) -> int:
        return len(self.obj)


def load_training_data(objects: list[RecogObject], config: DataConfig, out_dir: str | os.PathLike) -> TrainingData:
    """Read the chunks of every object (views whose object was not visible are left out)."""
    from data_tools.errors import FormatError
    base = Path(out_dir) / config.variant
    parts = {k: [] for k in ("patches", "obj", "view", "R_local", "offset", "mask")}
    for i, obj in enumerate(objects):
        files = sorted((base / obj.name).glob("chunk_*.npz"))
        if not files:
            raise FormatError(base / obj.name, "no training chunks (generate the data first)")
        for f in files:
            try:
                z = np.load(f)
                ok = z["ok"]
                parts["patches"].append(z["patches"][ok])
                parts["view"].append(z["view"][ok])
                parts["R_local"].append(z["R_local"][ok])
                parts["offset"].append(z["offset"][ok])
                parts["obj"].append(np.full(int(ok.sum()), i, np.int32))
                parts["mask"].append(z["mask"][ok] if "mask" in z.files else None)
            except (OSError, ValueError, KeyError) as e:
                raise FormatError(f, f"unreadable training chunk ({type(e).__name__}); delete it to make it again") \
                    from None
    masks = parts.pop("mask")
    return TrainingData(*(np.concatenate(parts[k]) for k in ("patches", "obj", "view", "R_local", "offset")),
                        names=[o.name for o in objects],
                        mask=None if any(m is None for m in masks) else np.concatenate(masks))


def describe(config: DataConfig) -> dict:
    d = asdict(config)
    d["randomisation"] = {k: list(v) for k, v in PHYSICAL_RANDOMISATION.items()} if config.variant == "physical" else {}
    return d
