"""Object-centred views for CAD-based recognition: one object, a sensor, many viewpoints.

Viewpoints are the vertices of a subdivided icosahedron on the upper half sphere around the
object (object resting on a ground plane), each with a set of in-plane rotations of the
camera about its optical axis; optional random clutter (boxes and cylinders on the ground)
and background walls. Every view is simulated by the chosen sensor model and written as

    OUT/depth/NNNNNN.png        16-bit sensor depth (metres = value / depth_scale)
    OUT/ideal/NNNNNN.png        16-bit ideal depth (optional)
    OUT/mask/NNNNNN.png         8-bit mask of the object's visible pixels (255)
    OUT/views.jsonl             one JSON line per view: object name, 4x4 object-to-camera
                                pose (OpenCV camera axes), viewpoint, in-plane angle, seed
    OUT/labels.json             all of them in one JSON document (written at the end)
    OUT/camera.json, sensor_config.json, views_config.json

so a run can be resumed (views already in views.jsonl are skipped).

    render_views(load_mesh("obj_01.ply", scale=0.001), "kinect_v1", "out/obj_01", subdivisions=2,
                 inplane_deg=(-30, 0, 30), clutter=5)
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.mesh import TriMesh
from data_tools.results import atomic_write_image, atomic_write_json
from data_tools.scene_spec import Material, SceneSpec


def icosphere_vertices(subdivisions: int = 1) -> np.ndarray:
    """(N, 3) unit vertices of an icosahedron subdivided ``subdivisions`` times (12, 42, 162, ...)."""
    t = (1 + 5 ** 0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
         (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.asarray(p, float) / np.linalg.norm(p) for p in v]
    faces = list(f)
    for _ in range(int(subdivisions)):
        cache: dict = {}

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]
        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.asarray(verts)


def hemisphere_viewpoints(subdivisions: int = 1, min_elevation_deg: float = 5.0) -> np.ndarray:
    """Unit directions (object -> camera) of the icosphere vertices with elevation above
    ``min_elevation_deg`` (z up), sorted by elevation then azimuth."""
    v = icosphere_vertices(subdivisions)
    v = v[np.degrees(np.arcsin(np.clip(v[:, 2], -1, 1))) >= min_elevation_deg - 1e-9]
    order = np.lexsort((np.arctan2(v[:, 1], v[:, 0]), -v[:, 2]))
    return v[order]


def _look_at_with_roll(eye, target, roll_deg: float) -> np.ndarray:
    from data_tools.geometry import look_at
    T = look_at(eye, target, up=(0.0, 0.0, 1.0))
    a = math.radians(roll_deg)
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    T[:3, :3] = T[:3, :3] @ Rz  # rotate the camera about its own optical axis
    return T


@dataclass
class ViewsConfig:
    """Settings of :func:`render_views` (saved as views_config.json)."""

    subdivisions: int = 1
    """Icosahedron subdivisions (0: 12 vertices, 1: 42, 2: 162; 4, 17, 73 of them lie above 5 deg
    elevation)."""
    inplane_deg: tuple[float, ...] = (0.0,)
    """In-plane rotations of the camera about its optical axis, degrees."""
    distance_m: float | None = None
    """Camera distance to the object centre; None = so the object fills ~40 % of the image
    height, but at least 0.2 m beyond the sensor's minimum depth."""
    min_elevation_deg: float = 5.0
    """Lowest viewpoint elevation above the ground, degrees."""
    ground: bool = True
    """Put a ground plane under the object."""
    clutter: int = 0
    """Number of random clutter objects around the object."""
    background: bool = False
    """Surround the set-up with four walls (every view has a background)."""
    seed: int = 0
    """Seed of the clutter layout and of the sensor draws (view i uses seed + i)."""
    write_ideal: bool = True
    """Also write the ideal depth PNGs."""
    max_views: int | None = None
    """Render only the views with index < max_views (a quick subset; a later run with a larger
    value or None and ``resume`` adds the rest). None = all views."""
    model_path: str = ""
    """Where the model was loaded from (provenance only; render_views takes the loaded mesh)."""
    model_scale: float = 1.0
    """Scale applied to the file's coordinates to get metres (provenance only)."""


MODEL_SIZE_RANGE_M = (0.005, 10.0)
"""Plausible bounding-box diagonal of a recognition object, metres; outside it the model's
units are almost certainly wrong (T-LESS CAD models are in millimetres: scale 0.001)."""


def check_model_size(model: TriMesh, source: str | os.PathLike | None = None, scale: float | None = None) -> float:
    """Bounding-box diagonal of ``model`` in metres; ConfigError (one line naming ``source`` or
    the model, with a hint about the scale) when it lies outside :data:`MODEL_SIZE_RANGE_M`."""
    lo, hi = model.bounds
    diag = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    where = str(source) if source is not None else f"model {model.name!r}"
    used = f" after scale {scale:g}" if scale is not None else ""
    a, b = MODEL_SIZE_RANGE_M
    if not diag > 0:
        raise ConfigError(f"{where}: model has no extent (all vertices coincide)")
    if diag > b:
        hint = (" - are its units millimetres? use --scale 0.001" if a <= diag * 1e-3 <= b else
                " - check its units (--scale converts them to metres)")
        raise ConfigError(f"{where}: model is {diag:.4g} m across{used}, absurd for a recognition object "
                          f"(expected {a:g}..{b:g} m){hint}")
    if diag < a:
        hint = (" - is it already in metres? drop --scale 0.001" if scale is not None and scale < 1 and
                a <= diag / scale <= b else " - check its units (--scale converts them to metres)")
        raise ConfigError(f"{where}: model is only {diag * 1e3:.3g} mm across{used}, too small for the "
                          f"sensor (expected {a:g}..{b:g} m){hint}")
    return diag


@dataclass
class ViewsResult:
    """What :func:`render_views` did."""

    out_dir: str
    """The output folder."""
    n_views: int
    """Views this run covers (all, or the first ``max_views``)."""
    n_written: int
    """Views written now (the others were already there: resumed run)."""
    object_name: str
    """Name of the model (the ``object`` label)."""
    views: list = field(default_factory=list)
    """The records written now (see views.jsonl)."""
    n_views_all: int = 0
    """Views of the full set (n_views is the subset of this run when max_views is set)."""


def clutter_meshes(rng: np.random.Generator, n: int, obj_radius: float, keep_out: float) -> list[TriMesh]:
    """``n`` random boxes on the ground (z = 0) around an object of radius ``obj_radius`` at the
    origin, none nearer than ``keep_out`` metres to it (names and materials ``clutter_<i>``)."""
    from synth.sensor.testscenes import box_mesh
    out = []
    for i in range(n):
        for _ in range(50):
            r = rng.uniform(keep_out + 0.05, keep_out + 4 * obj_radius + 0.3)
            a = rng.uniform(0, 2 * np.pi)
            s = rng.uniform(0.3, 1.2) * max(obj_radius, 0.05) * np.array([rng.uniform(0.5, 1.5), rng.uniform(0.5, 1.5),
                                                                           rng.uniform(0.5, 2.0)])
            c = np.array([r * np.cos(a), r * np.sin(a), s[2] / 2])
            if np.hypot(*c[:2]) - np.hypot(*s[:2]) / 2 > keep_out:
                out.append(box_mesh(c, s, f"clutter_{i}", f"clutter_{i}"))
                break
    return out


def build_views_scene(model: TriMesh, config: ViewsConfig, material: Material | None = None):
    """(SceneSpec, object-to-world 4x4, object radius): the model with its lowest point on the
    ground (z = 0) and its bounding-box centre above the origin, plus ground/clutter/walls."""
    from synth.sensor.testscenes import quad_mesh
    lo, hi = model.bounds
    centre = (lo + hi) / 2
    T_place = np.eye(4)
    T_place[:3, 3] = [-centre[0], -centre[1], -lo[2]]
    obj = model.transformed(T_place)
    obj.material = "object"
    radius = float(np.linalg.norm(hi - lo) / 2)
    if not radius > 0:
        raise RealgapError(f"model {model.name!r} has no extent")
    meshes = [obj]
    mats = {"object": material or Material(0.6, 0.05), "ground": Material(0.45, 0.05),
            "wall": Material(0.7, 0.0)}
    rng = np.random.default_rng(config.seed)
    if config.ground:
        g = max(20 * radius, 3.0)
        meshes.append(quad_mesh([0, 0, 0], [g, 0, 0], [0, g, 0], "ground", "ground", 4))
    for m in clutter_meshes(rng, config.clutter, radius, keep_out=radius * 1.2):
        mats[m.material] = Material(float(rng.uniform(0.1, 0.9)), float(rng.choice([0.0, 0.0, 0.3, 0.7])))
        meshes.append(m)
    if config.background:
        w = max(8 * radius, 2.5)
        for k, (c, a) in enumerate([((w, 0, w), (0, w, 0)), ((-w, 0, w), (0, w, 0)),
                                    ((0, w, w), (w, 0, 0)), ((0, -w, w), (w, 0, 0))]):
            meshes.append(quad_mesh(c, a, [0, 0, w], f"wall_{k}", "wall", 2))
    return SceneSpec(meshes, mats), T_place, radius


def render_views(model: TriMesh, sensor, out_dir: str | os.PathLike, config: ViewsConfig | None = None,
                 material: Material | None = None, resume: bool = False, overwrite: bool = False,
                 progress: bool = True, **overrides) -> ViewsResult:
    """Simulate object-centred views of ``model`` with ``sensor`` and write them to ``out_dir``.

    ``sensor``: preset name, SensorPreset, SensorConfig, sensor_config.json path, or a
    SensorSimulator (its config is reused). ``overrides`` set ViewsConfig fields
    (e.g. ``subdivisions=2, inplane_deg=(-30, 0, 30), clutter=5``). Returns a ViewsResult.
    """
    from data_tools.camera import write_camera_json
    from data_tools.sequence import write_depth_png
    from synth.sensor.simulator import SensorSimulator
    cfg = config or ViewsConfig()
    if overrides:
        unknown = set(overrides) - set(ViewsConfig.__dataclass_fields__)
        if unknown:
            raise ConfigError(f"render_views: unknown option(s) {', '.join(sorted(unknown))}")
        cfg = ViewsConfig(**{**asdict(cfg), **overrides})
    cfg.inplane_deg = tuple(float(a) for a in cfg.inplane_deg)
    if not cfg.inplane_deg:
        raise ConfigError("render_views: need at least one in-plane angle")
    if cfg.subdivisions < 0 or cfg.subdivisions > 5:
        raise ConfigError(f"render_views: subdivisions must be in 0..5, got {cfg.subdivisions}")
    if cfg.clutter < 0:
        raise ConfigError(f"render_views: clutter must be >= 0, got {cfg.clutter}")
    if cfg.max_views is not None and cfg.max_views < 1:
        raise ConfigError(f"render_views: max_views must be >= 1, got {cfg.max_views}")
    if cfg.distance_m is not None and not (math.isfinite(cfg.distance_m) and cfg.distance_m > 0):
        raise ConfigError(f"render_views: distance_m must be a positive number, got {cfg.distance_m}")
    check_model_size(model)
    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    out = check_output_dir(out_dir, what="views folder")
    index_path = out / "views.jsonl"
    if index_path.exists() and not (resume or overwrite):
        raise RealgapError(f"{out}: already holds views (--resume continues them, --overwrite replaces them)")
    if overwrite and index_path.exists():
        import shutil
        index_path.unlink()
        for sub in ("depth", "mask", "ideal"):   # no stale images of the previous run
            if (out / sub).is_dir():
                shutil.rmtree(out / sub)
    sensor_cfg = sensor.config if isinstance(sensor, SensorSimulator) else sensor
    scene, T_place, radius = build_views_scene(model, cfg, material)
    sim = SensorSimulator(sensor_cfg, None, scene)
    pre = sim.preset
    intr = pre.intrinsics
    centre = np.array([0.0, 0.0, (model.bounds[1][2] - model.bounds[0][2]) / 2])
    dist = cfg.distance_m
    if dist is None:
        half_fov = math.atan(intr.height / 2 / intr.fy)
        dist = radius / math.tan(0.4 * half_fov) + 0.0
        dist = max(dist, pre.min_depth_m + radius + 0.2)
    if dist - radius < pre.min_depth_m:
        raise ConfigError(f"render_views: distance {dist:.2f} m puts the object nearer than the sensor's "
                          f"minimum depth {pre.min_depth_m} m")
    effective = {**asdict(cfg), "distance_m": dist, "object": model.name}
    if resume and index_path.exists():
        _check_same_run(out, effective, sim.config.to_json())
    for sub in ("depth", "mask") + (("ideal",) if cfg.write_ideal else ()):
        (out / sub).mkdir(parents=True, exist_ok=True)
    write_camera_json(out / "camera.json", sim.camera())
    sim.config.save(out / "sensor_config.json")
    atomic_write_json(out / "views_config.json", effective)
    done = set()
    if index_path.exists():
        for line in index_path.read_text().splitlines():
            if line.strip():
                done.add(json.loads(line)["index"])
    dirs = hemisphere_viewpoints(cfg.subdivisions, cfg.min_elevation_deg)
    jobs = [(i * len(cfg.inplane_deg) + j, d, a) for i, d in enumerate(dirs) for j, a in enumerate(cfg.inplane_deg)]
    n_all = len(jobs)
    if cfg.max_views is not None:
        jobs = jobs[:cfg.max_views]
    todo = [j for j in jobs if j[0] not in done]
    it = todo
    if progress:
        from data_tools.progress import progress_bar
        it = progress_bar(todo, desc=f"views of {model.name}", initial=len(jobs) - len(todo), total=len(jobs),
                          unit="view")
    scale = sim.camera().depth_scale
    written = 0
    views = []
    mark_incomplete(out, "realgap synth views", len(jobs) - len(todo), len(jobs), unit="views")
    for idx, d, roll in it:
        T_c2w = _look_at_with_roll(centre + d * dist, centre, roll)
        res = sim.simulate(T_c2w, seed=cfg.seed + idx)
        name = f"{idx:06d}.png"
        for sub, arr in (("depth", res.depth),) + ((("ideal", res.ideal_depth),) if cfg.write_ideal else ()):
            write_depth_png(out / sub / name, arr, scale)
        mask = (res.instance_ids == 1).astype(np.uint8) * 255
        atomic_write_image(out / "mask" / name, mask)
        from data_tools.geometry import invert_pose
        T_obj2cam = invert_pose(T_c2w) @ T_place
        rec = {"index": idx, "object": model.name, "depth": f"depth/{name}", "mask": f"mask/{name}",
               "pose_obj_to_cam": [[float(x) for x in row] for row in T_obj2cam],
               "viewpoint": [float(x) for x in d], "inplane_deg": float(roll), "distance_m": float(dist),
               "seed": cfg.seed + idx, "visible_px": int((mask > 0).sum()),
               "valid_object_px": int(((mask > 0) & res.valid).sum())}
        if cfg.write_ideal:
            rec["ideal_depth"] = f"ideal/{name}"
        with open(index_path, "a") as f:
            f.write(json.dumps(rec) + "\n")
        views.append(rec)
        written += 1
        mark_incomplete(out, "realgap synth views", len(jobs) - len(todo) + written, len(jobs), unit="views")
    all_recs = read_views(out)
    atomic_write_json(out / "labels.json", {"object": model.name, "camera": "camera.json", "views": all_recs},
                      indent=1)
    clear_incomplete(out)
    return ViewsResult(str(out), len(jobs), written, model.name, views, n_all)


# fields that may differ between a run and its resumption (they do not change any view)
_RESUME_FREE = ("max_views", "model_path")


def _check_same_run(out: Path, effective: dict, sensor_json: dict) -> None:
    """ConfigError when a resumed run would mix views of different settings in ``out``."""
    p = out / "views_config.json"
    if p.exists():
        try:
            old = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise FormatError(p, f"not valid JSON ({e.msg})") from None
        new = json.loads(json.dumps(effective))  # tuples -> lists, as stored
        diff = sorted(k for k in set(old) | set(new) if k not in _RESUME_FREE and old.get(k) != new.get(k))
        if diff:
            raise ConfigError(f"{out}: cannot resume, the views there were made with other settings "
                              f"({', '.join(diff)}); use overwrite or another folder")
    s = out / "sensor_config.json"
    if s.exists():
        try:
            old_s = json.loads(s.read_text())
        except json.JSONDecodeError as e:
            raise FormatError(s, f"not valid JSON ({e.msg})") from None
        if old_s != json.loads(json.dumps(sensor_json)):
            raise ConfigError(f"{out}: cannot resume, the views there were made with another sensor model; "
                              f"use overwrite or another folder")


def read_views(out_dir: str | os.PathLike) -> list[dict]:
    """The view records of a render_views folder, sorted by index."""
    p = Path(out_dir) / "views.jsonl"
    if not p.exists():
        raise RealgapError(f"{p}: not found (not a render_views output?)")
    recs = [json.loads(l) for l in p.read_text().splitlines() if l.strip()]
    return sorted(recs, key=lambda r: r["index"])


def render_views_of_file(model_path: str | os.PathLike, scale: float, sensor, out_dir: str | os.PathLike,
                         config: ViewsConfig | None = None, *, resume: bool = False, overwrite: bool = False,
                         progress: bool = True):
    """:func:`render_views` of the mesh file ``model_path`` in units of ``scale`` metres (its
    size checked first: a model in millimetres without ``scale`` gets a one-line error)."""
    from data_tools.errors import ConfigError
    from data_tools.mesh import load_mesh
    if not scale > 0:
        raise ConfigError(f"--scale must be positive, got {scale}")
    model = load_mesh(model_path, scale=scale)
    check_model_size(model, model_path, scale)
    return render_views(model, sensor, out_dir, config, resume=resume, overwrite=overwrite, progress=progress)
