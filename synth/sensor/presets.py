"""Named depth-sensor presets: the device geometry, pattern, matcher and default effect models.

A preset holds what does not change from frame to frame (intrinsics, baseline, projector,
matcher window and sub-pixel step, working range) plus two effect lists:

* ``physical_effects``: the full physical pipeline (projector -> IR capture -> block matching
  -> post-processing); the default for every structured-light and active-stereo preset;
* ``direct_effects``: the analytic model built effect by effect from the ideal depth (and the
  default of the ToF preset, which has no physical pipeline here).

``effect_params`` gives per-preset defaults for the effect parameters. Numbers that come from
a publication say so in the docstring of the preset; tuned values (noise levels calibrated on
the flat-wall experiment) say that too.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from data_tools.camera import SENSOR_TYPES, Intrinsics
from data_tools.errors import ConfigError


@dataclass(frozen=True)
class SensorPreset:
    """One depth sensor: geometry, projector, matcher, range and default effect models."""

    name: str
    """Preset name (``kinect_v1``...)."""
    type: str
    """``structured_light``, ``active_stereo`` or ``tof``."""
    width: int
    """Depth image width, pixels."""
    height: int
    """Depth image height, pixels."""
    fx: float
    """IR (depth) camera focal length x, pixels."""
    fy: float
    """IR camera focal length y, pixels."""
    cx: float
    """Principal point x, pixels."""
    cy: float
    """Principal point y, pixels."""
    baseline_m: float
    """Structured light: camera-projector distance; active stereo: distance between the two IR
    cameras (the second one at +x); ToF: 0. Metres."""
    projector_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Projector (emitter) centre in the IR camera frame, metres."""
    min_depth_m: float = 0.4
    """Nearest depth the device reports, metres (also bounds the disparity search)."""
    max_depth_m: float = 8.0
    """Farthest depth the device reports, metres."""
    fps: float = 30.0
    """Frame rate, Hz (time between frames for motion effects)."""
    depth_scale: float = 5000.0
    """PNG value per metre when sequences are written."""
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    """IR lens distortion (OpenCV k1 k2 p1 p2 k3) used by the ``lens_distortion`` effect."""
    pattern: str = "generated"
    """``generated`` (the in-code Kinect-like generator) or a path to a pattern image."""
    pattern_size_px: tuple[int, int] = (633, 495)
    """Projector image (width, height), pattern pixels; a loaded image must have this size."""
    pattern_tiles: tuple[int, int] = (3, 3)
    """Generated pattern: (columns, rows) of identical tiles."""
    pattern_density: float = 0.111
    """Generated pattern: fraction of lit projector pixels."""
    pattern_seed: int = 0
    """Generated pattern: seed of the dot layout (fixed per device)."""
    projector_focal_px: float = 470.0
    """Projector focal length in pattern pixels (sets its field of view; principal point at the
    pattern centre, optical axis parallel to the camera's)."""
    block_size: int = 9
    """Matching window side, pixels (odd)."""
    subpixel_step_px: float = 0.125
    """Disparity quantisation step of the device, pixels (Kinect v1: 1/8)."""
    reference_depth_m: float = 1.0
    """Structured light: depth of the stored reference pattern image, metres
    (disparity d is relative to it: 1/z = 1/z0 + d/(f b))."""
    matcher: str = "bm"
    """``bm`` (OpenCV StereoBM, SAD), ``sgbm`` (semi-global, active stereo) or ``none`` (ToF)."""
    physical_effects: tuple[str, ...] = ()
    """Effect names of the physical pipeline, in order."""
    direct_effects: tuple[str, ...] = ()
    """Effect names of the direct (analytic) model, in order."""
    effect_params: dict = field(default_factory=dict, compare=False)
    """Per-effect parameter defaults of this device: {effect name: {param: value}}."""
    description: str = ""
    """One line about the device."""
    source: str = ""
    """Where the numbers come from."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """ConfigError (one line, naming the preset) for impossible values."""
        n = self.name or "custom"
        if self.type not in SENSOR_TYPES:
            raise ConfigError(f"sensor preset {n!r}: type must be one of {', '.join(SENSOR_TYPES)}, got {self.type!r}")
        if not (isinstance(self.width, int) and isinstance(self.height, int)) or self.width < 16 or self.height < 16:
            raise ConfigError(f"sensor preset {n!r}: width/height must be integers >= 16, got {self.width}x{self.height}")
        for k in ("fx", "fy", "cx", "cy", "baseline_m", "min_depth_m", "max_depth_m", "fps"):
            if not math.isfinite(float(getattr(self, k))):
                raise ConfigError(f"sensor preset {n!r}: {k} is not finite")
        if self.fx <= 0 or self.fy <= 0:
            raise ConfigError(f"sensor preset {n!r}: focal lengths must be positive")
        if self.baseline_m < 0:
            raise ConfigError(f"sensor preset {n!r}: baseline_m must be >= 0 (the side is given by "
                              f"projector_offset_m), got {self.baseline_m}")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError(f"sensor preset {n!r}: need 0 < min_depth_m < max_depth_m, got "
                              f"{self.min_depth_m}..{self.max_depth_m}")
        if len(self.projector_offset_m) != 3:
            raise ConfigError(f"sensor preset {n!r}: projector_offset_m needs 3 numbers")
        if self.type in ("structured_light", "active_stereo"):
            if self.baseline_m <= 0:
                raise ConfigError(f"sensor preset {n!r}: a {self.type} sensor needs a positive baseline_m, "
                                  f"got {self.baseline_m}")
            if self.block_size < 3 or self.block_size % 2 == 0 or self.block_size > 31:
                raise ConfigError(f"sensor preset {n!r}: block_size must be odd in [3, 31], got {self.block_size}")
            if not 0 < self.subpixel_step_px <= 1:
                raise ConfigError(f"sensor preset {n!r}: subpixel_step_px must be in (0, 1], got {self.subpixel_step_px}")
            if self.projector_focal_px <= 0:
                raise ConfigError(f"sensor preset {n!r}: projector_focal_px must be positive")
        if self.type == "structured_light":
            ox, oy, oz = (float(v) for v in self.projector_offset_m)
            if abs(oy) > 1e-6 or abs(oz) > 1e-6 or abs(abs(ox) - self.baseline_m) > 1e-6:
                raise ConfigError(f"sensor preset {n!r}: structured-light matching needs the projector on the "
                                  f"camera x axis at +-baseline_m, got offset {self.projector_offset_m} for "
                                  f"baseline {self.baseline_m}")
            if not self.reference_depth_m > 0:
                raise ConfigError(f"sensor preset {n!r}: reference_depth_m must be positive")
        if self.matcher not in ("bm", "sgbm", "none"):
            raise ConfigError(f"sensor preset {n!r}: matcher must be 'bm', 'sgbm' or 'none', got {self.matcher!r}")

    # -- derived ---------------------------------------------------------------------------
    @property
    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics of the depth image (no distortion: see the lens_distortion effect)."""
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    @property
    def fb(self) -> float:
        """Focal length times baseline, pixel-metres: disparity d = fb / z."""
        return self.fx * self.baseline_m

    @property
    def projector_side(self) -> float:
        """+1 when the projector (or second camera) is at +x of the IR camera, -1 at -x."""
        return -1.0 if self.projector_offset_m[0] < 0 else 1.0

    def cropped(self, width: int, height: int) -> "SensorPreset":
        """The same device with a centred ``width`` x ``height`` crop of its image (same focal
        length, projector and matcher): identical per-pixel physics at a fraction of the cost
        (used by fast tests)."""
        if not (16 <= width <= self.width and 16 <= height <= self.height):
            raise ConfigError(f"crop {width}x{height} must lie within {self.width}x{self.height}")
        return dataclasses.replace(self, width=int(width), height=int(height),
                                   cx=self.cx - (self.width - width) / 2.0,
                                   cy=self.cy - (self.height - height) / 2.0)

    def replace(self, **changes) -> "SensorPreset":
        """A validated copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d

    @classmethod
    def from_json(cls, d: dict) -> "SensorPreset":
        if not isinstance(d, dict):
            raise ConfigError("sensor preset must be a JSON object")
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - fields)
        if unknown:
            raise ConfigError(f"sensor preset: unknown key(s) {', '.join(unknown)}")
        kw = dict(d)
        for k in ("projector_offset_m", "distortion", "physical_effects", "direct_effects"):
            if k in kw:
                kw[k] = tuple(kw[k])
        for k in ("pattern_size_px", "pattern_tiles"):
            if k in kw:
                kw[k] = tuple(int(v) for v in kw[k])
        for k in ("width", "height", "block_size", "pattern_seed"):
            if k in kw:
                kw[k] = int(kw[k])
        try:
            return cls(**kw)
        except TypeError as e:
            raise ConfigError(f"sensor preset: {e}") from None


# ------------------------------------------------------------------------------------------
# The presets
# ------------------------------------------------------------------------------------------

_SL_PHYSICAL = ("rolling_shutter", "pattern_projection", "ambient_light", "motion_blur", "ir_capture",
                "block_matching", "range_limits")
_SL_DIRECT = ("projector_shadow", "incidence_dropout", "low_reflectance", "specular_dropout",
              "edge_fattening", "axial_noise", "disparity_quantization", "range_limits")

KINECT_V1 = SensorPreset(
    name="kinect_v1",
    type="structured_light",
    width=640, height=480, fx=580.0, fy=580.0, cx=319.5, cy=239.5,
    baseline_m=0.075, projector_offset_m=(0.075, 0.0, 0.0),
    min_depth_m=0.45, max_depth_m=8.0, fps=30.0,
    pattern="generated", pattern_size_px=(633, 495), pattern_tiles=(3, 3), pattern_density=0.111,
    projector_focal_px=470.0, block_size=9, subpixel_step_px=0.125, reference_depth_m=1.0,
    matcher="bm",
    physical_effects=_SL_PHYSICAL,
    direct_effects=_SL_DIRECT,
    effect_params={
        "ir_capture": {"gain_e": 30000.0, "full_well_e": 20000.0, "read_noise_e": 5.0,
                       "speckle_contrast": 0.3, "psf_sigma_px": 0.6, "adc_bits": 10},
        "block_matching": {"prefilter_cap": 31, "uniqueness_ratio": 10, "speckle_window_px": 200,
                           "speckle_range_steps": 1.0},
        "incidence_dropout": {"angle50_deg": 77.5, "width_deg": 2.0},
        "axial_noise": {"sigma0_m": 0.0, "sigma2_per_m": 0.0014, "z_offset_m": 0.0},
        "rolling_shutter": {"readout_time_s": 0.03},
        "motion_blur": {"exposure_s": 0.015},
    },
    description="Microsoft Kinect for Xbox 360 (PrimeSense PS1080), 640x480 depth at 30 Hz.",
    source=("f ~ 580 px, b = 7.5 cm, 9x9 correlation window, 1/8 px disparity: Konolige & Mihelich, "
            "'Technical description of Kinect calibration' (ROS wiki, 2011); Khoshelham & Elberink, "
            "Sensors 12(2):1437, 2012 (b ~ 7.5 cm, f ~ 5.45 mm ~ 580 px, 11-bit disparity); 3x3 tiled "
            "pattern of ~34,700 dots (shared/data/patterns). Noise levels of ir_capture are tuned on the "
            "flat-wall experiment (synth/sensor/validation.py) against Khoshelham 2012 and Nguyen et al. 2012."),
)

STRUCTURE = SensorPreset(
    name="structure",
    type="structured_light",
    width=640, height=480, fx=577.0, fy=577.0, cx=319.5, cy=239.5,
    baseline_m=0.065, projector_offset_m=(0.065, 0.0, 0.0),
    min_depth_m=0.4, max_depth_m=3.5, fps=30.0,
    pattern="generated", pattern_size_px=(633, 495), pattern_tiles=(3, 3), pattern_density=0.111,
    pattern_seed=7, projector_focal_px=470.0, block_size=9, subpixel_step_px=0.125, reference_depth_m=1.0,
    matcher="bm",
    physical_effects=_SL_PHYSICAL,
    direct_effects=_SL_DIRECT,
    effect_params={
        "ir_capture": {"gain_e": 30000.0, "full_well_e": 20000.0, "read_noise_e": 8.0,
                       "speckle_contrast": 0.6, "psf_sigma_px": 0.7, "adc_bits": 10},
        "block_matching": {"prefilter_cap": 31, "uniqueness_ratio": 10, "speckle_window_px": 200,
                           "speckle_range_steps": 1.0},
        "axial_noise": {"sigma0_m": 0.0, "sigma2_per_m": 0.0031, "z_offset_m": 0.0},
        "rolling_shutter": {"readout_time_s": 0.03},
        "motion_blur": {"exposure_s": 0.015},
    },
    description="Occipital Structure Sensor (first generation, PrimeSense-based), VGA depth at 30 Hz.",
    source=("Occipital spec sheet: 640x480 @ 30 fps, FOV 58 x 45 deg (-> f ~ 577 px), range 0.4-3.5 m, "
            "precision 0.5 mm at 40 cm and 30 mm at 3 m. The baseline is not published: 6.5 cm is an "
            "estimate; with it both precision figures give sigma_d ~ 0.12 px, which the higher speckle "
            "contrast (0.6, tuned on the flat-wall experiment: 0.8 mm at 0.5 m, 29 mm at 3 m) reproduces. "
            "Pattern: a generated Kinect-like one (the real one is not available)."),
)

REALSENSE_D435 = SensorPreset(
    name="realsense_d435",
    type="active_stereo",
    width=848, height=480, fx=428.0, fy=428.0, cx=423.5, cy=239.5,
    baseline_m=0.050, projector_offset_m=(0.025, 0.0, 0.0),
    min_depth_m=0.2, max_depth_m=10.0, fps=30.0,
    pattern="generated", pattern_size_px=(1000, 600), pattern_tiles=(1, 1), pattern_density=0.1,
    pattern_seed=11, projector_focal_px=420.0, block_size=7, subpixel_step_px=1.0 / 16.0,
    reference_depth_m=1.0, matcher="sgbm",
    physical_effects=("rolling_shutter", "pattern_projection", "ambient_light", "motion_blur", "ir_capture",
                      "block_matching", "range_limits"),
    direct_effects=("projector_shadow", "incidence_dropout", "low_reflectance", "specular_dropout",
                    "edge_fattening", "axial_noise", "disparity_quantization", "range_limits"),
    effect_params={
        "ir_capture": {"gain_e": 20000.0, "full_well_e": 20000.0, "read_noise_e": 5.0,
                       "speckle_contrast": 0.1, "psf_sigma_px": 0.6, "adc_bits": 10},
        "ambient_light": {"level": 0.05},
        "block_matching": {"prefilter_cap": 31, "uniqueness_ratio": 10, "speckle_window_px": 100,
                           "speckle_range_steps": 2.0, "lr_max_diff_px": 1},
        "axial_noise": {"sigma0_m": 0.0, "sigma2_per_m": 0.0019, "z_offset_m": 0.0},
        "rolling_shutter": {"readout_time_s": 0.0},
        "motion_blur": {"exposure_s": 0.008},
    },
    description="Intel RealSense D435: active IR stereo (global shutter), 848x480 depth.",
    source=("Intel D400 series datasheet: depth FOV 87 x 58 deg (-> f ~ 428 px at 848 px), baseline 50 mm, "
            "left imager is the depth reference (invalid band B*f/z px on the left), min-Z ~0.2 m at 848x480, "
            "range to ~10 m; semi-global matching with sub-pixel interpolation (OpenCV SGBM's 1/16 px here). "
            "The emitter is placed between the imagers; its random (non-tiled) dot pattern is generated."),
)

KINECT_V2 = SensorPreset(
    name="kinect_v2",
    type="tof",
    width=512, height=424, fx=365.5, fy=365.5, cx=255.5, cy=211.5,
    baseline_m=0.0, projector_offset_m=(0.0, 0.0, 0.0),
    min_depth_m=0.5, max_depth_m=4.5, fps=30.0,
    matcher="none",
    physical_effects=("incidence_dropout", "low_reflectance", "specular_dropout", "multipath",
                      "flying_pixels", "wiggling", "axial_noise", "range_limits"),
    direct_effects=("incidence_dropout", "low_reflectance", "specular_dropout", "multipath",
                    "flying_pixels", "wiggling", "axial_noise", "range_limits"),
    effect_params={
        "axial_noise": {"sigma0_m": 0.0005, "sigma1": 0.0004, "sigma2_per_m": 0.0,
                        "reflectance_exponent": 0.5},
        "incidence_dropout": {"angle50_deg": 82.0, "width_deg": 3.0},
        "low_reflectance": {"signal50": 0.004},
    },
    description="Microsoft Kinect for Xbox One (Kinect v2), continuous-wave ToF, 512x424 at 30 Hz.",
    source=("512x424, FOV 70.6 x 60 deg (f ~ 365 px), 0.5-4.5 m: Microsoft spec; multi-frequency CW-ToF "
            "(16/80/120 MHz: Sell & O'Connor, IEEE Micro 2014). Noise ~1-2 mm at 1 m growing with "
            "distance and with low amplitude, wiggling of a few mm, multipath in concave corners and "
            "flying pixels at edges: Sarbolandi, Lefloch & Kolb, CVIU 139, 2015; Fuersattel et al., "
            "2016. Only a ToF subset of direct effects is modelled (no phase-image simulation)."),
)

PRESETS: dict[str, SensorPreset] = {p.name: p for p in (KINECT_V1, STRUCTURE, REALSENSE_D435, KINECT_V2)}
"""All named presets."""


def get_preset(name: str) -> SensorPreset:
    """The preset called ``name``; ConfigError listing the known names otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown sensor preset {name!r}; known presets: {', '.join(sorted(PRESETS))}") from None
