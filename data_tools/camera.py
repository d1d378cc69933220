"""Pinhole camera intrinsics, sensor description and ``camera.json`` I/O.

Conventions (see ../shared/FORMATS.md): OpenCV optical frame (x right, y down, z forward),
pixel centres at integer coordinates, depth is z-depth in metres.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError

SENSOR_TYPES = ("structured_light", "active_stereo", "tof")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth (or colour) camera."""

    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    fx: float
    """Focal length along x, pixels."""
    fy: float
    """Focal length along y, pixels."""
    cx: float
    """Principal point x, pixels (pixel centres are integer coordinates)."""
    cy: float
    """Principal point y, pixels."""
    distortion: tuple[float, ...] | None = None
    """OpenCV distortion coefficients (k1, k2, p1, p2, k3); None means none."""

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            if int(v) != v or v <= 0:
                raise FormatError(None, f"intrinsics {name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise FormatError(None, f"intrinsics {name} is not finite ({v!r})")
            object.__setattr__(self, name, v)
        if self.fx <= 0 or self.fy <= 0:
            raise FormatError(None, f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.distortion is not None:
            d = tuple(float(x) for x in self.distortion)
            if len(d) not in (4, 5, 8):
                raise FormatError(None, f"distortion needs 4, 5 or 8 OpenCV coefficients, got {len(d)}")
            object.__setattr__(self, "distortion", None if not any(d) else d)

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape as (height, width)."""
        return (self.height, self.width)

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by ``factor`` (pixel-centre convention kept)."""
        return Intrinsics(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            distortion=self.distortion,
        )

    @classmethod
    def tum_default(cls) -> "Intrinsics":
        """TUM RGB-D documented defaults (640x480, f=525, c=(319.5, 239.5))."""
        return cls(640, 480, 525.0, 525.0, 319.5, 239.5)


@dataclass(frozen=True)
class SensorSpec:
    """The ``sensor`` block of camera.json: how the depth was measured."""

    type: str = "structured_light"
    """One of ``structured_light``, ``active_stereo``, ``tof``."""
    baseline_m: float = 0.075
    """Distance between the IR camera and the projector (or second IR camera), metres."""
    projector_offset_m: tuple[float, float, float] = (0.075, 0.0, 0.0)
    """Projector centre in the depth-camera frame, metres."""
    extra: dict = field(default_factory=dict)
    """Any further keys found in the file, kept verbatim."""

    def to_json(self) -> dict:
        d = {"type": self.type, "baseline_m": self.baseline_m,
             "projector_offset_m": list(self.projector_offset_m)}
        d.update(self.extra)
        return d


@dataclass(frozen=True)
class Camera:
    """Everything camera.json holds: intrinsics, depth PNG scale, optional sensor block."""

    intrinsics: Intrinsics
    """Depth-camera intrinsics (colour is assumed registered to depth)."""
    depth_scale: float = 5000.0
    """PNG value per metre: metres = value / depth_scale (TUM: 5000; 7-Scenes mm: 1000)."""
    sensor: SensorSpec | None = None
    """How depth was measured; None when unknown."""

    @classmethod
    def tum_default(cls) -> "Camera":
        return cls(Intrinsics.tum_default(), 5000.0, None)

    def to_json(self) -> dict:
        i = self.intrinsics
        d = {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx,
             "cy": i.cy, "depth_scale": self.depth_scale,
             "distortion": list(i.distortion) if i.distortion else [0.0, 0.0, 0.0, 0.0, 0.0]}
        if self.sensor is not None:
            d["sensor"] = self.sensor.to_json()
        return d


_REQUIRED = ("width", "height", "fx", "fy", "cx", "cy", "depth_scale")


def camera_from_dict(d: dict, path: str | os.PathLike | None = None) -> Camera:
    """Build a :class:`Camera` from parsed camera.json content; errors name ``path``."""
    if not isinstance(d, dict):
        raise FormatError(path, "camera.json must hold a JSON object")
    if "intrinsic_matrix" in d and "fx" not in d:
        d = _from_open3d_intrinsic(d, path)
    missing = [k for k in _REQUIRED if k not in d]
    if missing:
        raise FormatError(path, f"camera.json is missing key(s): {', '.join(missing)}")
    # JSON types must be right: a string or true/false where a number belongs is an error, not converted
    if d.get("sensor") is not None and not isinstance(d["sensor"], dict):
        raise FormatError(path, f"sensor must be a JSON object, got {d['sensor']!r}")
    sensor_d = d.get("sensor") or {}
    dist_d = d.get("distortion") or []
    off_d = sensor_d.get("projector_offset_m") or []
    if not isinstance(dist_d, list):
        raise FormatError(path, f"distortion must be a list of numbers, got {dist_d!r}")
    if not isinstance(off_d, list):
        raise FormatError(path, f"sensor.projector_offset_m must be a list of 3 numbers, got {off_d!r}")
    for key, value in [*((k, d[k]) for k in _REQUIRED), *(("distortion", v) for v in dist_d),
                       *((f"sensor.{k}", sensor_d[k]) for k in ("baseline_m",) if k in sensor_d),
                       *(("sensor.projector_offset_m", v) for v in off_d)]:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise FormatError(path, f"{key} must be a number, got {value!r}")
    try:
        dist = d.get("distortion")
        intr = Intrinsics(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"],
                          tuple(dist) if dist else None)
        scale = float(d["depth_scale"])
    except FormatError as e:
        raise FormatError(path, e.problem) from None
    except (TypeError, ValueError) as e:
        raise FormatError(path, f"camera.json has a value of the wrong type ({e})") from None
    if not math.isfinite(scale) or scale <= 0:
        raise FormatError(path, f"depth_scale must be a positive number, got {d['depth_scale']!r}")
    sensor = None
    if d.get("sensor") is not None:
        s = dict(d["sensor"])
        stype = s.pop("type", "structured_light")
        if stype not in SENSOR_TYPES:
            raise FormatError(path, f"sensor.type must be one of {', '.join(SENSOR_TYPES)}, got {stype!r}")
        try:
            baseline = float(s.pop("baseline_m", 0.075))
            off = tuple(float(x) for x in s.pop("projector_offset_m", (baseline, 0.0, 0.0)))
        except (TypeError, ValueError) as e:
            raise FormatError(path, f"sensor block has a value of the wrong type ({e})") from None
        if len(off) != 3:
            raise FormatError(path, "sensor.projector_offset_m must have 3 numbers")
        if baseline < 0:
            raise FormatError(path, f"sensor.baseline_m must be >= 0, got {baseline}")
        sensor = SensorSpec(stype, baseline, off, s)
    return Camera(intr, scale, sensor)


OPEN3D_DEFAULT_DEPTH_SCALE = 1000.0
"""Depth units per metre assumed for an Open3D intrinsic JSON (Open3D's own default: millimetres)."""


def _from_open3d_intrinsic(d: dict, path) -> dict:
    """camera.json keys from Open3D's ``PinholeCameraIntrinsic`` JSON (``width``, ``height`` and the
    3x3 ``intrinsic_matrix`` stored column-major, as ``o3d.io.write_pinhole_camera_intrinsic``
    writes it). It has no depth scale: ``depth_scale`` from the file if present, else 1000
    (Open3D's default) with a warning."""
    from data_tools.errors import warn
    K = d.get("intrinsic_matrix")
    if not isinstance(K, list) or len(K) != 9:
        raise FormatError(path, "intrinsic_matrix must hold 9 numbers (Open3D: the 3x3 matrix, column-major)")
    try:
        M = [[float(K[c * 3 + r]) for c in range(3)] for r in range(3)]
    except (TypeError, ValueError):
        raise FormatError(path, "intrinsic_matrix must hold 9 numbers") from None
    if M[0][1] != 0 or M[1][0] != 0 or M[2] != [0.0, 0.0, 1.0]:
        raise FormatError(path, "intrinsic_matrix is not a pinhole matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] "
                                "(Open3D stores it column-major)")
    out = {"width": d.get("width"), "height": d.get("height"), "fx": M[0][0], "fy": M[1][1], "cx": M[0][2],
           "cy": M[1][2], "depth_scale": d.get("depth_scale", OPEN3D_DEFAULT_DEPTH_SCALE)}
    if "depth_scale" not in d:
        warn(f"{path}: Open3D intrinsic JSON has no depth scale; assuming {OPEN3D_DEFAULT_DEPTH_SCALE:g} "
                      f"units per metre (Open3D's default; add \"depth_scale\" to the file to change it)")
    for k in ("sensor", "distortion"):
        if k in d:
            out[k] = d[k]
    return out


def read_camera_json(path: str | os.PathLike) -> Camera:
    """Read camera.json (see ../shared/FORMATS.md), or Open3D's ``PinholeCameraIntrinsic`` JSON
    (converted by :func:`_from_open3d_intrinsic`)."""
    path = Path(path)
    if path.is_dir():
        raise FormatError(path, "is a folder, expected a camera JSON file")
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except UnicodeDecodeError:
        raise FormatError(path, "not a text (JSON) file") from None
    except json.JSONDecodeError as e:
        raise FormatError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    return camera_from_dict(d, path)


def write_camera_json(path: str | os.PathLike, camera: Camera) -> None:
    from data_tools.results import atomic_write_json
    atomic_write_json(path, camera.to_json())
