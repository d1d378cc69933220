"""The effect registry: every physical effect of a depth sensor is a small registered class.

An effect has

* a unique ``name`` (the key used in JSON models and on the command line),
* a typed ``Params`` dataclass: every field is a :func:`param` with its unit and plausible
  bounds (or choices), and a docstring under it; values outside are a one-line ConfigError;
  :meth:`Effect.param_specs` lists them (``realgap sensor effects`` prints that table),
* ``FITTABLE``: the parameters a sensor lab may fit, with their (low, high) search range (the
  plausible bounds of a fittable parameter unless :func:`param` gives wider ones),
* ``sample(rng, state) -> draw``: the random draw of one frame (unit noise fields, uniform
  variates...), independent of the parameters wherever possible so that a fit sees common
  random numbers,
* ``apply(state, draw)``: deterministic given the state and the draw; it reads and writes the
  per-frame :class:`~synth.sensor.state.SensorState` (effects pass arrays to later effects only
  through its published products, never through each other's attributes);
* what the sensor lab needs to know about it, in the same file: ``SIGNATURE`` (how to see it
  in measured data), ``evidence(ctx, params, gain)`` (a sentence from the data),
  ``fit_start(measured, config, frames)`` (data-driven starting values), ``CONFIG_PARAMETERS``
  (fittable numbers that live outside ``Params``), ``sensor_types``;
* what the contract tests need: ``IDENTITY_PARAMS`` (zero strength), ``KEEPS_INVALID``,
  ``REQUIRED_IN_PIPELINE``.

Adding an effect touches its file, its preset values (``synth/sensor/presets.py``, only when a
preset uses it) and its tests; ``tests/test_effect_contract.py`` runs on it automatically.

Effects are ordered by ``stage`` (geometry < projection < optics < capture < matching < depth
< post-processing), so a model can list them in any order. Modules in
``synth/sensor/effects/`` (and folders named in ``$REALGAP_EFFECT_PATH``) are discovered lazily
(on first lookup, never at import time): adding an effect is one new file with a
``@register_effect`` class (``tests/test_effect_plugin.py`` adds one from outside the package and
runs the contract suite, a fit and a diagnosis on it).
"""
from __future__ import annotations

import dataclasses
import functools
import importlib
import os
import pkgutil
import zlib
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from data_tools.errors import ConfigError

# Stage numbers (effects run in increasing stage order; ties keep the model's order).
STAGE_GEOMETRY = 10
"""Changes what each pixel sees (rolling shutter re-renders rows)."""
STAGE_PROJECTION = 20
"""Computes the radiance of the projected pattern (physical pipeline)."""
STAGE_LIGHT = 25
"""Adds further light to the radiance (ambient IR)."""
STAGE_OPTICS = 30
"""Optical transforms of the radiance image before the sensor (motion blur, lens distortion)."""
STAGE_CAPTURE = 40
"""Sensor: speckle, blur, shot/read noise, exposure, saturation, ADC."""
STAGE_MATCHING = 50
"""Image -> disparity -> depth (block matching)."""
STAGE_DROPOUT = 60
"""Direct (analytic) effects that remove pixels."""
STAGE_DEPTH = 70
"""Direct effects that change depth values (noise, bias, ToF errors)."""
STAGE_QUANTIZE = 80
"""Quantisation of the disparity / depth code."""
STAGE_WARP = 85
"""Direct geometric warps of the depth image (lens distortion on depth)."""
STAGE_POST = 90
"""Device post-processing (range limits, hole filling)."""


def param(default: Any, unit: str, low: float | None = None, high: float | None = None, *,
          choices: tuple[str, ...] | None = None):
    """A ``Params`` field with its unit and plausible range: ``unit`` is an SI-style symbol (``m``,
    ``px``, ``deg``, ``rad``, ``s``, ``Hz``, ``1/m``, ``e-``; ``1`` for dimensionless numbers, ``""``
    for switches and names); ``low``/``high`` bound the values a model may hold (None: the
    ``FITTABLE`` range of the parameter); ``choices`` lists the allowed strings."""
    if (low is None) != (high is None):
        raise TypeError("param: give both low and high, or neither")
    return dataclasses.field(default=default, metadata={
        "unit": unit, "bounds": None if low is None else (low, high),
        "choices": None if choices is None else tuple(choices)})


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of an effect as a user sees it (``realgap sensor effects``)."""

    name: str
    """Field name in ``Params`` (and in model JSON)."""
    type: str
    """``float``, ``int``, ``bool``, ``str`` or ``tuple``."""
    default: Any
    """Value when a model does not set it (a preset may set another: ``effect_params``)."""
    unit: str | None
    """Unit symbol (see :func:`param`); None when the effect does not declare it."""
    bounds: tuple[float, float] | None
    """Plausible (allowed) range; None: any value of the type."""
    choices: tuple[str, ...] | None
    """Allowed strings; None: any."""
    fit_range: tuple[float, float] | None
    """The sensor lab's search range when the parameter is ``FITTABLE``, else None."""
    doc: str
    """The docstring under the field."""


@dataclass(frozen=True)
class Signature:
    """How the sensor lab recognises an effect in measured data (its diagnosis figure)."""

    title: str
    """The pattern in a few words."""
    explanation: str
    """What to look for in the figure (one or two sentences)."""
    panels: tuple[tuple[str, str], ...] = ()
    """``plot == "binned"``: (lab feature, statistic) per panel, statistic one of ``bias``, ``std``,
    ``invalid_fraction`` (measured, current model and model with the effect, binned by the feature)."""
    plot: str = "binned"
    """The lab's figure kind: ``binned``, ``shadow_sides`` (holes on either side of depth edges),
    ``disparity_levels`` (depth-level spacing vs distance) or ``radial_error_map``."""


@dataclass(frozen=True)
class ConfigParameter:
    """A fittable number of an effect that is not one of its numeric ``Params`` fields (it lives
    elsewhere in the sensor config, e.g. the preset's reference depth). Declared by the effect in
    ``CONFIG_PARAMETERS``; the sensor lab fits it like a FITTABLE parameter (key ``effect.name``)."""

    low: float
    """Lower bound (the parameter's units)."""
    high: float
    """Upper bound."""
    get: Callable
    """get(config, effect) -> current value (float)."""
    set: Callable
    """set(config, effect, value) -> a new SensorConfig with the value (every other field kept)."""
    doc: str
    """What the number is and why it lives outside the effect's Params."""
    applies: Callable | None = None
    """applies(config) -> False when the parameter has no effect for this sensor (then it is not
    fitted); None = always."""
    unit: str | None = None
    """Unit symbol (as for :func:`param`)."""


class Effect(ABC):
    """Base class of all sensor effects. Subclasses set the class attributes and ``apply``."""

    name: ClassVar[str] = ""
    """Registry key."""
    Params: ClassVar[type] = None  # type: ignore[assignment]
    """Dataclass of typed parameters (defaults = generic defaults; presets override)."""
    FITTABLE: ClassVar[dict[str, tuple[float, float]]] = {}
    """Parameters a sensor lab may fit, with (low, high) bounds in the parameter's units."""
    stage: ClassVar[int] = STAGE_DEPTH
    """Where the effect runs (see the STAGE_* constants)."""
    physical: ClassVar[bool] = False
    """True for the stages of the physical pipeline (projection, capture, matching)."""
    in_reference: ClassVar[bool] = False
    """True when the effect also shapes the stored reference image (noise-free draw)."""
    sensor_types: ClassVar[tuple[str, ...] | None] = None
    """Sensor types (``SensorPreset.type``) whose physics the effect models; None = every type.
    The sensor lab does not try an effect on a sensor of another type."""
    IDENTITY_PARAMS: ClassVar[dict | None] = None
    """Parameter values at which the effect does nothing (zero strength), or None when there are
    none (a stage of the physical pipeline). The contract tests check it."""
    KEEPS_INVALID: ClassVar[bool] = True
    """False when the effect's purpose is to produce values where there were none (hole filling,
    depth recomputed from images, a re-rendered or warped view); True = pixels invalid before
    the effect stay invalid (checked by the contract tests)."""
    REQUIRED_IN_PIPELINE: ClassVar[bool] = False
    """True for the stages the physical pipeline cannot run without (projection, capture,
    matching): disabling one is not an identity."""
    SIGNATURE: ClassVar[Signature | None] = None
    """How the sensor lab shows the effect in measured data (None: a generic distance breakdown)."""
    CONFIG_PARAMETERS: ClassVar[dict[str, ConfigParameter]] = {}
    """Fittable numbers of the effect that are not numeric Params fields (see ConfigParameter)."""
    FITTABLE_FOR: ClassVar[dict[str, tuple[str, ...]]] = {}
    """FITTABLE parameters that the lab fits only for some sensor types (``SensorPreset.type``):
    a parameter whose physics another sensor does not have stays at its value there, so a fit
    cannot use it to explain what another effect should."""
    PLANE_ONLY: ClassVar[tuple[str, ...]] = ()
    """FITTABLE parameters that the lab fits only on a planar reference (where the objective's
    noise-vs-distance term sees them, ``synth.lab.calibration``): elsewhere the gap's pooled
    distributions cannot tell them from the other noise terms, so they stay at their value."""
    START_PRIORITY: ClassVar[int] = 0
    """Order of the closed-form starts (lower first). The starts of an effect with a negative priority
    are applied to the ``config`` that the later effects' ``fit_start`` see: a pixel re-mapping such
    as the lens warp is estimated first, so that a depth-bias regression does not explain it with a
    radial term."""
    START_ONLY_PARAMS: ClassVar[tuple[str, ...]] = ()
    """Parameters that ``fit_start`` chooses or measures from the data and the search keeps fixed: a
    choice (str, e.g. a window shape) or a number outside FITTABLE (float, e.g. a lens's small
    tangential terms, measured only when the data show them clearly)."""
    FILE_PARAMS: ClassVar[tuple[str, ...]] = ()
    """String parameters that name a data file of the model (e.g. a learned ``.npy`` map): a
    relative path is relative to the model JSON's folder when the model is loaded, and saving a
    model copies the file beside the JSON (:meth:`SensorConfig.save`). ``fit_start`` may return a
    value for them (the file it estimated)."""
    DEPTH_LIMIT_PARAMS: ClassVar[dict[str, str]] = {}
    """FITTABLE parameters that cut the reported depth range: name -> ``"min"`` or ``"max"``
    (0 = the preset's attribute of the same name). A fit bounds them by the measured valid depths
    (:mod:`synth.lab.guards`), so it can never throw the measurement away."""
    SIGNAL_HOLES: ClassVar[bool] = False
    """True for an effect that removes pixels where little signal returns (far, dark or oblique
    surfaces): the far holes that a too-near maximum range (``DEPTH_LIMIT_PARAMS``) explains as well.
    A model refitted without the effect may have pulled its range in to explain them, so the lab
    re-starts the model's depth limits from their closed-form start with such a candidate
    (:func:`synth.lab.diagnose.fit_candidate`)."""
    FRAME_EXPOSURE_PARAM: ClassVar[str | None] = None
    """Name of the parameter that is the frame's exposure time in seconds, for the one effect that
    models the exposure (``motion_blur``); the simulator copies it into ``state.frame.exposure_s``."""
    DRAW_FROM_SHAPE: ClassVar[bool] = False
    """True when ``sample`` reads nothing of the state but ``shape``, ``preset``, ``intr``,
    ``physical`` and ``is_reference``: the simulator may then draw it in a background thread
    while earlier stages run (same generator, same values; numpy's generators release the GIL
    while filling arrays). Leave False when ``sample`` looks at the scene."""

    def __init__(self, params: Any = None, enabled: bool = True):
        if params is None:
            params = self.Params()
        elif isinstance(params, dict):
            params = params_from_dict(self.Params, params, self.name)
        elif not isinstance(params, self.Params):
            raise ConfigError(f"effect {self.name!r}: params must be a {self.Params.__name__} or a dict")
        self.params = params
        self.enabled = bool(enabled)
        self.validate()

    # -- overridable -----------------------------------------------------------------------
    def validate(self) -> None:
        """Raise ConfigError for impossible parameter values (default: every parameter within its
        declared bounds / choices, see :meth:`param_specs`; overrides add checks and call this)."""
        for spec in self.param_specs():
            v = getattr(self.params, spec.name)
            if spec.choices is not None and v not in spec.choices:
                raise ConfigError(f"effect {self.name!r}: {spec.name}={v!r} is not one of "
                                  f"{', '.join(repr(c) for c in spec.choices)}")
            if spec.bounds is not None and not isinstance(v, (str, tuple, list)):
                lo, hi = spec.bounds
                if not (lo <= float(v) <= hi):
                    raise ConfigError(f"effect {self.name!r}: {spec.name}={v} is outside its bounds [{lo}, {hi}]"
                                      + (f" {spec.unit}" if spec.unit not in (None, "", "1") else ""))

    @classmethod
    def param_specs(cls) -> list[ParamSpec]:
        """Every parameter with its type, default, unit, bounds, choices, fit range and docstring
        (read once per class: the docstrings come from the source, and ``validate`` runs on every
        construction)."""
        return list(_param_specs(cls))

    def stage_for(self, physical_model: bool) -> int:
        """Stage in a model that does (``physical_model``) or does not run the physical pipeline."""
        return self.stage

    def sample(self, rng: np.random.Generator, state) -> Any:
        """Random draw of one frame (default: nothing random)."""
        return None

    def null_draw(self, state) -> Any:
        """The noise-free draw used for the reference image (default: same as no randomness)."""
        return None

    @abstractmethod
    def apply(self, state, draw: Any) -> None:
        """Deterministically apply the effect to ``state`` given ``draw``."""

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None) -> str | None:
        """One sentence of evidence for the effect in measured data, for the sensor lab's diagnosis:
        ``ctx`` is a :class:`synth.lab.evidence.EvidenceContext` (measured and current-model depth,
        pooled per-pixel features and the sentence helpers), ``params`` the fitted
        ``{"effect.param": value}``, ``gain`` the fraction of the gap the effect removes. The
        sentence claims the effect's signature only when its numbers show it. None (the default):
        the lab names the comparison feature the effect improves most."""
        return None

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """Starting values of fitted parameters estimated directly from measured data
        (``{"effect.param": value}``), for parameters whose gap landscape is too rugged for a
        coarse grid; ``measured`` is a :class:`synth.lab.measured.MeasuredSequence`, ``frames``
        the positions of the fit's frames; ``config`` holds the starts of the effects of lower
        :attr:`START_PRIORITY`. Default: none."""
        return {}

    @classmethod
    def plausible_bounds(cls, preset) -> dict[str, tuple[float, float]]:
        """Per-device narrowing of :attr:`FITTABLE`: ``{param: (low, high)}`` values a sensor of
        ``preset`` can physically have (e.g. no Kinect reports nothing nearer than 5 m). The lab
        searches the intersection with FITTABLE, so a fit cannot move an effect to an implausible
        value to explain what another effect should, and a value ending on such a limit is
        reported as at bound. Default: FITTABLE as it is."""
        return {}

    def search_bounds(self, preset) -> dict[str, tuple[float, float]]:
        """The narrowing the lab's search uses for this effect as it stands: :meth:`plausible_bounds`,
        and where ``fit_start`` measured a parameter exactly from the data (recorded in one of its
        :attr:`START_ONLY_PARAMS`), a narrow window around that value (e.g. a disparity step read
        off the measured lattice). Default: :meth:`plausible_bounds`."""
        return self.plausible_bounds(preset)

    # -- helpers ---------------------------------------------------------------------------
    def to_json(self) -> dict:
        return {"name": self.name, "enabled": self.enabled, "params": params_to_dict(self.params)}

    def replace(self, **changes) -> "Effect":
        """A copy with some parameters changed (validated)."""
        return type(self)(dataclasses.replace(self.params, **changes), self.enabled)

    def fittable(self) -> dict[str, tuple[float, float, float]]:
        """{param: (value, low, high)} for the fittable parameters."""
        return {k: (float(getattr(self.params, k)), lo, hi) for k, (lo, hi) in self.FITTABLE.items()}

    def rng(self, seed: int) -> np.random.Generator:
        """Per-effect generator: depends on the frame seed and the effect name only, so switching
        another effect on or off never changes this effect's draw."""
        return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(self.name.encode())])

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r}, enabled={self.enabled})"


@functools.cache
def _param_specs(cls: type) -> tuple[ParamSpec, ...]:
    from data_tools.config import field_docs
    if cls.Params is None:
        return ()
    docs = field_docs(cls.Params)
    out = []
    for f in dataclasses.fields(cls.Params):
        meta = f.metadata or {}
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        fit = cls.FITTABLE.get(f.name)
        bounds = meta.get("bounds") or (tuple(fit) if fit is not None else None)
        out.append(ParamSpec(f.name, type(default).__name__, default, meta.get("unit"), bounds,
                             meta.get("choices"), tuple(fit) if fit is not None else None,
                             docs.get(f.name, "")))
    return tuple(out)


def params_to_dict(params) -> dict:
    d = dataclasses.asdict(params)
    for k, v in d.items():
        if isinstance(v, tuple):
            d[k] = list(v)
    return d


def params_from_dict(cls, d: dict, effect_name: str = ""):
    """Build a Params dataclass from a dict (:func:`data_tools.config.config_from_dict`): missing
    keys keep their defaults; unknown keys and wrong types are one-line ConfigErrors naming the
    effect and the parameter."""
    from data_tools.config import config_from_dict
    return config_from_dict(cls, d, f"effect {effect_name!r} params", item="parameter", strict=True)


_REGISTRY: dict[str, type[Effect]] = {}
_DISCOVERED = False


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator: add an effect to the registry (names must be unique)."""
    if not cls.name:
        raise TypeError(f"{cls.__name__} has no name")
    if cls.Params is None or not dataclasses.is_dataclass(cls.Params):
        raise TypeError(f"{cls.__name__}.Params must be a dataclass")
    fields = {f.name for f in dataclasses.fields(cls.Params)}
    for k in cls.FITTABLE:
        if k not in fields:
            raise TypeError(f"{cls.__name__}.FITTABLE names unknown parameter {k!r}")
    for k in cls.FITTABLE_FOR:
        if k not in cls.FITTABLE:
            raise TypeError(f"{cls.__name__}.FITTABLE_FOR names {k!r}, which is not FITTABLE")
    for k in cls.PLANE_ONLY:
        if k not in cls.FITTABLE:
            raise TypeError(f"{cls.__name__}.PLANE_ONLY names {k!r}, which is not FITTABLE")
    for k in (cls.IDENTITY_PARAMS or {}):
        if k not in fields:
            raise TypeError(f"{cls.__name__}.IDENTITY_PARAMS names unknown parameter {k!r}")
    for k, side in cls.DEPTH_LIMIT_PARAMS.items():
        if k not in cls.FITTABLE or side not in ("min", "max"):
            raise TypeError(f"{cls.__name__}.DEPTH_LIMIT_PARAMS: {k!r} -> {side!r} (a FITTABLE name -> 'min'/'max')")
    for k in cls.FILE_PARAMS:
        if k not in fields or not isinstance(getattr(cls.Params(), k), str):
            raise TypeError(f"{cls.__name__}.FILE_PARAMS: {k!r} is not a str parameter")
    for k in cls.START_ONLY_PARAMS:
        if k not in fields or not isinstance(getattr(cls.Params(), k), (str, float)) or k in cls.FITTABLE:
            raise TypeError(f"{cls.__name__}.START_ONLY_PARAMS: {k!r} is not a str or float parameter outside FITTABLE")
    if cls.SIGNATURE is not None and not isinstance(cls.SIGNATURE, Signature):
        raise TypeError(f"{cls.__name__}.SIGNATURE must be a Signature")
    for k in cls.CONFIG_PARAMETERS:
        if k in fields:
            raise TypeError(f"{cls.__name__}.CONFIG_PARAMETERS: {k!r} is a Params field (declare it in FITTABLE)")
    other = _REGISTRY.get(cls.name)
    if other is not None and other.__qualname__ != cls.__qualname__:
        raise TypeError(f"effect name {cls.name!r} registered twice ({other.__qualname__}, {cls.__qualname__})")
    _REGISTRY[cls.name] = cls
    return cls


EFFECT_PATH_ENV = "REALGAP_EFFECT_PATH"
"""Environment variable: folders (``os.pathsep``-separated) whose ``*.py`` files are effect
modules too, loaded with the built-in ones: an effect of your own is one file there, no change to
realgap (worker processes inherit the variable)."""


def discover_effects() -> None:
    """Import every module of ``synth.sensor.effects`` and of the folders in
    ``$REALGAP_EFFECT_PATH`` (once) so their classes register."""
    global _DISCOVERED
    if _DISCOVERED:
        return
    from synth.sensor import effects as pkg
    for mod in pkgutil.iter_modules(pkg.__path__):
        if not mod.name.startswith("_"):
            importlib.import_module(f"{pkg.__name__}.{mod.name}")
    _DISCOVERED = True
    for folder in filter(None, os.environ.get(EFFECT_PATH_ENV, "").split(os.pathsep)):
        _load_effect_folder(Path(folder))


def _load_effect_folder(folder: Path) -> None:
    import importlib.util
    import sys
    if not folder.is_dir():
        raise ConfigError(f"{folder}: not a folder (named in ${EFFECT_PATH_ENV})")
    for path in sorted(folder.glob("*.py")):
        if path.name.startswith("_"):
            continue
        name = f"realgap_user_effects.{path.stem}"
        if name in sys.modules:
            continue
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        try:
            spec.loader.exec_module(module)
        except Exception as e:  # a user's file: report it as one line naming the file
            del sys.modules[name]
            raise ConfigError(f"{path}: cannot load this effect module ({type(e).__name__}: {e})") from None


def effect_names() -> list[str]:
    """Sorted names of all registered effects."""
    discover_effects()
    return sorted(_REGISTRY)


def effect_class(name: str) -> type[Effect]:
    """The effect class registered as ``name``; ConfigError listing the known names otherwise."""
    discover_effects()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ConfigError(f"unknown sensor effect {name!r}; known effects: {', '.join(sorted(_REGISTRY))}") from None


def make_effect(spec, defaults: dict | None = None) -> Effect:
    """An Effect from a name, a ``{"name", "enabled", "params"}`` dict, or an Effect instance.

    ``defaults`` (preset-specific parameter values) are applied under the explicit params.
    """
    if isinstance(spec, Effect):
        return spec
    if isinstance(spec, str):
        name, params, enabled = spec, {}, True
    elif isinstance(spec, dict):
        if "name" not in spec:
            raise ConfigError(f"effect entry {spec!r} has no 'name'")
        name, params, enabled = spec["name"], spec.get("params") or {}, spec.get("enabled", True)
        extra = set(spec) - {"name", "params", "enabled"}
        if extra:
            raise ConfigError(f"effect entry {name!r}: unknown key(s) {', '.join(sorted(extra))}")
    elif isinstance(spec, (tuple, list)) and len(spec) == 2:
        name, params, enabled = spec[0], dict(spec[1] or {}), True
    else:
        raise ConfigError(f"cannot build a sensor effect from {spec!r}")
    cls = effect_class(name)
    merged = dict(defaults or {})
    merged.update(params)
    return cls(params_from_dict(cls.Params, merged, name), enabled)
