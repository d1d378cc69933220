"""Configuration of the sensor-lab comparison: :class:`CompareConfig` (sampling, error scale,
weights), its named presets and the error scale s(z) (the formula is in :mod:`synth.lab.compare`)."""
from __future__ import annotations

import math

from dataclasses import dataclass, field

import numpy as np

from data_tools.config import config_from_dict, config_to_dict
from data_tools.errors import ConfigError
from synth.lab.features import FEATURES, FeatureConfig

__all__ = ["CompareConfig", "PRESETS", "compare_preset", "error_scale_m"]

@dataclass
class CompareConfig:
    """How the comparison samples, bins and weighs (the formula is in :mod:`synth.lab.compare`)."""

    max_pixels_per_frame: int | None = 20000
    """Random (seeded) geometry pixels used per frame for the binned terms; None = all pixels."""
    seed: int = 0
    """Seed of the pixel subsets (frame k uses the stream (seed, k))."""
    gap_features: tuple[str, ...] = ("distance", "incidence", "radial", "material",
                                     "edge_distance", "edge_shadow")
    """Features whose terms are averaged into the gap (those without data are skipped)."""
    extra_features: tuple[str, ...] = ("incidence_projector",)
    """Features computed for the breakdowns only."""
    scale_a_m: float = 0.001
    """Constant part a of the error scale s(z) = a + b z^2, metres."""
    scale_b_per_m: float = 0.002
    """Quadratic coefficient b of s(z) = a + b z^2, 1/metre (so b z^2 is metres)."""
    error_clip: float = 10.0
    """Normalised errors e / s(z) are clipped to +-error_clip before W1."""
    weight_error: float = 1.0
    """w_err: weight of the W1 term (units of s(z))."""
    weight_invalid: float = 2.0
    """w_inv: weight of the invalid-fraction difference."""
    weight_spatial: float = 2.0
    """w_sp: weight of the spatial (misplaced holes) term."""
    min_bin_count: int = 20
    """Bins with fewer sampled geometry pixels are left out."""
    min_valid_count: int = 10
    """W1 needs at least this many valid samples on both sides (else it counts 0)."""
    spatial_block_px: int = 8
    """Block size (pixels) of the spatial term."""
    spatial_kappa: float = 2.0
    """Binomial standard deviations of hole-rate difference forgiven per block."""
    features: FeatureConfig = field(default_factory=FeatureConfig)
    """How features are computed and binned."""

    def validate(self) -> "CompareConfig":
        if self.max_pixels_per_frame is not None and int(self.max_pixels_per_frame) < 1:
            raise ConfigError(f"max_pixels_per_frame must be >= 1 or None, got {self.max_pixels_per_frame}")
        for name in (*self.gap_features, *self.extra_features):
            if name not in FEATURES:
                raise ConfigError(f"unknown lab feature {name!r}; known: {', '.join(FEATURES)}")
        if self.scale_a_m < 0 or self.scale_b_per_m < 0 or self.scale_a_m + self.scale_b_per_m <= 0:
            raise ConfigError("error scale s(z) = a + b z^2 needs a, b >= 0, not both 0")
        for name in ("error_clip", "weight_error", "weight_invalid", "weight_spatial", "spatial_kappa"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{name} must be a finite number >= 0, got {v}")
        if self.error_clip <= 0:
            raise ConfigError("error_clip must be > 0")
        if self.min_bin_count < 1 or self.min_valid_count < 1 or self.spatial_block_px < 1:
            raise ConfigError("min_bin_count, min_valid_count and spatial_block_px must be >= 1")
        self.features.validate()
        return self

    def feature_names(self) -> list[str]:
        """Gap and extra features in registry order."""
        wanted = set(self.gap_features) | set(self.extra_features)
        return [n for n in FEATURES if n in wanted]

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "CompareConfig":
        return config_from_dict(cls, d, "compare config")


PRESETS: dict[str, CompareConfig] = {
    "default": CompareConfig(),
    "fast": CompareConfig(max_pixels_per_frame=5000),
    "exact": CompareConfig(max_pixels_per_frame=None),
}
"""Named configurations: ``default`` (20k samples/frame), ``fast`` (5k), ``exact`` (all pixels)."""


def compare_preset(name: str) -> CompareConfig:
    """A fresh copy of a named preset."""
    if name not in PRESETS:
        raise ConfigError(f"unknown compare preset {name!r}; known: {', '.join(PRESETS)}")
    return CompareConfig.from_dict(PRESETS[name].to_dict())


def error_scale_m(z_m: np.ndarray, config: CompareConfig) -> np.ndarray:
    """s(z) = a + b z^2 in metres for ideal depths z (metres)."""
    z = np.asarray(z_m, dtype=np.float64)
    return config.scale_a_m + config.scale_b_per_m * z * z
