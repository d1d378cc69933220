"""Test sets: "measured" scans of the objects with labels, made with a sensor the recogniser was
not trained with.

    TESTSET/camera.json     intrinsics + depth scale of the scans
    TESTSET/depth/NNNNNN.png 16-bit depth
    TESTSET/labels.json     [{"file": "depth/000001.png", "object": "obj_05",
                              "pose": [[4x4 object-to-camera, metres, OpenCV optical]],
                              "bbox": [x0, y0, x1, y1]}, ...]
    TESTSET/testset_config.json  how it was made

This is also the format :func:`read_testset` accepts from anywhere else (``bbox`` in pixels, x1/y1
exclusive: the detection window; detection itself is out of scope, as in the thesis).

Scans differ from the training views on purpose: another sensor (default the ``structure``
preset's full physical pipeline, i.e. another projector, baseline and focal length than the
kinect_v1 training sensor), random continuous viewpoints (elevation 15-80 deg, any azimuth,
in-plane rotation within +-40 deg) instead of the training grid, the object anywhere in the
central part of the full 640 x 480 image instead of centred, distances drawn from the same
per-object range as training (0.5-0.9 m for T-LESS-size objects), other clutter layouts and
albedos. The window is the bounding box of the object's visible pixels in the ideal render.

Changed effects: ``effect_overrides`` sets effect parameters of the sensor model by name
(``realgap recog testset --effect-override ir_capture.read_noise_e=20``, checked by
:meth:`synth.sensor.config.SensorConfig.with_params`: an unknown effect or parameter, or a value outside
the parameter's bounds, is a one-line error); :data:`EFFECT_PRESETS` names sets of them
(``--effect-preset beyond_training``: every parameter of the physical training randomisation
:data:`recog.data.PHYSICAL_RANDOMISATION` half its range's width beyond the upper end, generated from
that table so that it stays outside training when the table changes).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from data_tools.errors import ConfigError, FormatError
from recog.objects import RecogObject

__all__ = ["TestsetConfig", "make_testset", "read_testset", "TestScan", "EFFECT_PRESETS", "beyond_training",
           "parse_effect_overrides", "testset_sensor"]


def beyond_training(beyond: float = 0.5) -> dict[str, float]:
    """{'effect.param': value}: every parameter of :data:`recog.data.PHYSICAL_RANDOMISATION` ``beyond`` widths
    of its range above the upper end (lin: hi + beyond (hi - lo); log: hi (hi / lo) ** beyond), 4 decimals."""
    from recog.data import PHYSICAL_RANDOMISATION
    out = {}
    for key, (lo, hi, kind) in PHYSICAL_RANDOMISATION.items():
        v = hi * (hi / lo) ** beyond if kind == "log" else hi + beyond * (hi - lo)
        out[key] = round(float(v), 4)
    return out


EFFECT_PRESETS: dict[str, Callable[[], dict[str, float]]] = {"beyond_training": beyond_training}
"""Named sets of effect overrides (``--effect-preset``): name -> a function returning {'effect.param': value}."""


def parse_effect_overrides(items) -> dict[str, float]:
    """{'effect.param': value} of ``EFFECT.PARAM=VALUE`` strings (each may be a comma list); one-line
    :class:`ConfigError` on a malformed item. Names are checked against the sensor by :func:`testset_sensor`."""
    out: dict[str, float] = {}
    for item in items or ():
        for part in str(item).split(","):
            part = part.strip()
            if not part:
                continue
            key, eq, raw = part.partition("=")
            key = key.strip()
            if not eq or key.count(".") != 1 or not all(key.split(".")):
                raise ConfigError(f"--effect-override {part!r}: expected EFFECT.PARAM=VALUE, "
                                  f"e.g. ir_capture.read_noise_e=20")
            try:
                out[key] = float(raw)
            except ValueError:
                raise ConfigError(f"--effect-override {part!r}: {raw.strip()!r} is not a number") from None
    return out


def testset_sensor(cfg: "TestsetConfig"):
    """The :class:`~synth.sensor.config.SensorConfig` of the scans: the sensor with its effects, then the named
    preset's overrides, then ``effect_overrides`` (which win)."""
    from synth.sensor.config import SensorConfig
    sensor = SensorConfig.from_spec(cfg.sensor, cfg.effects)
    values: dict[str, float] = {}
    if cfg.effect_preset:
        if cfg.effect_preset not in EFFECT_PRESETS:
            raise ConfigError(f"unknown effect preset {cfg.effect_preset!r}; known: {', '.join(EFFECT_PRESETS)}")
        have = sensor.fittable()
        values.update({k: v for k, v in EFFECT_PRESETS[cfg.effect_preset]().items() if k in have})
    values.update(cfg.effect_overrides or {})
    return sensor.with_params(values) if values else sensor


@dataclass
class TestsetConfig:
    """How a test set is made (saved as testset_config.json)."""

    sensor: str = "structure"
    """Sensor preset (or a sensor_config.json) of the scans."""
    effects: str = "physical"
    """Its effects: physical, direct, or a comma list."""
    per_object: int = 40
    """Scans per object."""
    elevation_deg: tuple[float, float] = (15.0, 80.0)
    """Range of the viewpoint elevation, degrees."""
    inplane_deg: float = 40.0
    """In-plane rotations drawn from +-this, degrees."""
    off_centre: float = 0.25
    """The object centre lands within this fraction of the image size from the image centre."""
    distance_m: tuple[float, float] = (0.5, 0.9)
    """Camera distance range (widened for large objects as in training)."""
    clutter: int = 6
    """Clutter boxes per scan."""
    seed: int = 1000
    """Seed (training uses 0-based seeds of its own)."""
    effect_preset: str = ""
    """A name of :data:`EFFECT_PRESETS` (its parameters the sensor has are set), or "" for none."""
    effect_overrides: dict[str, float] = field(default_factory=dict)
    """{'effect.param': value} set on the sensor model after the preset (parameters never seen in training)."""


@dataclass
class TestScan:
    file: str
    object: str
    pose: np.ndarray
    bbox: tuple[int, int, int, int]
    rgb: str | None = None
    """The scan's colour image (a colour test set, :mod:`recog.synda.colour_testset`), or None."""


def make_testset(objects: list[RecogObject], out_dir: str | os.PathLike, config: TestsetConfig | None = None,
                 overwrite: bool = False, progress: bool = True) -> int:
    """Simulate ``config.per_object`` scans of every object into ``out_dir``; returns the scan count."""
    from data_tools.geometry import invert_pose
    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    from data_tools.results import atomic_write_json
    from data_tools.sequence import write_depth_png
    from recog.data import DataConfig, distance_range, object_scene
    from recog.patches import bbox_from_mask
    from synth.sensor.simulator import SensorSimulator
    cfg = config or TestsetConfig()
    if cfg.per_object < 1:
        raise ConfigError(f"--per-object must be >= 1, got {cfg.per_object}")
    sensor = testset_sensor(cfg)            # bad effect names / values fail before any file is written
    out = check_output_dir(out_dir, finished="labels.json", overwrite=overwrite)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    labels = []
    total = cfg.per_object * len(objects)
    mark_incomplete(out, "realgap recog testset", 0, total, unit="scans")
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=total, desc="test scans", unit="scan")
    camera = None
    k = 0
    for oi, obj in enumerate(objects):
        dist = distance_range(obj, DataConfig(distance_m=tuple(cfg.distance_m)))
        for s in range(cfg.per_object):
            rng = np.random.default_rng([cfg.seed, oi, s])
            albedo = float(rng.uniform(0.3, 0.9))
            scene, T_place, obj_ids, centre = object_scene(obj, cfg.clutter, rng, albedo)
            sim = SensorSimulator(sensor, None, scene)
            intr = sim.preset.intrinsics
            camera = sim.camera()
            for _attempt in range(20):
                el = math.radians(rng.uniform(*cfg.elevation_deg))
                az = rng.uniform(0, 2 * math.pi)
                d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
                T_c2w = _pose(d, centre, rng.uniform(*dist), rng.uniform(-cfg.inplane_deg, cfg.inplane_deg))
                # turn the camera so the object lands off-centre in the image
                fx = rng.uniform(-cfg.off_centre, cfg.off_centre) * intr.width / intr.fx
                fy = rng.uniform(-cfg.off_centre, cfg.off_centre) * intr.height / intr.fy
                from recog.patches import ray_rotation
                R = ray_rotation(intr, intr.cx + fx * intr.fx, intr.cy + fy * intr.fy)
                T_c2w[:3, :3] = T_c2w[:3, :3] @ R.T
                res = sim.simulate(T_c2w, seed=int(rng.integers(2**31)), with_rgb=False)
                mask = np.isin(res.instance_ids, np.asarray(obj_ids) + 1)
                box = bbox_from_mask(mask)
                if box is not None and mask.sum() >= 100 and (mask & (res.depth > 0)).sum() >= 50:
                    break
            else:
                raise ConfigError(f"{obj.name}: no view with the object visible in 20 tries (is it too large "
                                  f"for the sensor's range?)")
            name = f"depth/{k:06d}.png"
            write_depth_png(out / name, res.depth, camera.depth_scale)
            T_o2c = invert_pose(T_c2w) @ T_place
            labels.append({"file": name, "object": obj.name, "pose": [[float(x) for x in r] for r in T_o2c],
                           "bbox": [int(v) for v in box]})
            k += 1
            mark_incomplete(out, "realgap recog testset", k, total, unit="scans", resumable=False)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    from data_tools.camera import write_camera_json
    write_camera_json(out / "camera.json", camera)
    atomic_write_json(out / "testset_config.json", {**asdict(cfg), "objects": [o.to_json() for o in objects]})
    atomic_write_json(out / "labels.json", labels, indent=1)
    clear_incomplete(out)
    return k


def _pose(direction: np.ndarray, centre: np.ndarray, dist: float, roll_deg: float) -> np.ndarray:
    from recog.data import _look_at
    return _look_at(centre + direction * dist, centre, roll_deg)


def read_testset(folder: str | os.PathLike, known: list[str] | None = None):
    """(camera, [TestScan]) of a test set; one-line errors name the file and the entry."""
    from data_tools.camera import read_camera_json
    from data_tools.outputs import check_input_dir
    folder = check_input_dir(folder, "test set folder")
    lab = folder / "labels.json"
    if not lab.is_file():
        raise FormatError(lab, "file not found (a test set has camera.json, depth/ and labels.json)")
    if not (folder / "camera.json").is_file():
        raise FormatError(folder / "camera.json", "file not found (the scans' intrinsics and depth scale)")
    camera = read_camera_json(folder / "camera.json")
    try:
        items = json.loads(lab.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(lab, f"not valid JSON ({e})") from None
    if isinstance(items, dict) and "views" in items:     # a `synth views` labels.json
        items = [{"file": v["depth"], "object": items.get("object", v.get("object")), "pose": v["pose_obj_to_cam"],
                  "bbox": v.get("bbox")} for v in items["views"]]
    if not isinstance(items, list) or not items:
        raise FormatError(lab, "expected a non-empty list of {file, object, pose, bbox}")
    scans = []
    for i, it in enumerate(items):
        where = f"entry {i}"
        if not isinstance(it, dict) or not {"file", "object", "pose", "bbox"} <= set(it):
            raise FormatError(lab, f"{where}: needs file, object, pose and bbox")
        if known is not None and it["object"] not in known:
            raise FormatError(lab, f"{where}: unknown object {it['object']!r} (the recogniser knows "
                                   f"{', '.join(known)})")
        pose = np.asarray(it["pose"], float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise FormatError(lab, f"{where}: pose must be a finite 4x4 matrix")
        from data_tools.geometry import is_rigid
        if not is_rigid(pose, 1e-4):
            raise FormatError(lab, f"{where}: pose is not a rigid transform (rotation not orthonormal)")
        bbox = it["bbox"]
        if not (isinstance(bbox, (list, tuple)) and len(bbox) == 4):
            raise FormatError(lab, f"{where}: bbox must be [x0, y0, x1, y1]")
        from recog.patches import check_bbox
        try:
            box = check_bbox(bbox, camera.intrinsics.width, camera.intrinsics.height)
        except Exception as e:
            raise FormatError(lab, f"{where}: {e}") from None
        rgb = it.get("rgb")
        if rgb is not None and not (isinstance(rgb, str) and rgb):
            raise FormatError(lab, f"{where}: rgb must be the colour image's file name, got {rgb!r}")
        scans.append(TestScan(str(it["file"]), str(it["object"]), pose, box, rgb))
    return camera, scans
