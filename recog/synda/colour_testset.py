"""Colour test sets for SynDA's rgb domain (issue 47: "colour test images rendered differently from A").

A colour test set is a depth test set (:mod:`recog.testset`: camera.json, depth/, labels.json, read by
``recog eval``) whose labels also name a colour image per scan::

    TESTSET/rgb/NNNNNN.png    8-bit colour image (RGB), registered to the depth image
    TESTSET/depth/NNNNNN.png  16-bit rendered depth of the same scene (occluders included; 0 = background)
    TESTSET/labels.json       [{"file": "depth/..", "rgb": "rgb/..", "object", "pose", "bbox"}, ...]
    TESTSET/testset_config.json  {"domain": "rgb", ...}: how it was made

What differs from A (the training augmentation, :mod:`recog.synda.augment`), on purpose:

* **renderer and shading**: a rasteriser (the caller's ``render``, e.g. VTK through PyVista in
  ``app/colour_render.py``) with 1-3 coloured point lights, Phong or physically based (metallic /
  roughness) materials; A shades a normal map per pixel with one directional Blinn-Phong light;
* **textures**: image textures (``--textures``: by default the sample images scikit-image ships)
  mapped onto the mesh by a spherical or planar projection; A's object textures are procedural
  noise in hue and saturation indexed by the normals and never an image;
* **backgrounds**: whole photographs of any folder (``--backgrounds``; the benchmark uses real
  7-Scenes office frames, which A never sees), cropped at 60-100 % of their side and resized to
  the image; A's default bank is scikit-image's images at 25-100 % crops of 128 px;
* **occluders**: 3D solids (sphere, box, cylinder, cone) lit like the object, placed just in
  front of it; A pastes flat 2D polygons filled with colour noise;
* no blur (A blurs every sample).

Scan poses follow :mod:`recog.testset` (elevation 15-80 deg over the ground the object stands on,
any azimuth, in-plane +-40 deg, the object anywhere in the central part of the image, distances as
in training); the ground itself is not rendered (the background is the photograph). Occluders are
placed between 0 and ``occluder_depth`` object diameters in front of the object's nearest point so
that the depth patch's reference depth (10th percentile of the window, :mod:`recog.patches`)
stays on the object or close to it; scans whose object keeps less than ``min_visible`` of its
pixels are drawn again without the nearest occluder.

The window (``bbox``) is the box of the object's visible pixels, as in :mod:`recog.testset`.
Everything a scan needs is drawn from ``numpy.random.default_rng([seed, object, scan])``
(:func:`draw_scene`), so a test set is reproducible for a seed with a deterministic renderer.
"""
from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from data_tools.errors import ConfigError, FormatError
from recog.objects import RecogObject
from recog.synda.images import image_files

__all__ = ["ColourTestsetConfig", "ColourScene", "draw_scene", "make_colour_testset", "image_files",
           "colour_patch", "OCCLUDER_SHAPES", "compose"]

OCCLUDER_SHAPES = ("sphere", "box", "cylinder", "cone")
"""Solids the renderer must know (``ColourScene.occluders[i]["shape"]``)."""

@dataclass
class ColourTestsetConfig:
    """How a colour test set is made (saved in testset_config.json)."""

    per_object: int = 10
    """Scans per object."""
    width: int = 640
    """Image width, pixels."""
    height: int = 480
    """Image height, pixels."""
    focal_px: float = 525.0
    """Focal length (fx = fy), pixels; the principal point is the image centre (an ideal colour camera:
    the Kinect v1 colour camera's nominal focal length)."""
    elevation_deg: tuple[float, float] = (15.0, 80.0)
    """Range of the viewpoint elevation over the ground the object stands on, degrees."""
    inplane_deg: float = 40.0
    """In-plane rotations drawn from +-this, degrees."""
    off_centre: float = 0.25
    """The object centre lands within this fraction of the image size from the image centre."""
    distance_m: tuple[float, float] = (0.5, 0.9)
    """Camera distance range (widened for large objects as in training: :func:`recog.data.distance_range`)."""
    occluders: tuple[int, int] = (0, 3)
    """Number of occluding solids per scan, drawn uniformly from this range (inclusive)."""
    occluder_depth: float = 0.25
    """Occluders lie 0 to this many object diameters in front of the object's nearest point."""
    min_visible: float = 0.5
    """Fraction of the object's pixels that must stay visible (else the nearest occluder is dropped)."""
    textures: str = "skimage"
    """Folder of texture images for the object and some occluders (``skimage``: scikit-image's samples)."""
    backgrounds: str = "skimage"
    """Folder (searched recursively) of background photographs (``skimage``: scikit-image's samples - the
    folder A's default bank also uses; give another folder for backgrounds A never saw)."""
    max_backgrounds: int = 200
    """At most this many background files are used (evenly spaced over the sorted list)."""
    seed: int = 3000
    """Seed of every draw."""

    def validate(self) -> "ColourTestsetConfig":
        if self.per_object < 1:
            raise ConfigError(f"--per-object must be >= 1, got {self.per_object}")
        if self.width < 32 or self.height < 32 or not self.focal_px > 0:
            raise ConfigError(f"colour test set image {self.width}x{self.height}, focal {self.focal_px}: too small")
        lo, hi = self.occluders
        if not 0 <= lo <= hi:
            raise ConfigError(f"colour test set occluders range {self.occluders!r} must be 0 <= low <= high")
        if not 0.0 < self.min_visible <= 1.0:
            raise ConfigError(f"colour test set min_visible must be in (0, 1], got {self.min_visible}")
        return self


@dataclass
class ColourScene:
    """One scan, everything the renderer needs (camera frame: OpenCV, x right, y down, z forward; metres)."""

    object_index: int
    """Index of the object in the object list."""
    pose: np.ndarray
    """(4, 4) object-to-camera pose."""
    lights: list[dict]
    """Point lights: ``position`` (3,) camera frame, ``colour`` (3,) in [0, 1], ``intensity``."""
    material: dict
    """``pbr`` (bool), ``metallic``, ``roughness`` (pbr), ``ambient``, ``diffuse``, ``specular``,
    ``specular_power`` (Phong)."""
    texture: int
    """Index into the texture image list (the object's texture)."""
    mapping: str
    """``sphere`` or ``plane``: how texture coordinates are laid on the mesh."""
    occluders: list[dict] = field(default_factory=list)
    """``shape`` (:data:`OCCLUDER_SHAPES`), ``centre`` (3,) camera frame, ``size`` (metres), ``rotation``
    (3, 3), ``colour`` (3,), ``texture`` (index or -1 for the plain colour)."""
    background: int = 0
    """Index into the background image list."""
    crop: tuple[float, float, float] = (1.0, 0.0, 0.0)
    """Background crop: side fraction, x and y offset fractions of the remaining margin."""


def draw_scene(obj: RecogObject, oi: int, s: int, cfg: ColourTestsetConfig, n_textures: int,
               n_backgrounds: int, drop: int = 0) -> ColourScene:
    """Scan ``s`` of object ``oi``: pose, lights, material, texture, occluders (without the ``drop`` nearest
    ones) and background, all from ``default_rng([seed, oi, s])``."""
    from recog.data import DataConfig, distance_range
    from recog.patches import ray_rotation
    from recog.testset import _pose
    from data_tools.camera import Intrinsics
    from data_tools.geometry import invert_pose
    rng = np.random.default_rng([cfg.seed, oi, s])
    lo, hi = obj.bounds
    place = np.eye(4)
    place[:3, 3] = [-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]]
    centre = np.array([0.0, 0.0, (hi[2] - lo[2]) / 2])
    dist = distance_range(obj, DataConfig(distance_m=tuple(cfg.distance_m)))
    el = math.radians(rng.uniform(*cfg.elevation_deg))
    az = rng.uniform(0, 2 * math.pi)
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    T_c2w = _pose(d, centre, rng.uniform(*dist), rng.uniform(-cfg.inplane_deg, cfg.inplane_deg))
    intr = Intrinsics(cfg.width, cfg.height, cfg.focal_px, cfg.focal_px, cfg.width / 2, cfg.height / 2)
    fx = rng.uniform(-cfg.off_centre, cfg.off_centre) * cfg.width
    fy = rng.uniform(-cfg.off_centre, cfg.off_centre) * cfg.height
    R = ray_rotation(intr, intr.cx + fx, intr.cy + fy)
    T_c2w[:3, :3] = T_c2w[:3, :3] @ R.T
    pose = invert_pose(T_c2w) @ place
    # lights around the camera, in front of the object (camera frame)
    z_obj = float(pose[2, 3])
    lights = []
    for _ in range(int(rng.integers(1, 4))):
        pos = np.array([rng.uniform(-1, 1), rng.uniform(-1, 0.3), rng.uniform(-0.3, 0.6)]) * z_obj
        lights.append({"position": pos, "colour": rng.uniform(0.6, 1.0, 3), "intensity": float(rng.uniform(0.5, 1.0))})
    pbr = bool(rng.random() < 0.5)
    material = {"pbr": pbr, "metallic": float(rng.uniform(0.0, 0.7)), "roughness": float(rng.uniform(0.2, 0.9)),
                "ambient": float(rng.uniform(0.05, 0.3)), "diffuse": float(rng.uniform(0.5, 1.0)),
                "specular": float(rng.uniform(0.0, 0.6)), "specular_power": float(rng.uniform(5, 60))}
    texture = int(rng.integers(n_textures))
    mapping = str(rng.choice(["sphere", "plane"]))
    # occluders: in front of the object's nearest point, over the object's image region
    verts = np.concatenate([m.vertices for m in obj.meshes]) @ pose[:3, :3].T + pose[:3, 3]
    z_near = float(verts[:, 2].min())
    occ = []
    for _ in range(int(rng.integers(cfg.occluders[0], cfg.occluders[1] + 1))):
        j = int(rng.integers(len(verts)))                     # over a random point of the object
        z = z_near - rng.uniform(0.0, cfg.occluder_depth) * obj.diameter_m
        size = float(rng.uniform(0.1, 0.3) * obj.diameter_m)
        c = verts[j] * (z / verts[j, 2])
        q = rng.normal(size=4)
        occ.append({"shape": str(rng.choice(OCCLUDER_SHAPES)), "centre": c, "size": size,
                    "rotation": _quat_matrix(q / np.linalg.norm(q)), "colour": rng.uniform(0.05, 0.95, 3),
                    "texture": int(rng.integers(n_textures)) if rng.random() < 0.5 else -1})
    occ.sort(key=lambda o: float(o["centre"][2]))              # nearest first: dropped first
    crop = (float(rng.uniform(0.6, 1.0)), float(rng.random()), float(rng.random()))
    return ColourScene(oi, pose, lights, material, texture, mapping, occ[drop:], int(rng.integers(n_backgrounds)),
                       crop)


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def background_image(path: Path, crop: tuple[float, float, float], width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8: the crop (side fraction, offsets) of the photograph at ``path`` with the image's aspect,
    resized to ``width`` x ``height`` (area interpolation)."""
    import cv2

    from data_tools.sequence import read_rgb_image
    im = read_rgb_image(path)
    h, w = im.shape[:2]
    aspect = width / height
    cw = min(w, h * aspect) * crop[0]
    ch = cw / aspect
    x0 = int(round((w - cw) * crop[1]))
    y0 = int(round((h - ch) * crop[2]))
    sub = im[y0:y0 + max(int(ch), 1), x0:x0 + max(int(cw), 1)]
    return cv2.resize(sub, (width, height), interpolation=cv2.INTER_AREA)


def compose(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: the rendered ``rgba`` (H, W, 4) over ``background`` (H, W, 3) by its alpha."""
    a = rgba[..., 3:4].astype(np.float32) / 255.0
    out = rgba[..., :3].astype(np.float32) * a + background.astype(np.float32) * (1 - a)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


Render = Callable[[ColourScene, RecogObject], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""``render(scene, obj) -> (rgba (H, W, 4) uint8, depth (H, W) metres, 0 = nothing, object mask (H, W) bool of the
object's visible pixels)``; the renderer knows the camera (the config's intrinsics) and the texture files."""


def make_colour_testset(objects: list[RecogObject], out_dir: str | os.PathLike, cfg: ColourTestsetConfig,
                        render: Render, overwrite: bool = False, progress: bool = True,
                        command: str = "realgap synda testset") -> int:
    """Render ``cfg.per_object`` colour scans of every object into ``out_dir`` (see the module docstring);
    returns the scan count. ``render`` is built for ``cfg`` by the caller (it needs ``image_files(cfg.textures)``)."""
    from data_tools.camera import Camera, Intrinsics, write_camera_json
    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    from data_tools.results import atomic_write_bytes, atomic_write_json
    from data_tools.sequence import encode_rgb_png, write_depth_png
    from recog.patches import bbox_from_mask
    cfg.validate()
    out = check_output_dir(out_dir, finished="labels.json", overwrite=overwrite)
    for sub in ("rgb", "depth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    textures = image_files(cfg.textures)
    backgrounds = image_files(cfg.backgrounds, recursive=True, limit=cfg.max_backgrounds)
    total = cfg.per_object * len(objects)
    mark_incomplete(out, command, 0, total, unit="scans", resumable=False)
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=total, desc="colour scans", unit="scan")
    camera = Camera(Intrinsics(cfg.width, cfg.height, cfg.focal_px, cfg.focal_px, cfg.width / 2, cfg.height / 2),
                    5000.0, None)
    labels, k = [], 0
    for oi, obj in enumerate(objects):
        for s in range(cfg.per_object):
            full = None
            for drop in range(cfg.occluders[1] + 1):
                scene = draw_scene(obj, oi, s, cfg, len(textures), len(backgrounds), drop)
                rgba, depth, mask = render(scene, obj)
                if full is None:
                    full = int(render(ColourScene(**{**asdict(scene), "occluders": []}), obj)[2].sum())
                if mask.sum() >= max(cfg.min_visible * full, 100) or not scene.occluders:
                    break
            box = bbox_from_mask(mask)
            if box is None or mask.sum() < 100:
                raise ConfigError(f"{obj.name}: scan {s} shows fewer than 100 object pixels (object too large or "
                                  f"too small for the camera?)")
            bg = background_image(backgrounds[scene.background], scene.crop, cfg.width, cfg.height)
            rgb_name, depth_name = f"rgb/{k:06d}.png", f"depth/{k:06d}.png"
            atomic_write_bytes(out / rgb_name, encode_rgb_png(compose(rgba, bg)))
            write_depth_png(out / depth_name, depth, camera.depth_scale)
            labels.append({"file": depth_name, "rgb": rgb_name, "object": obj.name,
                           "pose": [[float(x) for x in r] for r in scene.pose], "bbox": [int(v) for v in box],
                           "occluders": len(scene.occluders), "visible_px": int(mask.sum())})
            k += 1
            mark_incomplete(out, command, k, total, unit="scans", resumable=False)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    write_camera_json(out / "camera.json", camera)
    atomic_write_json(out / "testset_config.json", {"domain": "rgb", **asdict(cfg),
                                                     "objects": [o.to_json() for o in objects]})
    atomic_write_json(out / "labels.json", labels, indent=1)
    clear_incomplete(out)
    return k


def colour_patch(rgb: np.ndarray, intr, patch, config) -> np.ndarray:
    """(3, S, S) float32 in [-1, 1]: the colour image ``rgb`` ((H, W, 3) uint8, registered to the depth) cut with
    the virtual camera of the depth patch ``patch`` (:class:`recog.patches.Patch` cut with ``config``, a
    :class:`recog.patches.PatchConfig`: same rotation, reference depth and pixels, nearest neighbour), i.e.
    pixel-aligned with the depth patch as A's colour is with its normals; outside the image black (-1)."""
    from recog.patches import resample_nearest
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ConfigError(f"a colour image must be (H, W, 3), got {rgb.shape}")
    ch = [resample_nearest(rgb[..., c].astype(np.float32), intr, patch.R_ray, patch.z_ref_m, config) for c in range(3)]
    return (np.stack(ch) / 127.5 - 1.0).astype(np.float32)
