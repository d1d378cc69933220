"""Per-pixel features of the sensor lab and the :class:`FrameObservation` they are computed from.

The sensor lab explains *where* a depth model fails by binning pixels by physical features
computed from the ideal (noise-free) geometry of each frame:

``distance``
    Ideal z-depth of the pixel, metres.
``incidence``
    Angle between the camera ray and the surface normal, degrees in [0, 90]
    (0 = the surface faces the camera). The normal's orientation does not matter (``|cos|``).
``incidence_projector``
    Same angle measured against the ray from the surface point to the projector centre
    (needs ``projector_offset_m``); this is the angle that sets the brightness of a projected
    dot pattern.
``radial``
    Distance of the pixel centre from the principal point divided by the largest such distance
    over the four corner pixel centres, so it lies in [0, 1] (equal to the normalised
    half-diagonal when the principal point is central). :func:`~synth.lab.feature_maps.radial_distance` also returns
    it in pixels.
``material``
    Material name of the surface hit by the pixel (instance id -> material table).
``edge_distance``
    Signed distance (pixels) to the nearest ideal-depth discontinuity; **+ on the far
    (background) side, - on the near (foreground) side** (see below).
``edge_shadow``
    For background-side pixels only: signed distance (pixels) to the nearest discontinuity,
    **+ on the side where projector shadows fall, - on the lit side** (needs
    ``projector_offset_m``); NaN on the foreground side.

How edges and the shadow side are found (and why): :mod:`synth.lab.feature_maps`.

Features form a registry (:data:`FEATURES`): a new feature is a :class:`Feature` subclass with
``@register_feature``; :mod:`synth.lab.compare` bins and compares whatever is registered."""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from data_tools.config import config_from_dict, config_to_dict
from data_tools.camera import Intrinsics
from data_tools.errors import ConfigError, RealgapError
from synth.lab.feature_maps import (EdgeDistanceMaps, baseline_image_direction, edge_distance_maps,
                                    incidence_angle_deg, radial_distance, shadow_edge_values,
                                    signed_edge_values)

NO_GEOMETRY_MATERIAL = "(no geometry)"
"""Material name of pixels whose id is 0 (background / no hit)."""
UNKNOWN_MATERIAL = "(unknown)"
"""Material name of ids missing from the material table."""


# --------------------------------------------------------------------------------------------
# Input
# --------------------------------------------------------------------------------------------

def _check_depth(name: str, a, shape: tuple[int, int]) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2 or a.shape != shape:
        raise RealgapError(f"FrameObservation.{name}: expected shape {shape} (H, W) from the "
                           f"intrinsics, got {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise RealgapError(f"FrameObservation.{name}: expected a real-valued depth array, got {a.dtype}")
    a = a.astype(np.float32, copy=False)
    if not np.isfinite(a).all():
        raise RealgapError(f"FrameObservation.{name}: contains NaN or inf (use 0 for 'invalid')")
    if (a < 0).any():
        raise RealgapError(f"FrameObservation.{name}: contains negative depths (metres, 0 = invalid)")
    return a


def material_table(names: Mapping[int, str] | Sequence[str]) -> dict[int, str]:
    """Normalise a material table: mapping id -> name, or a sequence whose index is the id."""
    if isinstance(names, Mapping):
        items = names.items()
    elif isinstance(names, Sequence) and not isinstance(names, str):
        items = enumerate(names)
    else:
        raise RealgapError("material_names must be a mapping id -> name or a list indexed by id")
    out = {}
    for k, v in items:
        try:
            ki = int(k)
        except (TypeError, ValueError):
            raise RealgapError(f"material_names: id {k!r} is not an integer") from None
        out[ki] = str(v)
    return out


def material_table_from_scene(scene) -> dict[int, str]:
    """Instance id -> material name for a :class:`data_tools.scene_spec.SceneSpec`.

    Instance id of ``scene.meshes[k]`` is k + 1 (project convention); 0 = no hit.
    """
    table = {0: NO_GEOMETRY_MATERIAL}
    for k, mesh in enumerate(scene.meshes):
        table[k + 1] = mesh.material or UNKNOWN_MATERIAL
    return table


@dataclass
class FrameObservation:
    """One frame seen by the real sensor and by the model, plus its ideal geometry.

    All images are (H, W) with (H, W) = ``intrinsics.shape``; arrays are checked and converted
    at construction (float32 depths, int32 ids), bad input raises :class:`RealgapError`.
    """

    measured: np.ndarray
    """(H, W) float32 measured z-depth, metres; 0 = invalid (no measurement)."""
    simulated: np.ndarray
    """(H, W) float32 simulated z-depth of the same frame, metres; 0 = invalid."""
    ideal: np.ndarray
    """(H, W) float32 ideal (noise-free, rendered) z-depth, metres; 0 = no geometry."""
    normals: np.ndarray
    """(H, W, 3) float32 ideal surface normals in the camera frame (any orientation; 0 where no geometry)."""
    material_ids: np.ndarray
    """(H, W) int instance/material id per pixel (0 = background / no hit)."""
    material_names: Mapping[int, str] | Sequence[str]
    """Id -> material name (a mapping, or a list indexed by id); stored as a dict."""
    intrinsics: Intrinsics
    """Depth-camera intrinsics (pixels)."""
    projector_offset_m: tuple[float, float, float] | None = None
    """Projector (or second stereo camera) centre in the camera frame, metres; None = unknown/ToF."""
    index: int = 0
    """Frame index in its sequence (used in labels)."""
    timestamp: float | None = None
    """Seconds, optional."""

    def __post_init__(self) -> None:
        if not isinstance(self.intrinsics, Intrinsics):
            raise RealgapError("FrameObservation.intrinsics must be a data_tools.camera.Intrinsics")
        shape = self.intrinsics.shape
        self.measured = _check_depth("measured", self.measured, shape)
        self.simulated = _check_depth("simulated", self.simulated, shape)
        self.ideal = _check_depth("ideal", self.ideal, shape)
        n = np.asarray(self.normals)
        if n.shape != shape + (3,):
            raise RealgapError(f"FrameObservation.normals: expected shape {shape + (3,)}, got {n.shape}")
        n = n.astype(np.float32, copy=False)
        if not np.isfinite(n).all():
            raise RealgapError("FrameObservation.normals: contains NaN or inf (use 0 where unknown)")
        self.normals = n
        ids = np.asarray(self.material_ids)
        if ids.shape != shape:
            raise RealgapError(f"FrameObservation.material_ids: expected shape {shape}, got {ids.shape}")
        if not np.issubdtype(ids.dtype, np.integer):
            raise RealgapError(f"FrameObservation.material_ids: expected an integer array, got {ids.dtype}")
        self.material_ids = ids.astype(np.int32, copy=False)
        self.material_names = material_table(self.material_names)
        if self.projector_offset_m is not None:
            p = tuple(float(x) for x in self.projector_offset_m)
            if len(p) != 3 or not all(math.isfinite(x) for x in p):
                raise RealgapError(f"FrameObservation.projector_offset_m must be 3 finite numbers, got {self.projector_offset_m!r}")
            self.projector_offset_m = p
        self.index = int(self.index)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return self.intrinsics.shape


# --------------------------------------------------------------------------------------------
# Feature registry
# --------------------------------------------------------------------------------------------

@dataclass
class FeatureConfig:
    """How features are computed and binned."""

    edge_rel_threshold: float = 0.05
    """Relative ideal-depth jump (z_far - z_near) / z_near that makes a depth edge."""
    distance_range_m: tuple[float, float] = (0.25, 8.0)
    """Range of the distance bins, metres (pixels outside are left out of this feature)."""
    distance_step_m: float = 0.25
    """Width of the distance bins, metres."""
    incidence_step_deg: float = 5.0
    """Width of the incidence-angle bins over [0, 90] degrees."""
    radial_bins: int = 10
    """Number of equal bins of the normalised radial distance over [0, 1]."""
    edge_bins_px: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0)
    """Increasing |distance| edges (pixels) of the signed edge bins; each side gets
    [0, e1), [e1, e2), ..., [e_last, inf)."""

    def validate(self) -> "FeatureConfig":
        lo, hi = (float(x) for x in self.distance_range_m)
        if not (0 <= lo < hi) or self.distance_step_m <= 0:
            raise ConfigError(f"distance bins: need 0 <= lo < hi and step > 0, got {self.distance_range_m}, {self.distance_step_m}")
        if not (0 < self.incidence_step_deg <= 90):
            raise ConfigError(f"incidence_step_deg must be in (0, 90], got {self.incidence_step_deg}")
        if int(self.radial_bins) < 1:
            raise ConfigError(f"radial_bins must be >= 1, got {self.radial_bins}")
        e = [float(x) for x in self.edge_bins_px]
        if not e or e[0] <= 0 or any(b <= a for a, b in zip(e, e[1:])):
            raise ConfigError(f"edge_bins_px must be positive and increasing, got {self.edge_bins_px}")
        if not (0 < self.edge_rel_threshold < 10):
            raise ConfigError(f"edge_rel_threshold must be in (0, 10), got {self.edge_rel_threshold}")
        return self

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureConfig":
        return config_from_dict(cls, d, "feature config")


@dataclass(frozen=True)
class Binning:
    """Bins of a numeric feature: intervals [edges[k], edges[k+1]) (the last one closed)."""

    edges: tuple[float, ...]
    """K + 1 increasing edges (may start at -inf / end at +inf)."""
    labels: tuple[str, ...]
    """K human-readable labels."""

    def assign(self, values: np.ndarray) -> np.ndarray:
        """Bin index (int64) per value; -1 for NaN and values outside the range."""
        e = np.asarray(self.edges)
        v = np.asarray(values, dtype=np.float64)
        k = len(e) - 1
        with np.errstate(invalid="ignore"):
            idx = np.searchsorted(e, v, side="right") - 1
            idx[v == e[-1]] = k - 1
            idx[(idx < 0) | (idx >= k) | np.isnan(v)] = -1
        return idx.astype(np.int64)

    @property
    def centres(self) -> np.ndarray:
        """Bin centres (infinite ends replaced by a point one bin-width beyond the finite edge)."""
        e = np.asarray(self.edges, dtype=np.float64).copy()
        if np.isinf(e[0]):
            e[0] = e[1] - (e[2] - e[1] if len(e) > 2 and np.isfinite(e[2]) else 1.0)
        if np.isinf(e[-1]):
            e[-1] = e[-2] + (e[-2] - e[-3] if len(e) > 2 and np.isfinite(e[-3]) else 1.0)
        return 0.5 * (e[:-1] + e[1:])


@dataclass
class CategoricalValues:
    """Values of a categorical feature at some pixels: local codes into ``names``."""

    codes: np.ndarray
    """(N,) int codes, -1 = no category."""
    names: list[str]
    """Category names."""


class FrameFeatures:
    """Per-frame cache of derived images (edge distance transforms) shared by the features."""

    def __init__(self, obs: FrameObservation, config: FeatureConfig):
        self.obs = obs
        self.config = config
        self._maps: EdgeDistanceMaps | None = None

    @property
    def baseline_dir(self) -> np.ndarray | None:
        o = self.obs
        return None if o.projector_offset_m is None else baseline_image_direction(o.projector_offset_m, o.intrinsics)

    @property
    def edge_maps(self) -> EdgeDistanceMaps:
        """Edge distance transforms, split by baseline side when a projector is known."""
        if self._maps is None:
            self._maps = edge_distance_maps(self.obs.ideal, self.config.edge_rel_threshold, self.baseline_dir)
        return self._maps


class Feature(ABC):
    """A per-pixel feature used to bin the comparison. Subclass, set the class attributes,
    implement :meth:`values` (and :meth:`binning` for numeric features), decorate with
    :func:`register_feature`."""

    name: ClassVar[str]
    """Registry key, also the key in ``metrics.json`` breakdowns."""
    title: ClassVar[str]
    """Axis label without unit."""
    unit: ClassVar[str]
    """Unit of the values ('' for none)."""
    categorical: ClassVar[bool] = False
    """True when values are categories (bars), not numbers (curves)."""

    def __init__(self, config: FeatureConfig):
        self.config = config

    def available(self, frame: FrameFeatures) -> bool:
        """False when the frame lacks what the feature needs (e.g. a projector offset)."""
        return True

    @abstractmethod
    def values(self, frame: FrameFeatures, idx: np.ndarray) -> np.ndarray | CategoricalValues:
        """Feature values at flat pixel indices ``idx`` (N,) of the frame (NaN = undefined)."""

    def binning(self) -> Binning:
        """Bins of a numeric feature."""
        raise NotImplementedError(f"feature {self.name} has no numeric binning")


FEATURES: dict[str, type[Feature]] = {}
"""Registry of features by name (registration order = report order)."""


def register_feature(cls: type[Feature]) -> type[Feature]:
    """Class decorator adding a :class:`Feature` to :data:`FEATURES`."""
    if not getattr(cls, "name", None):
        raise TypeError(f"{cls.__name__} needs a 'name'")
    FEATURES[cls.name] = cls
    return cls


def make_feature(name: str, config: FeatureConfig) -> Feature:
    """Instantiate a registered feature; unknown names raise :class:`ConfigError`."""
    try:
        return FEATURES[name](config)
    except KeyError:
        raise ConfigError(f"unknown lab feature {name!r}; known: {', '.join(FEATURES)}") from None


def _range_bins(lo: float, hi: float, step: float, fmt: str, unit: str) -> Binning:
    n = max(1, int(round((hi - lo) / step)))
    edges = tuple(float(x) for x in np.round(lo + step * np.arange(n + 1), 9))
    labels = tuple(f"{fmt.format(a)}–{fmt.format(b)}{unit}" for a, b in zip(edges, edges[1:]))
    return Binning(edges, labels)


@register_feature
class DistanceFeature(Feature):
    name = "distance"
    title = "ideal depth z"
    unit = "m"

    def values(self, frame, idx):
        return frame.obs.ideal.reshape(-1)[idx].astype(np.float64)

    def binning(self):
        lo, hi = self.config.distance_range_m
        return _range_bins(lo, hi, self.config.distance_step_m, "{:.2f}", " m")


@register_feature
class IncidenceFeature(Feature):
    name = "incidence"
    title = "incidence angle (camera ray vs normal)"
    unit = "deg"

    def values(self, frame, idx):
        return incidence_angle_deg(frame.obs.normals, frame.obs.intrinsics, idx=idx)

    def binning(self):
        return _range_bins(0.0, 90.0, self.config.incidence_step_deg, "{:g}", "°")


@register_feature
class ProjectorIncidenceFeature(Feature):
    name = "incidence_projector"
    title = "incidence angle (projector ray vs normal)"
    unit = "deg"

    def available(self, frame):
        return frame.obs.projector_offset_m is not None

    def values(self, frame, idx):
        o = frame.obs
        return incidence_angle_deg(o.normals, o.intrinsics, depth=o.ideal,
                                   origin_m=o.projector_offset_m, idx=idx)

    def binning(self):
        return _range_bins(0.0, 90.0, self.config.incidence_step_deg, "{:g}", "°")


@register_feature
class RadialFeature(Feature):
    name = "radial"
    title = "radial distance from the principal point (1 = farthest corner)"
    unit = ""

    def values(self, frame, idx):
        return radial_distance(frame.obs.intrinsics, idx)[0]

    def binning(self):
        return _range_bins(0.0, 1.0, 1.0 / int(self.config.radial_bins), "{:.2f}", "")


@register_feature
class MaterialFeature(Feature):
    name = "material"
    title = "material"
    unit = ""
    categorical = True

    def values(self, frame, idx):
        ids = frame.obs.material_ids.reshape(-1)[idx]
        uniq, inv = np.unique(ids, return_inverse=True)
        table = frame.obs.material_names
        names = [table.get(int(k), NO_GEOMETRY_MATERIAL if k == 0 else UNKNOWN_MATERIAL) for k in uniq]
        return CategoricalValues(inv.reshape(-1).astype(np.int64), names)


def _signed_bins(edges_px: Sequence[float]) -> Binning:
    e = [float(x) for x in edges_px]
    neg = [-np.inf] + [-x for x in reversed(e)]
    edges = tuple(neg + [0.0] + e + [np.inf])
    labels = []
    for a, b in zip(edges, edges[1:]):
        if np.isinf(a):
            labels.append(f"< {b:g}")
        elif np.isinf(b):
            labels.append(f"> {a:g}")
        else:
            labels.append(f"{a:g}..{b:g}")
    return Binning(edges, tuple(labels))


@register_feature
class EdgeDistanceFeature(Feature):
    name = "edge_distance"
    title = "signed distance to depth edge (+ background side)"
    unit = "px"

    def values(self, frame, idx):
        return signed_edge_values(frame.edge_maps, idx).astype(np.float64)

    def binning(self):
        return _signed_bins(self.config.edge_bins_px)


@register_feature
class EdgeShadowFeature(Feature):
    name = "edge_shadow"
    title = "background distance to depth edge (+ projector-shadow side)"
    unit = "px"

    def available(self, frame):
        return frame.baseline_dir is not None

    def values(self, frame, idx):
        return shadow_edge_values(frame.edge_maps, idx).astype(np.float64)

    def binning(self):
        return _signed_bins(self.config.edge_bins_px)
