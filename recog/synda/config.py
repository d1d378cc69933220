"""SynDA configuration (thesis chapter 5): the generator h_G, the augmentation A, the optimiser
numbers a preset is sized for, and the input domain. No torch here (configs are read by the CLI).

Two domains: ``rgb`` (the thesis' setting: colour images made from normal maps by A) and
``depth`` (a noisy depth patch -> clean synthetic depth and normals, the input of the triplet
recogniser). Presets (:func:`synda_preset`): ``gpu`` is the thesis' full size (encoder down to
1x1x512, distillation width 64); ``cpu`` is narrower (widths / 4 ... / 8) so that it trains on
2 CPU cores in <= 30 min (see :data:`PRESET_NOTES`).

Every numeric range is ``(low, high)`` and drawn uniformly unless its docstring says otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

from data_tools.errors import ConfigError

__all__ = ["Domain", "DOMAINS", "MODALITIES", "MODALITY_CHANNELS", "TEXTURES", "BACKGROUNDS", "BLURS",
           "GeneratorConfig", "AugmentConfig", "SyndaTrainConfig", "SyndaConfig", "PRESETS", "PRESET_NOTES",
           "synda_preset", "input_channels"]

Domain = Literal["rgb", "depth"]
DOMAINS = ("rgb", "depth")
MODALITIES = ("normals", "depth", "mask", "lightness")
"""The synthetic modalities h_G can decode (thesis section 5.3.1: normal, depth, semantic mask,
foreground lightness)."""
MODALITY_CHANNELS = {"normals": 3, "depth": 1, "mask": 1, "lightness": 1}
"""Channels of each modality's decoded map (the mask's is :attr:`GeneratorConfig.mask_classes`)."""
TEXTURES = ("perlin", "voronoi", "white", "none")
BACKGROUNDS = ("perlin", "voronoi", "white", "image")
BLURS = ("none", "gaussian", "box", "median")


def input_channels(domain: str) -> int:
    """Channels of h_G's input: 3 for ``rgb``, 1 for ``depth``."""
    return 3 if domain == "rgb" else 1


def _range(name: str, r, low: float | None = None, high: float | None = None) -> None:
    if not (isinstance(r, (tuple, list)) and len(r) == 2):
        raise ConfigError(f"synda option {name} must be a (low, high) pair, got {r!r}")
    a, b = float(r[0]), float(r[1])
    if a > b:
        raise ConfigError(f"synda option {name}: low {a} exceeds high {b}")
    if (low is not None and a < low) or (high is not None and b > high):
        raise ConfigError(f"synda option {name} must lie in [{low}, {high}], got {r!r}")


def _kinds(name: str, kinds, known) -> None:
    bad = [k for k in kinds if k not in known]
    if bad or not kinds:
        raise ConfigError(f"synda option {name}: unknown or no kinds {bad or list(kinds)}; "
                          f"choose from {', '.join(known)}")


@dataclass
class GeneratorConfig:
    """Architecture of h_G (thesis Fig. 5.4); the booleans are the ablation switches of Table 5.4."""

    size: int = 64
    """Input and output side in pixels; must be 2 ** len(widths) so that the code is 1x1."""
    widths: tuple[int, ...] = (64, 128, 256, 512, 512, 512)
    """Channels of the encoder blocks e1..e6 (each a 4x4 stride-2 conv halving the side)."""
    decoders: tuple[str, ...] = ("normals", "depth", "mask", "lightness")
    """Modalities with their own decoder (a subset of :data:`MODALITIES`)."""
    target: str = "normals"
    """The final output's modality: what the distillation module decodes (without distillation,
    the output of that modality's decoder)."""
    mask_classes: int = 1
    """Mask channels: 1 = binary foreground logits (binary cross-entropy); >= 2 = class logits
    (cross-entropy over background + object classes)."""
    distillation: bool = True
    """Distillation module h_R on top of the decoders (off: the target decoder's output is final)."""
    attention: bool = True
    """SAGAN self-attention on each re-encoded modality inside h_R (off: plain sum)."""
    distill_width: int = 64
    """Channels of h_R's re-encoding / decoding blocks (64 in Fig. 5.4)."""
    skips: bool = True
    """U-Net skip connections from each encoder block to its reciprocal decoder block."""
    triplet: bool = False
    """Expose the bottleneck code for a triplet loss (thesis Eq. 5.1, optional there)."""
    dropout: float = 0.5
    """Dropout rate in the first decoder blocks (0.5 in the thesis)."""
    dropout_blocks: int = 3
    """How many of the first decoder blocks have dropout (pix2pix's 3)."""
    init_std: float = 0.02
    """Std of the zero-mean Gaussian initial conv weights (thesis section 5.4.1)."""
    mask_prior: float = 0.1
    """Foreground share the mask head starts at: its bias is initialised to logit(mask_prior) (one
    channel) or to log(1 - prior) / log(prior / (C - 1)) for background / object classes (the prior
    initialisation of Lin et al. 2017). With a 0 bias (p = 0.5) the first steps drove every weight of
    the head negative on its ReLU features and the foreground never rose above p = 0.52 (the chairs
    fill ~10 % of a patch)."""

    def validate(self) -> "GeneratorConfig":
        if self.size < 4 or self.size != 2 ** len(self.widths):
            raise ConfigError(f"synda generator size {self.size} must be 2 ** len(widths) = {2 ** len(self.widths)}")
        if any(int(w) < 1 for w in self.widths) or self.distill_width < 1:
            raise ConfigError(f"synda generator widths must be >= 1, got {list(self.widths)} / {self.distill_width}")
        _kinds("generator.decoders", self.decoders, MODALITIES)
        if len(set(self.decoders)) != len(self.decoders):
            raise ConfigError(f"synda generator decoders repeat a modality: {list(self.decoders)}")
        if self.target not in MODALITIES or self.target == "mask":
            raise ConfigError(f"synda generator target {self.target!r} must be normals, depth or lightness")
        if not self.distillation and self.target not in self.decoders:
            raise ConfigError(f"synda generator without distillation needs a {self.target} decoder (the target)")
        if self.mask_classes < 1:
            raise ConfigError(f"synda generator mask_classes must be >= 1, got {self.mask_classes}")
        if not 0.0 <= self.dropout < 1.0 or not 0 <= self.dropout_blocks <= len(self.widths):
            raise ConfigError(f"synda generator dropout {self.dropout} must be in [0, 1) and dropout_blocks "
                              f"{self.dropout_blocks} in [0, {len(self.widths)}]")
        if not self.init_std > 0:
            raise ConfigError(f"synda generator init_std must be > 0, got {self.init_std}")
        if not 0.0 < self.mask_prior < 1.0:
            raise ConfigError(f"synda generator mask_prior must be in (0, 1), got {self.mask_prior}")
        return self

    def channels(self, modality: str) -> int:
        """Channels of ``modality``'s decoded map."""
        return self.mask_classes if modality == "mask" else MODALITY_CHANNELS[modality]


@dataclass
class AugmentConfig:
    """The online augmentation A (thesis section 5.3.2 and 5.4.1), drawn anew every iteration."""

    ambient: tuple[float, float] = (0.05, 0.3)
    """a ~ U(low, high)^3: RGB ambient coefficient of Algorithm 5.1."""
    diffuse: tuple[float, float] = (0.1, 0.8)
    """d ~ U(low, high)^3: RGB diffuse coefficient."""
    specular: tuple[float, float] = (0.0, 0.1)
    """s ~ U(low, high)^3: RGB specular coefficient."""
    hardness: tuple[float, float] = (0.9, 1.1)
    """s^ ~ U(low, high): specular hardness (exponent of N.H)."""
    light_angle_deg: tuple[float, float] = (0.0, 75.0)
    """Angle between the light direction and the optical axis (towards the camera side), degrees;
    the azimuth is uniform."""
    focal_px: float = 100.0
    """Focal length (pixels) of the camera that rendered the normal maps (view vectors of Alg. 5.1)."""
    textures: tuple[str, ...] = ("perlin", "voronoi", "white", "none")
    """Hue/saturation texture kinds, one drawn per sample (``none`` keeps the shading's colour)."""
    texture_values: tuple[float, float] = (0.0001, 0.9)
    """Range of the texture's hue (x 360 deg) and saturation values (thesis: U(0.0001, 0.9))."""
    texture_scale: tuple[float, float] = (0.5, 2.0)
    """How many texture periods the normals' (x, y) range [-1, 1] spans (texture indexing)."""
    backgrounds: tuple[str, ...] = ("perlin", "voronoi", "white", "image")
    """Background kinds, one drawn per sample (``image``: crops of :attr:`background_images`)."""
    background_images: str = "skimage"
    """Folder of images for ``image`` backgrounds, or ``skimage`` for the colour sample images
    that ship with scikit-image."""
    homogenise_background: bool = True
    """Shift the background's lightness so its mean equals the object's (thesis: "lightness maps
    from the shading step are used to homogenize the background brightness")."""
    occluders: tuple[int, int] = (0, 2)
    """Number of occluding polygons per sample, drawn uniformly from low..high inclusive."""
    vertices: tuple[int, int] = (3, 10)
    """n ~ U{low..high}: vertices of an occluding polygon (Algorithm 5.2)."""
    irregularity: tuple[float, float] = (0.0, 0.5)
    """epsilon ~ U(low, high): angular irregularity of Algorithm 5.2 (fraction of 2 pi / n)."""
    spikeyness: tuple[float, float] = (0.0, 0.5)
    """sigma ~ U(low, high): radius spread of Algorithm 5.2 (fraction of the mean radius)."""
    occluder_radius: tuple[float, float] = (0.15625, 0.25)
    """r_mu ~ U(low, high) x image side (thesis: U(10 px, m / 4) for m = 64)."""
    blurs: tuple[str, ...] = ("none", "gaussian", "box", "median")
    """Blur kinds, one drawn per sample."""
    blur_kernel: tuple[int, int] = (3, 5)
    """Odd blur kernel sides drawn from {low, low + 2, ..., high}."""
    blur_sigma: tuple[float, float] = (0.3, 1.5)
    """Gaussian blur sigma (pixels)."""
    depth_occluder_offset: tuple[float, float] = (0.05, 0.5)
    """Depth domain: an occluder is this much nearer than the object's nearest point (normalised
    depth units of the [-1, 1] patches)."""
    depth_background: tuple[float, float] = (-0.2, 1.0)
    """Depth domain: the range of the procedural background depth (normalised units; the patch
    convention puts the object's centre at 0 and nearer at negative values)."""

    depth_keep_background: float = 0.0
    """Depth domain: probability that a sample keeps its own background (the measured scene around the
    object: ground, clutter) instead of a procedural one; needs measured inputs (see
    :meth:`recog.synda.augment.Augmenter.apply`)."""

    def validate(self) -> "AugmentConfig":
        _range("augment.ambient", self.ambient, 0.0, 1.0)
        _range("augment.diffuse", self.diffuse, 0.0, 1.0)
        _range("augment.specular", self.specular, 0.0, 1.0)
        _range("augment.hardness", self.hardness, 0.0, None)
        _range("augment.light_angle_deg", self.light_angle_deg, 0.0, 89.9)
        _range("augment.texture_values", self.texture_values, 0.0, 1.0)
        _range("augment.texture_scale", self.texture_scale, 0.0, None)
        _range("augment.occluders", self.occluders, 0, 20)
        _range("augment.vertices", self.vertices, 3, 64)
        _range("augment.irregularity", self.irregularity, 0.0, 0.99)
        _range("augment.spikeyness", self.spikeyness, 0.0, 2.0)
        _range("augment.occluder_radius", self.occluder_radius, 0.0, 1.0)
        _range("augment.blur_kernel", self.blur_kernel, 1, 31)
        _range("augment.blur_sigma", self.blur_sigma, 0.0, None)
        _range("augment.depth_occluder_offset", self.depth_occluder_offset, 0.0, None)
        _range("augment.depth_background", self.depth_background, -1.0, 1.0)
        if not 0.0 <= self.depth_keep_background <= 1.0:
            raise ConfigError(f"synda option augment.depth_keep_background must be in [0, 1], "
                              f"got {self.depth_keep_background}")
        if not self.focal_px > 0:
            raise ConfigError(f"synda option augment.focal_px must be > 0, got {self.focal_px}")
        if self.blur_kernel[0] % 2 == 0 or self.blur_kernel[1] % 2 == 0:
            raise ConfigError(f"synda option augment.blur_kernel must hold odd sides, got {self.blur_kernel!r}")
        _kinds("augment.textures", self.textures, TEXTURES)
        _kinds("augment.backgrounds", self.backgrounds, BACKGROUNDS)
        _kinds("augment.blurs", self.blurs, BLURS)
        if "image" in self.backgrounds and not self.background_images:
            raise ConfigError("synda option augment.backgrounds has 'image' but background_images is empty")
        return self


@dataclass
class SyndaTrainConfig:
    """The optimiser numbers a preset is sized for (the loop is the project's shared one)."""

    iterations: int = 20000
    """Optimiser steps."""
    batch: int = 64
    """Samples per step (each augmented anew)."""
    lr: float = 2e-4
    """Adam learning rate (thesis: 2e-4)."""
    beta1: float = 0.5
    """Adam beta1 (thesis: 0.5)."""
    triplet_weight: float = 1.0
    """Weight of the bottleneck triplet loss (used when ``generator.triplet``)."""
    seed: int = 0
    """Seed of the initial weights and of the augmentation draws."""
    device: str = "cpu"
    """torch device."""
    descriptor_weight: float = 0.0
    """Weight of the descriptor (feature-matching) loss, a deviation from the thesis: the squared L2 (or L1,
    :attr:`descriptor_distance`) between a frozen recogniser's descriptors of h_G's output and of the clean
    target patch, mean over the batch. 0 = off (the shipped generator's recipe)."""
    descriptor_recogniser: str = ""
    """The frozen (clean-trained) recogniser folder whose network gives the descriptors; needed when
    :attr:`descriptor_weight` > 0; its patches must be the generator's (size and crop)."""
    descriptor_distance: Literal["l2", "l1"] = "l2"
    """Distance of the descriptor loss: ``l2`` = squared Euclidean, ``l1`` = sum of absolute differences."""
    object_weight: float = 0.0
    """Weight of an extra L1 of the final output on the object's pixels (mean over the mask), on top of the
    output's L1 over the whole patch, which the background dominates. 0 = off."""

    def validate(self) -> "SyndaTrainConfig":
        if self.iterations < 1 or self.batch < 1:
            raise ConfigError(f"synda train iterations and batch must be >= 1, got {self.iterations}, {self.batch}")
        if not self.lr > 0 or not 0 <= self.beta1 < 1 or self.triplet_weight < 0:
            raise ConfigError(f"synda train lr must be > 0, beta1 in [0, 1), triplet_weight >= 0; got "
                              f"{self.lr}, {self.beta1}, {self.triplet_weight}")
        if not (self.descriptor_weight >= 0 and self.object_weight >= 0):
            raise ConfigError(f"synda train descriptor_weight and object_weight must be >= 0, got "
                              f"{self.descriptor_weight}, {self.object_weight}")
        if self.descriptor_distance not in ("l2", "l1"):
            raise ConfigError(f"synda train descriptor_distance {self.descriptor_distance!r}: choose l2 or l1")
        if self.descriptor_weight > 0 and not self.descriptor_recogniser:
            raise ConfigError("synda train descriptor_weight > 0 needs descriptor_recogniser (a recogniser folder)")
        return self


@dataclass
class SyndaConfig:
    """Everything that defines a SynDA generator and how it is trained (saved with it)."""

    domain: Domain = "rgb"
    """Input domain: ``rgb`` colour images or ``depth`` measured depth patches."""
    generator: GeneratorConfig = field(default_factory=GeneratorConfig)
    """Architecture of h_G."""
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    """The augmentation A."""
    train: SyndaTrainConfig = field(default_factory=SyndaTrainConfig)
    """Optimiser numbers."""

    def validate(self) -> "SyndaConfig":
        if self.domain not in DOMAINS:
            raise ConfigError(f"synda domain {self.domain!r}: choose rgb or depth")
        self.generator.validate()
        self.augment.validate()
        self.train.validate()
        if self.domain == "depth" and "lightness" in self.generator.decoders + (self.generator.target,):
            raise ConfigError("synda depth domain has no lightness (it comes from the colour shading): "
                              "drop the lightness decoder")
        if (self.train.descriptor_weight > 0 or self.train.object_weight > 0) and self.generator.target != "depth":
            raise ConfigError(f"synda descriptor / object losses need the final output to be depth (the recogniser's "
                              f"input), not {self.generator.target}")
        return self

    @property
    def in_channels(self) -> int:
        """Channels of h_G's input."""
        return input_channels(self.domain)


PRESETS = ("cpu", "gpu")
PRESET_NOTES = {
    "gpu": "the thesis' size: encoder 64-128-256-512-512-512 to 1x1x512, distillation width 64, "
           "batch 64, 20000 steps",
    "cpu": "encoder 16-32-64-128-128-128, distillation width 16, batch 16, 3000 steps: sized for "
           "<= 30 min on the shared 2-core machine with one torch thread (augmentation + step measured "
           "0.48 s rgb, 0.35 s depth: 24 / 18 min; see docs/synda.md)",
}


def synda_preset(name: str, domain: str = "rgb") -> SyndaConfig:
    """The ``cpu`` or ``gpu`` preset for ``domain`` (validated). The depth domain decodes
    normals, depth and mask with depth as the final output and keeps the measured background in
    half of the samples; rgb decodes all four with normals
    as the final output (the thesis)."""
    if name not in PRESETS:
        raise ConfigError(f"unknown synda preset {name!r}; choose one of {', '.join(PRESETS)}")
    if domain not in DOMAINS:
        raise ConfigError(f"synda domain {domain!r}: choose rgb or depth")
    gen = GeneratorConfig()
    if domain == "depth":
        gen = replace(gen, decoders=("normals", "depth", "mask"), target="depth")
    train = SyndaTrainConfig()
    if name == "cpu":
        gen = replace(gen, widths=(16, 32, 64, 128, 128, 128), distill_width=16)
        train = replace(train, iterations=3000, batch=16)
    else:
        train = replace(train, device="cuda")
    aug = AugmentConfig(depth_keep_background=0.5) if domain == "depth" else AugmentConfig()
    return SyndaConfig(domain=domain, generator=gen, augment=aug, train=train).validate()
