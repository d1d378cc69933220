"""A sensor model: a preset plus an ordered list of effects (:class:`SensorConfig`), and the camera
motion it is meant for (:class:`MotionLimits`). ``SensorConfig.to_json()`` is the model file of
the lab and the ``sensor_config.json`` written next to every simulated sequence.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError
from data_tools.geometry import rotation_angle_rad
from synth.sensor.presets import SensorPreset, get_preset
from synth.sensor.registry import Effect, effect_class, make_effect

__all__ = ["MotionLimits", "SensorConfig", "expand_pipelines", "PIPELINE_WORDS"]

# ------------------------------------------------------------------------------------------
# Configuration
# ------------------------------------------------------------------------------------------

@dataclass
class MotionLimits:
    """Plausibility limits of the camera motion between ``prev_pose`` and ``pose`` (one frame
    period apart) for the motion effects (rolling shutter, motion blur).

    A trajectory sampled with few frames can jump metres between consecutive poses; read as
    the motion during one frame period that is an absurd velocity, and the motion effects
    (which interpolate at constant velocity between the two poses) would then dominate the
    frame. Above either limit the previous pose is treated as a cut: the frame is simulated as
    if the camera were static (motion effects inactive) and SimResult.warnings says so.
    Defaults: a fast hand-held camera or mobile robot (walking pace ~1.5 m/s; hand-held
    rotations in TUM RGB-D fr1 peak around 1-2 rad/s).
    """

    max_speed_m_s: float = 3.0
    """Largest plausible camera speed, metres/second (0 = no limit)."""
    max_angular_speed_rad_s: float = 4.0
    """Largest plausible camera rotation rate, radians/second (0 = no limit)."""

    def __post_init__(self) -> None:
        for k in ("max_speed_m_s", "max_angular_speed_rad_s"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"motion limits: {k} must be a number >= 0 (0 = no limit), got {v!r}")
            setattr(self, k, float(v))

    def speeds(self, pose_c2w: np.ndarray, prev_pose_c2w: np.ndarray, frame_dt_s: float) -> tuple[float, float]:
        """(speed m/s, angular speed rad/s) implied by the two poses one frame period apart."""
        T1, T0 = np.asarray(pose_c2w, np.float64), np.asarray(prev_pose_c2w, np.float64)
        dist = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        ang = float(rotation_angle_rad(T1[:3, :3] @ T0[:3, :3].T))
        return dist / frame_dt_s, ang / frame_dt_s

    def violation(self, pose_c2w: np.ndarray, prev_pose_c2w: np.ndarray, frame_dt_s: float) -> str | None:
        """A one-line reason when the motion exceeds a limit, else None."""
        v, w = self.speeds(pose_c2w, prev_pose_c2w, frame_dt_s)
        if self.max_speed_m_s and v > self.max_speed_m_s:
            return (f"camera moved {v * frame_dt_s:.3g} m in one frame period ({v:.3g} m/s > max_speed_m_s "
                    f"{self.max_speed_m_s:g}): previous pose treated as a cut, motion effects skipped")
        if self.max_angular_speed_rad_s and w > self.max_angular_speed_rad_s:
            return (f"camera turned {math.degrees(w * frame_dt_s):.3g} deg in one frame period ({w:.3g} rad/s > "
                    f"max_angular_speed_rad_s {self.max_angular_speed_rad_s:g}): previous pose treated as a cut, "
                    f"motion effects skipped")
        return None



PIPELINE_WORDS = ("physical", "direct")
"""Words that stand for a preset's whole pipeline in an effect list (``SensorPreset.<word>_effects``)."""


def expand_pipelines(effects, preset) -> list:
    """``effects`` (names / dicts / Effects) with each pipeline word (``physical``, ``direct``)
    replaced by the preset's effects of that pipeline, in place; an effect named again after its
    pipeline brought it is dropped (``physical,range_limits`` = the physical pipeline, whose
    range limits it already has), so a pipeline plus extra effects is one comma list."""
    out, piped = [], set()
    for spec in effects:
        if isinstance(spec, str) and spec.strip().lower() in PIPELINE_WORDS:
            for n in getattr(preset, f"{spec.strip().lower()}_effects"):
                if n not in piped:
                    out.append(n)
                    piped.add(n)
        elif not (isinstance(spec, str) and spec in piped):
            out.append(spec)      # a name listed twice by hand still fails in SensorConfig.build
    return out

@dataclass
class SensorConfig:
    """A sensor model: the device preset and the ordered effects (each with its parameters)."""

    preset: SensorPreset
    """Device geometry, pattern, matcher and range."""
    effects: list[Effect] = field(default_factory=list)
    """Effects in model order (they run sorted by stage; disabled ones are kept but skipped)."""
    motion: MotionLimits = field(default_factory=MotionLimits)
    """Plausibility limits of the motion between ``prev_pose`` and ``pose`` (above them the
    previous pose is a cut: no motion effects for that frame, a warning)."""

    @classmethod
    def build(cls, preset: str | SensorPreset = "kinect_v1", effects=None,
              motion: MotionLimits | None = None) -> "SensorConfig":
        """Config from a preset and ``effects``: None/"physical" (the preset's physical
        pipeline), "direct" (its analytic model), or a list (or comma string) of names / dicts /
        Effects in which the pipeline words stand for their effects (:func:`expand_pipelines`);
        ``motion``: the motion plausibility limits (default :class:`MotionLimits`)."""
        pre = get_preset(preset) if isinstance(preset, str) else preset
        if not isinstance(pre, SensorPreset):
            raise ConfigError(f"expected a sensor preset name or SensorPreset, got {type(preset).__name__}")
        if effects is None:
            effects = "physical"
        if isinstance(effects, str):
            effects = [e.strip() for e in effects.split(",") if e.strip()]
        names = expand_pipelines(effects, pre)
        built = []
        for spec in names:
            name = spec.name if isinstance(spec, Effect) else (spec["name"] if isinstance(spec, dict) else
                                                                (spec[0] if isinstance(spec, (tuple, list)) else spec))
            built.append(make_effect(spec, pre.effect_params.get(name)))
        seen = set()
        for e in built:
            if e.name in seen:
                raise ConfigError(f"sensor model lists effect {e.name!r} twice")
            seen.add(e.name)
        return cls(pre, built, motion if motion is not None else MotionLimits())

    def to_json(self, base_dir: str | os.PathLike | None = None) -> dict:
        """The model as JSON. ``base_dir``: the folder the JSON is written to; data files of the
        effects (``Effect.FILE_PARAMS``, e.g. a learned map) are then copied there and referenced by
        their file name, so the folder is self-contained. Without it the paths are kept as they are."""
        effects = [e.to_json() for e in self.effects]
        if base_dir is not None:
            for e, d in zip(self.effects, effects):
                for k in e.FILE_PARAMS:
                    if d["params"].get(k):
                        d["params"][k] = _copy_beside(Path(d["params"][k]), Path(base_dir))
        return {"preset": self.preset.to_json(), "effects": effects,
                "motion": {"max_speed_m_s": self.motion.max_speed_m_s,
                           "max_angular_speed_rad_s": self.motion.max_angular_speed_rad_s}}

    @classmethod
    def from_json(cls, d: dict, base_dir: str | os.PathLike | None = None) -> "SensorConfig":
        """The model of a JSON object; ``base_dir``: the JSON file's folder, against which relative
        data-file parameters (``Effect.FILE_PARAMS``) are resolved."""
        if not isinstance(d, dict) or "effects" not in d or "preset" not in d:
            raise ConfigError("sensor config must be a JSON object with 'preset' and 'effects'")
        if base_dir is not None and isinstance(d["effects"], list):
            d = dict(d, effects=[_resolve_files(e, Path(base_dir)) for e in d["effects"]])
        p = d["preset"]
        pre = get_preset(p) if isinstance(p, str) else _typed_preset(p)
        if not isinstance(d["effects"], list):
            raise ConfigError("sensor config 'effects' must be a list")
        for e in d["effects"]:
            _check_effect_entry(e)
        motion = d.get("motion") or {}
        if not isinstance(motion, dict):
            raise ConfigError("sensor config 'motion' must be a JSON object")
        unknown = sorted(set(motion) - {"max_speed_m_s", "max_angular_speed_rad_s"})
        if unknown:
            raise ConfigError(f"sensor config 'motion': unknown key(s) {', '.join(unknown)}; "
                              f"known: max_speed_m_s, max_angular_speed_rad_s")
        return cls(pre, [make_effect(e) for e in d["effects"]], MotionLimits(**motion))

    @classmethod
    def from_spec(cls, sensor: str, effects=None, width: int | None = None, height: int | None = None) -> "SensorConfig":
        """The config a user names: a preset name with ``effects`` (see :meth:`build`), or a
        sensor_config.json path (then ``effects`` must be None); ``width``/``height``: a centred
        crop of the sensor image (same per-pixel physics)."""
        if str(sensor).endswith(".json"):
            if effects:
                raise ConfigError("--effects cannot be combined with a sensor_config.json (edit the file instead)")
            cfg = cls.load(sensor)
        else:
            cfg = cls.build(sensor, effects)
        if width is not None or height is not None:
            pre = cfg.preset
            cfg = dataclasses.replace(cfg, preset=pre.cropped(width or pre.width, height or pre.height))  # keeps motion
        return cfg

    def save(self, path: str | os.PathLike) -> Path:
        from data_tools.results import atomic_write_json
        return atomic_write_json(path, self.to_json(base_dir=Path(path).parent))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "SensorConfig":
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise FormatError(path, "file not found") from None
        except json.JSONDecodeError as e:
            raise FormatError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
        try:
            return cls.from_json(d, base_dir=path.parent)
        except ConfigError as e:
            raise FormatError(path, str(e)) from None

    def effect(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        effect_class(name)  # unknown name -> ConfigError listing the known ones
        raise ConfigError(f"effect {name!r} is not in this sensor model ({', '.join(self.names())})")

    def names(self, enabled_only: bool = False) -> list[str]:
        return [e.name for e in self.effects if e.enabled or not enabled_only]

    @property
    def physical(self) -> bool:
        """True when the model runs the physical pipeline (pattern_projection enabled)."""
        return any(e.enabled and e.name == "pattern_projection" for e in self.effects)

    def ordered(self) -> list[Effect]:
        """Enabled effects in execution order (by stage, ties in model order)."""
        phys = self.physical
        en = [e for e in self.effects if e.enabled]
        return sorted(en, key=lambda e: e.stage_for(phys))

    def fittable(self) -> dict[str, tuple[float, float, float]]:
        """{"effect.param": (value, low, high)} over the enabled effects."""
        out = {}
        for e in self.effects:
            if e.enabled:
                for k, v in e.fittable().items():
                    out[f"{e.name}.{k}"] = v
        return out

    def with_params(self, values: dict[str, float]) -> "SensorConfig":
        """A copy with ``{"effect.param": value}`` changed (validated against the bounds)."""
        effects = list(self.effects)
        for key, val in values.items():
            if "." not in key:
                raise ConfigError(f"parameter key {key!r} must be 'effect.param'")
            en, pn = key.split(".", 1)
            for i, e in enumerate(effects):
                if e.name == en:
                    if pn in e.FILE_PARAMS or pn in e.START_ONLY_PARAMS:    # a path, a choice or a measured number
                        cur = getattr(e.params, pn)
                        try:
                            new = str(val) if isinstance(cur, str) else type(cur)(val)
                        except (TypeError, ValueError):
                            raise ConfigError(f"{key}: expected a number, got {val!r}") from None
                        effects[i] = e.replace(**{pn: new})
                        break
                    if pn not in e.FITTABLE:
                        raise ConfigError(f"{key}: not a fittable parameter of {en!r} ({', '.join(e.FITTABLE)})")
                    cur = getattr(e.params, pn)
                    effects[i] = e.replace(**{pn: type(cur)(val) if not isinstance(cur, bool) else bool(val)})
                    break
            else:
                raise ConfigError(f"{key}: effect {en!r} is not in this sensor model")
        return replace(self, effects=effects)


def _typed_preset(p) -> SensorPreset:
    """A preset JSON object with every field of its declared type (``"width": "640"`` or
    ``"fx": true`` is a one-line error naming the key, not a silent conversion)."""
    from data_tools.config import config_from_dict
    if not isinstance(p, dict):
        raise ConfigError("sensor config 'preset' must be a preset name or a JSON object")
    return config_from_dict(SensorPreset, p, "sensor config 'preset'", item="key", strict=True)


def _check_effect_entry(e) -> None:
    """An effect entry's keys have their JSON types: ``"enabled"`` a boolean (the string
    ``"false"`` would be truthy and turn the effect ON), ``"name"`` a string, ``"params"`` an
    object. Parameter types are checked by the effect's Params (``params_from_dict``)."""
    if not isinstance(e, dict):
        return                     # a bare name or [name, params]: make_effect checks those
    name = e.get("name", "?")
    if "name" in e and not isinstance(e["name"], str):
        raise ConfigError(f"effect entry {e['name']!r}: 'name' must be a string")
    if "enabled" in e and not isinstance(e["enabled"], bool):
        raise ConfigError(f"effect {name!r}: 'enabled' must be true or false (a JSON boolean), "
                          f"got {json.dumps(e['enabled'])}")
    if "params" in e and e["params"] is not None and not isinstance(e["params"], dict):
        raise ConfigError(f"effect {name!r}: 'params' must be a JSON object, got {json.dumps(e['params'])}")


def _resolve_files(spec, base: Path):
    """An effect entry of a model JSON with its relative data-file parameters made absolute."""
    if not isinstance(spec, dict) or not isinstance(spec.get("params"), dict) or "name" not in spec:
        return spec
    try:
        files = effect_class(spec["name"]).FILE_PARAMS
    except ConfigError:
        return spec
    params = dict(spec["params"])
    for k in files:
        v = params.get(k)
        if isinstance(v, str) and v and not os.path.isabs(v):
            params[k] = str(base / v)
    return dict(spec, params=params)


def _copy_beside(src: Path, folder: Path) -> str:
    """Copy the data file ``src`` into ``folder`` (atomically; kept when the same bytes are there
    already, renamed with a content hash when another file has its name) and return its name."""
    import hashlib
    import shutil
    folder.mkdir(parents=True, exist_ok=True)
    try:
        if src.parent.resolve() == folder.resolve():
            return src.name
        data = src.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{src}: data file of the sensor model not found") from None
    dst = folder / src.name
    if dst.exists() and dst.read_bytes() != data:
        dst = folder / f"{src.stem}-{hashlib.sha1(data).hexdigest()[:8]}{src.suffix}"
    if not dst.exists():
        tmp = dst.with_name(dst.name + f".tmp{os.getpid()}")
        shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
    return dst.name
