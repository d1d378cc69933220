"""The sensor simulator: a preset + an ordered list of effects applied to ideal renders.

    sim = SensorSimulator("kinect_v1", scene=scene)          # full physical pipeline
    res = sim.simulate(pose_c2w, seed=3)                     # SimResult (depth, ir, valid, ...)
    again = sim.simulate(pose_c2w, seed=3)                   # identical
    replay = sim.simulate(pose_c2w, draws=res.draws)         # identical, from the stored draws
    direct = SensorSimulator("kinect_v1", effects="direct", scene=scene)
    custom = SensorSimulator("kinect_v1", effects=["axial_noise", "disparity_quantization"], scene=scene)

A model is just the preset plus a list of ``{"name", "enabled", "params"}`` entries;
:class:`SensorConfig` round-trips it through JSON (``sensor_config.json`` next to outputs).
"""
from __future__ import annotations

import dataclasses

import json
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from data_tools.camera import Camera, Intrinsics, SensorSpec
from data_tools.errors import ConfigError, FormatError, RealgapError
from synth.sensor.presets import PRESETS, SensorPreset, get_preset
from synth.sensor.registry import Effect, effect_class, make_effect


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
        c = (float(np.trace(T1[:3, :3] @ T0[:3, :3].T)) - 1.0) / 2.0
        ang = math.acos(min(1.0, max(-1.0, c)))
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
        pipeline), "direct" (its analytic model), or a list of names / dicts / Effects;
        ``motion``: the motion plausibility limits (default :class:`MotionLimits`)."""
        pre = get_preset(preset) if isinstance(preset, str) else preset
        if not isinstance(pre, SensorPreset):
            raise ConfigError(f"expected a sensor preset name or SensorPreset, got {type(preset).__name__}")
        if effects is None or effects == "physical":
            names = list(pre.physical_effects)
        elif effects == "direct":
            names = list(pre.direct_effects)
        elif isinstance(effects, str):
            names = [e.strip() for e in effects.split(",") if e.strip()]
        else:
            names = list(effects)
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

    def to_json(self) -> dict:
        return {"preset": self.preset.to_json(), "effects": [e.to_json() for e in self.effects],
                "motion": {"max_speed_m_s": self.motion.max_speed_m_s,
                           "max_angular_speed_rad_s": self.motion.max_angular_speed_rad_s}}

    @classmethod
    def from_json(cls, d: dict) -> "SensorConfig":
        if not isinstance(d, dict) or "effects" not in d or "preset" not in d:
            raise ConfigError("sensor config must be a JSON object with 'preset' and 'effects'")
        p = d["preset"]
        pre = get_preset(p) if isinstance(p, str) else SensorPreset.from_json(p)
        if not isinstance(d["effects"], list):
            raise ConfigError("sensor config 'effects' must be a list")
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
        return atomic_write_json(path, self.to_json())

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
            return cls.from_json(d)
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
                    if pn not in e.FITTABLE:
                        raise ConfigError(f"{key}: not a fittable parameter of {en!r} ({', '.join(e.FITTABLE)})")
                    cur = getattr(e.params, pn)
                    effects[i] = e.replace(**{pn: type(cur)(val) if not isinstance(cur, bool) else bool(val)})
                    break
            else:
                raise ConfigError(f"{key}: effect {en!r} is not in this sensor model")
        return replace(self, effects=effects)


# ------------------------------------------------------------------------------------------
# Results
# ------------------------------------------------------------------------------------------

@dataclass
class SimResult:
    """One simulated frame. All images (H, W) in the depth camera's pixel grid."""

    depth: np.ndarray
    """float32 measured z-depth, metres; 0 = no measurement."""
    valid: np.ndarray
    """bool, True where ``depth`` is a measurement."""
    ideal_depth: np.ndarray
    """float32 noise-free z-depth at ``pose_c2w``, metres; 0 = no hit."""
    normals: np.ndarray
    """(H, W, 3) float32 ideal camera-frame normals (facing the camera)."""
    instance_ids: np.ndarray
    """int32 ideal instance ids (k + 1 for scene.meshes[k], 0 = none)."""
    ir: np.ndarray | None
    """uint16 captured IR image in ADC counts (physical pipeline), else None."""
    disparity: np.ndarray | None
    """float32 disparity, pixels, NaN where invalid (triangulating sensors), else None."""
    pose_c2w: np.ndarray
    """(4, 4) camera-to-world pose of the frame."""
    seed: int | None
    """Seed of the draws (None when replayed from given draws)."""
    draws: dict
    """{effect name: draw}: pass back as ``simulate(..., draws=...)`` to replay the frame."""
    log: dict
    """{effect name: statistics} plus ``timings_ms`` (wall time per stage) and ``cpu_ms`` (CPU
    time of all threads of the process per stage: less sensitive to a shared machine). Draws of
    ``DRAW_FROM_SHAPE`` effects run in a background thread from the end of ``render`` on, so
    their time is counted in whichever stages they overlap (mostly ``pattern_projection``)."""
    warnings: list[str] = field(default_factory=list)
    """Human-readable notes (e.g. 'no geometry in view')."""
    rgb: np.ndarray | None = None
    """(H, W, 3) uint8 ideal shaded colour when requested, else None."""

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())

    def to_frame(self, timestamp: float, index: int = 0):
        """A :class:`data_tools.sequence.Frame` (depth, rgb, pose; ideal depth, IR, valid mask,
        normals and instance ids in ``extra``) for :class:`SequenceWriter`."""
        from data_tools.sequence import Frame
        extra = {"ideal_depth": self.ideal_depth, "valid": self.valid, "normals": self.normals,
                 "instance_ids": self.instance_ids}
        if self.ir is not None:
            extra["ir"] = self.ir
        return Frame(float(timestamp), self.depth, self.rgb, self.pose_c2w, index, extra)


# ------------------------------------------------------------------------------------------
# The simulator
# ------------------------------------------------------------------------------------------

class SensorSimulator:
    """Simulate a depth sensor in a scene (see the module docstring).

    Args:
        preset_or_config: preset name, :class:`SensorPreset`, :class:`SensorConfig`, its JSON
            dict, or a path to a ``sensor_config.json``.
        effects: None (the preset's physical pipeline, or the ToF preset's model), "direct",
            a comma-separated string, or a list of effect names / dicts / Effect instances.
            Ignored when a full config is given.
        scene: the :class:`~data_tools.scene_spec.SceneSpec` to image (may be None with an
            explicit ``renderer``; a scene without meshes gives all-invalid frames).
        renderer: an :class:`synth.render.IdealRenderer` to reuse (built from ``scene`` if None).
        pattern: override the preset's pattern (a path or a ``DotPattern``).
    """

    def __init__(self, preset_or_config: Any = "kinect_v1", effects=None, scene=None, *, renderer=None,
                 pattern=None):
        cfg = preset_or_config
        if isinstance(cfg, (str, os.PathLike)) and (str(cfg).endswith(".json") or os.path.sep in str(cfg)):
            cfg = SensorConfig.load(cfg)
        elif isinstance(cfg, dict):
            cfg = SensorConfig.from_json(cfg)
        if not isinstance(cfg, SensorConfig):
            cfg = SensorConfig.build(cfg, effects)
        self.config: SensorConfig = cfg
        self.scene = scene
        if renderer is None and scene is not None and getattr(scene, "meshes", None):
            from synth.render import IdealRenderer
            renderer = IdealRenderer(scene)
        self.renderer = renderer
        self._pattern_override = pattern
        self._pattern = None
        self._reference_key = None
        self._reference = None
        self._rays = None

    # -- properties ------------------------------------------------------------------------
    @property
    def preset(self) -> SensorPreset:
        return self.config.preset

    @property
    def intrinsics(self) -> Intrinsics:
        """Intrinsics of the output depth image (distortion listed when lens_distortion is on)."""
        intr = self.preset.intrinsics
        ld = [e for e in self.config.effects if e.enabled and e.name == "lens_distortion"]
        if ld:
            coeffs = ld[0].coefficients(self.preset)
            if any(coeffs):
                intr = Intrinsics(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy, tuple(coeffs))
        return intr

    def camera(self) -> Camera:
        """camera.json content for sequences written with this sensor (with the sensor block)."""
        p = self.preset
        spec = SensorSpec(p.type, float(p.baseline_m), tuple(float(v) for v in p.projector_offset_m),
                          {"preset": p.name, "simulator": "realgap.synth.sensor",
                           "effects": self.config.names(enabled_only=True)})
        return Camera(self.intrinsics, float(p.depth_scale), spec)

    def effect(self, name: str) -> Effect:
        return self.config.effect(name)

    def set_enabled(self, name: str, enabled: bool = True) -> None:
        """Switch one effect of the model on or off (ConfigError if unknown / not in the model)."""
        self.config.effect(name).enabled = bool(enabled)

    def pattern(self):
        """The projector's :class:`DotPattern` (loaded/generated once)."""
        if self._pattern is None:
            from synth.sensor.pattern import DotPattern, generate_dot_pattern, load_pattern
            p = self.preset
            src = self._pattern_override if self._pattern_override is not None else p.pattern
            if isinstance(src, DotPattern):
                pat = src
                if pat.size != tuple(p.pattern_size_px):
                    raise ConfigError(f"pattern is {pat.size[0]}x{pat.size[1]} px but preset {p.name!r} "
                                      f"expects {p.pattern_size_px[0]}x{p.pattern_size_px[1]} px")
            elif src == "generated":
                tw = p.pattern_size_px[0] // p.pattern_tiles[0]
                th = p.pattern_size_px[1] // p.pattern_tiles[1]
                if (tw * p.pattern_tiles[0], th * p.pattern_tiles[1]) != tuple(p.pattern_size_px):
                    raise ConfigError(f"preset {p.name!r}: pattern_size_px {p.pattern_size_px} is not a "
                                      f"multiple of pattern_tiles {p.pattern_tiles}")
                pat = generate_dot_pattern((tw, th), p.pattern_tiles, p.pattern_density, p.pattern_seed)
            else:
                pat = load_pattern(src, p.pattern_size_px)
            self._pattern = pat
        return self._pattern

    def ray_dirs(self) -> np.ndarray:
        if self._rays is None:
            if self.renderer is not None and hasattr(self.renderer, "ray_dirs_cam"):
                self._rays = self.renderer.ray_dirs_cam(self.preset.intrinsics)
            else:
                from synth.sensor.state import pinhole_rays
                self._rays = pinhole_rays(self.preset.intrinsics)
        return self._rays

    # -- reference image --------------------------------------------------------------------
    def reference_image(self) -> np.ndarray | None:
        """Structured light: the stored reference (the pattern on a white plane at z0, captured
        noise-free through the same optics), padded for the search range; None otherwise."""
        p = self.preset
        if (p.type != "structured_light" or not self.config.physical
                or "block_matching" not in self.config.names(enabled_only=True)):
            return None
        ref_effects = [e for e in self.config.ordered() if e.in_reference]
        key = json.dumps([e.to_json() for e in ref_effects], sort_keys=True)
        bm = [e for e in self.config.effects if e.name == "block_matching"]
        setup = bm[0].setup(p) if bm else None
        if setup is None:
            from synth.sensor.matching import MatchSetup
            setup = MatchSetup.for_preset(p)
        key += repr(setup)
        if key == self._reference_key:
            return self._reference
        from synth.render import pinhole_ray_dirs
        from synth.sensor.state import FrameContext, SensorState, plane_view
        rintr = setup.reference_intrinsics(p.intrinsics)
        rays = pinhole_ray_dirs(rintr)
        view = plane_view(rays, float(p.reference_depth_m))
        st = SensorState(p, rintr, FrameContext(np.eye(4), None, 1.0 / p.fps), None, rays, view, view,
                         view.depth, view.hit.copy(), {e.name: e for e in ref_effects}, True, True,
                         pattern=self.pattern().image)
        for e in ref_effects:
            e.apply(st, e.null_draw(st))
        if st.ir8 is None:
            raise ConfigError("the reference image needs 'pattern_projection' and 'ir_capture' in the model")
        self._reference_key, self._reference = key, st.ir8
        return st.ir8

    # -- simulation -------------------------------------------------------------------------
    def make_state(self, pose_c2w: np.ndarray, prev_pose: np.ndarray | None = None, render=None,
                   with_rgb: bool = False, frame_index: int | None = None, timestamp_s: float | None = None):
        """The :class:`SensorState` of a frame before any effect ran (ideal depth, all hit pixels
        valid), with the pattern and reference image attached for physical models. Returns
        (state, warnings, rgb). ``frame_index`` / ``timestamp_s`` go to ``state.frame``. Useful to
        apply single effects by hand (tests, sensor lab)."""
        from synth.sensor.state import FrameContext, SensorState, empty_view, geometry_from_render
        T = _check_pose(pose_c2w, "pose_c2w")
        Tp = None if prev_pose is None else _check_pose(prev_pose, "prev_pose")
        p = self.preset
        intr = p.intrinsics
        rgb = None
        warnings: list[str] = []
        cut = None
        if Tp is not None:
            cut = self.config.motion.violation(T, Tp, 1.0 / p.fps)
            if cut:
                warnings.append(cut)
                Tp = None
        no_scene = self.renderer is None
        if no_scene:
            ideal = empty_view(intr.shape)
            warnings.append("scene has no geometry: all pixels invalid")
        else:
            if render is None:
                render = self.renderer.render(T, intr, with_rgb=with_rgb)
            rgb = render.rgb if with_rgb else None
            ideal = geometry_from_render(render, self.renderer, T)
        phys = self.config.physical
        ordered = self.config.ordered()
        exposure = next((float(getattr(e.params, e.FRAME_EXPOSURE_PARAM)) for e in ordered
                         if e.FRAME_EXPOSURE_PARAM), 0.0)
        frame = FrameContext(T, Tp, 1.0 / p.fps, frame_index, timestamp_s, exposure)
        state = SensorState(p, intr, frame, self.renderer, self.ray_dirs(), ideal, ideal,
                            ideal.depth, ideal.hit.copy(), {e.name: e for e in ordered}, phys)
        if cut:
            state.log["motion"] = {"cut": True, "reason": cut}
        if not ideal.hit.any():
            if not no_scene:
                warnings.append("no geometry in view: all pixels invalid")
        elif phys:
            state.pattern = self.pattern().image
            state.reference_ir8 = self.reference_image()
        return state, warnings, rgb

    def simulate(self, pose_c2w: np.ndarray, seed: int | None = 0, prev_pose: np.ndarray | None = None,
                 draws: dict | None = None, render=None, with_rgb: bool = False, frame_index: int | None = None,
                 timestamp_s: float | None = None) -> SimResult:
        """Simulate the frame seen from ``pose_c2w`` (4x4 camera-to-world, OpenCV axes).

        ``seed`` fixes every random draw (per effect: the effect's draw depends only on the
        seed and its name). ``prev_pose`` (pose one frame period earlier) switches on the
        motion effects, unless the motion it implies exceeds ``config.motion`` (then it is
        treated as a cut: static frame, a warning in ``SimResult.warnings``). ``draws`` replays a previous result's draws exactly. ``render`` reuses
        an ideal :class:`RenderResult` of this pose. ``frame_index`` and ``timestamp_s`` describe
        the frame in its sequence (:class:`~synth.sensor.state.FrameContext`). Deterministic given
        (seed or draws).
        """
        if draws is None and seed is None:
            raise ConfigError("simulate needs a seed or the draws of a previous frame")
        t0, c0 = time.perf_counter(), time.process_time()
        # draws that depend only on the image shape are made in a background thread while the
        # first stages run (the same generators, so the same values as drawing them in turn);
        # started first, so that they fill the core the single-threaded parts of the set-up
        # leave free (a frame without geometry simply does not use them)
        early = self._start_draws(seed) if draws is None else None
        state, warnings, rgb = self.make_state(pose_c2w, prev_pose, render, with_rgb, frame_index, timestamp_s)
        timings = {"render": (time.perf_counter() - t0) * 1e3}
        cpu = {"render": (time.process_time() - c0) * 1e3}
        ideal = state.ideal
        used_draws: dict = {}
        if not ideal.hit.any():
            state.valid[:] = False
            state.depth[:] = 0
        else:
            for e in state.model.values():  # already in execution order
                t1, c1 = time.perf_counter(), time.process_time()
                if draws is not None:
                    if e.name in draws:
                        d = draws[e.name]
                    else:
                        d = e.sample(e.rng(seed), state) if seed is not None else None
                        if d is not None:
                            raise RealgapError(f"replay: the given draws lack effect {e.name!r}")
                elif early is not None and e.name in early[1]:
                    d = early[0].result()[e.name]
                else:
                    d = e.sample(e.rng(seed), state)
                e.apply(state, d)
                used_draws[e.name] = d
                timings[e.name] = (time.perf_counter() - t1) * 1e3
                cpu[e.name] = (time.process_time() - c1) * 1e3
        depth = np.where(state.valid & (state.depth > 0), state.depth, 0).astype(np.float32, copy=False)
        valid = depth > 0
        if not valid.any() and ideal.hit.any():
            warnings.append("the sensor measured no valid pixel in this frame")
        log = dict(state.log)
        timings["total"] = (time.perf_counter() - t0) * 1e3
        cpu["total"] = (time.process_time() - c0) * 1e3
        log["timings_ms"] = timings
        log["cpu_ms"] = cpu
        disp = state.disparity
        if disp is not None:
            disp = np.where(valid, disp, np.nan).astype(np.float32, copy=False)
        return SimResult(depth, valid, ideal.depth, np.asarray(ideal.normals_cam), ideal.instance_ids.copy(),
                         state.ir, disp, state.pose_c2w, None if draws is not None else seed, used_draws, log,
                         warnings, rgb)

    def _start_draws(self, seed: int):
        """Start the draws of the enabled ``DRAW_FROM_SHAPE`` effects in the background thread:
        (future of {name: draw}, their names), or None when there are none."""
        from synth.sensor.state import DrawContext
        effects = [e for e in self.config.ordered() if e.DRAW_FROM_SHAPE]
        if not effects:
            return None
        ctx = DrawContext(self.preset, self.preset.intrinsics, self.config.physical)
        fut = _draw_executor().submit(_draw_all, effects, int(seed), ctx)
        return fut, {e.name for e in effects}

    def simulate_sequence(self, poses_c2w: np.ndarray, seed: int = 0, motion: bool = True):
        """Yield one SimResult per pose; frame i uses seed ``seed + i`` and, with ``motion``,
        the previous pose for rolling shutter / motion blur."""
        prev = None
        for i, T in enumerate(np.asarray(poses_c2w)):
            yield self.simulate(T, seed=seed + i, prev_pose=prev if motion else None, frame_index=i)
            prev = T


def simulate_trajectory(sim: SensorSimulator, poses_c2w: np.ndarray, timestamps: np.ndarray, writer,
                        seed: int = 0, motion: bool = True, with_rgb: bool = True, progress: bool = True,
                        workers: int = 1) -> int:
    """Simulate every pose and append the frames to a :class:`data_tools.sequence.SequenceWriter`
    (open it with ``camera=sim.camera()``); frames already in the writer (``len(writer)``, a
    resumed run) are skipped, so the result is identical to an uninterrupted run (frame i
    always uses seed ``seed + i`` and pose i - 1 as its previous pose; where that implies more
    than ``sim.config.motion`` allows, the frame is a cut - static - and the progress bar counts
    it). Returns the number of frames written now. ``workers`` > 1 simulates that many frames
    at once in worker processes (:class:`SimulationPool`: more frames per second when cores are
    free, identical frames, a few seconds of start-up); frames are still written in order.

        with SequenceWriter(out, sim.camera(), scene, resume=resume) as w:
            sim.config.save(out / "sensor_config.json")
            simulate_trajectory(sim, traj.poses, traj.timestamps, w, seed=cfg.seed)
    """
    poses = np.asarray(poses_c2w, dtype=np.float64)
    ts = np.asarray(timestamps, dtype=np.float64)
    if len(poses) != len(ts):
        raise RealgapError(f"simulate_trajectory: {len(poses)} poses but {len(ts)} timestamps")
    if int(workers) < 1:
        raise ConfigError(f"simulate_trajectory: workers must be >= 1, got {workers}")
    start = len(writer)
    idx = range(start, len(poses))
    if progress:
        from tqdm import tqdm
        idx = tqdm(idx, desc=f"simulating {sim.preset.name}", initial=start, total=len(poses))
    prevs = [poses[i - 1] if (motion and i > 0) else None for i in range(len(poses))]
    n_workers = min(int(workers), len(poses) - start)   # no more processes than frames left
    pool = SimulationPool(sim, workers=n_workers) if n_workers > 1 else None
    if pool is None:
        results = (sim.simulate(poses[i], seed=seed + i, prev_pose=prevs[i], with_rgb=with_rgb, frame_index=i,
                                timestamp_s=float(ts[i])) for i in range(start, len(poses)))
    else:
        results = pool.map(poses[start:], [seed + i for i in range(start, len(poses))], prevs[start:],
                           with_rgb=with_rgb, keep_draws=False,  # frames are written, draws not kept
                           frame_indices=range(start, len(poses)), timestamps=ts[start:])
    n = cuts = 0
    try:
        for i, res in zip(idx, results):
            writer.write(res.to_frame(ts[i], i))
            n += 1
            if res.log.get("motion", {}).get("cut"):
                cuts += 1
                if progress:  # frames whose motion exceeded sim.config.motion (motion effects skipped)
                    idx.set_postfix_str(f"{cuts} motion cut(s)")
    finally:
        if pool is not None:
            pool.close()
    return n


class SimulationPool:
    """Frames in flight in parallel: ``workers`` processes, each with its own copy of a
    simulator (same config, scene and pattern), simulate different frames at the same time.

        with SimulationPool(sim, workers=2) as pool:
            for res in pool.map(poses, seeds=range(len(poses)), prev_poses=[None] + list(poses[:-1])):
                ...                                  # SimResults in input order

    Every frame's result is identical to ``sim.simulate(pose, seed=seed, prev_pose=prev)``
    (frames are independent given their seed and previous pose; nothing is shared between
    frames). Processes rather than threads: Open3D's ray casting holds the Python GIL for the
    whole query (measured: a second Python thread stalls for the duration of each
    ``cast_rays``), so two threads cannot overlap two frames' ray casts. Workers are started
    with ``spawn`` (forking a process whose Open3D/TBB and OpenCV thread pools are running is
    unsafe) and each builds its Embree scene and the reference image once, in
    :meth:`__init__` (a few seconds). This raises throughput, not single-frame latency. The
    result arrays (about 12 MB per VGA frame with the draws) come back through shared-memory
    slots owned by this object (one memcpy each way instead of pickling them through a pipe,
    which cost ~10 ms of CPU per frame); results that do not fit a slot are pickled.
    """

    def __init__(self, sim: "SensorSimulator", workers: int = 2, slot_bytes: int = 32 << 20):
        """``slot_bytes``: size of one shared-memory result slot (a VGA frame needs ~12 MB,
        active stereo more; 0 = pickle every result)."""
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        if workers < 1:
            raise ConfigError(f"SimulationPool: workers must be >= 1, got {workers}")
        scene = sim.scene if sim.scene is not None else getattr(sim.renderer, "scene", None)
        if sim.renderer is not None and scene is None:
            raise ConfigError("SimulationPool: the simulator's renderer has no scene to copy into the workers")
        pattern = sim.pattern() if sim.config.physical else sim._pattern_override
        self.workers = int(workers)
        self._slots: list = []
        self.slot_bytes = max(int(slot_bytes), 0)
        self._ex = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                       initializer=_pool_init, initargs=(sim.config.to_json(), scene, pattern))
        # wait until every worker is up (imports, BVH, reference image), so timings exclude it
        list(self._ex.map(_pool_ready, range(self.workers)))

    def map(self, poses_c2w, seeds, prev_poses=None, max_in_flight: int | None = None,
            with_rgb: bool = False, keep_draws: bool = True, frame_indices=None, timestamps=None):
        """Yield ``simulate(poses_c2w[i], seed=seeds[i], prev_pose=prev_poses[i], with_rgb=with_rgb,
        frame_index=frame_indices[i], timestamp_s=timestamps[i])`` in order, with at most ``max_in_flight`` (default 2 x workers) frames submitted ahead.
        ``keep_draws=False`` returns results with empty ``draws`` (a caller that only writes the
        frames saves shipping them: ~20 % of each VGA result)."""
        from collections import deque
        poses = list(poses_c2w)
        seeds = list(seeds)
        prevs = list(prev_poses) if prev_poses is not None else [None] * len(poses)
        idx = list(frame_indices) if frame_indices is not None else [None] * len(poses)
        ts = [float(t) for t in timestamps] if timestamps is not None else [None] * len(poses)
        if not (len(poses) == len(seeds) == len(prevs) == len(idx) == len(ts)):
            raise RealgapError(f"SimulationPool.map: {len(poses)} poses, {len(seeds)} seeds, "
                               f"{len(prevs)} previous poses")
        from multiprocessing.shared_memory import SharedMemory
        ahead = max(1, max_in_flight or 2 * self.workers)
        while len(self._slots) < ahead:
            self._slots.append(SharedMemory(create=True, size=max(self.slot_bytes, 1)))
        free = deque(self._slots[:ahead])
        pending: deque = deque()

        def collect():
            fut, slot = pending.popleft()
            try:
                return _unpack_result(fut.result(), slot)
            finally:
                free.append(slot)

        for i in range(len(poses)):
            slot = free.popleft()
            pending.append((self._ex.submit(_pool_simulate, poses[i], seeds[i], prevs[i], slot.name,
                                            self.slot_bytes, with_rgb, keep_draws, idx[i], ts[i]), slot))
            if len(pending) >= ahead:
                yield collect()
        while pending:
            yield collect()

    def close(self) -> None:
        self._ex.shutdown(wait=True, cancel_futures=True)
        for shm in self._slots:
            shm.close()
            shm.unlink()
        self._slots = []

    def __enter__(self) -> "SimulationPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_POOL_SIM: "SensorSimulator | None" = None
"""The simulator of a :class:`SimulationPool` worker process."""


def _pool_init(config_json: dict, scene, pattern) -> None:
    """Worker set-up: one thread per library call (the workers are the parallelism: with
    Open3D's and OpenCV's thread pools on top, 2 workers on 2 cores measured 2-6x the CPU time
    per frame of a serial run; the outputs do not depend on the thread counts)."""
    global _POOL_SIM
    import cv2
    import synth.jit
    cv2.setNumThreads(1)
    synth.jit.THREADS = 1
    sim = SensorSimulator(SensorConfig.from_json(config_json), scene=scene if scene is not None and
                          getattr(scene, "meshes", None) else None, pattern=pattern)
    if sim.renderer is not None:  # compile/load the raster kernels and build Open3D's BVH (shadow
        # rays; Open3D commits the scene on its first query) now, not in the first frame
        sim.renderer.render(np.eye(4), sim.preset.intrinsics, with_rgb=False)
        sim.renderer.cast_rays(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    if sim.config.physical:
        sim.pattern()
        sim.reference_image()
    _POOL_SIM = sim


def _pool_ready(_i: int) -> bool:
    return _POOL_SIM is not None


_RESULT_ARRAYS = ("depth", "valid", "ideal_depth", "normals", "instance_ids", "ir", "disparity", "rgb")
_POOL_SLOTS: dict = {}
"""Worker side: shared-memory slots attached so far, by name."""


def _result_arrays(res: SimResult) -> list:
    """[(key, array)] of the large arrays of a result: its image fields and the arrays among its
    draws (a draw that is an array, or a dict holding arrays)."""
    out = [((f,), getattr(res, f)) for f in _RESULT_ARRAYS if isinstance(getattr(res, f), np.ndarray)]
    for name, d in res.draws.items():
        if isinstance(d, np.ndarray):
            out.append((("draws", name), d))
        elif isinstance(d, dict):
            out += [(("draws", name, k), v) for k, v in d.items() if isinstance(v, np.ndarray)]
    return out


def _set_result_array(res: SimResult, key: tuple, value) -> None:
    if key[0] != "draws":
        setattr(res, key[0], value)
    elif len(key) == 2:
        res.draws[key[1]] = value
    else:
        res.draws[key[1]][key[2]] = value


def _pool_simulate(pose, seed, prev, slot_name: str, slot_size: int, with_rgb: bool = False,
                   keep_draws: bool = True, frame_index: int | None = None, timestamp_s: float | None = None):
    """Simulate one frame (its draws dropped unless ``keep_draws``); its arrays go into the
    shared-memory slot when they fit: ("shm", result without them, [(key, dtype, shape,
    offset)]), else ("pickle", result)."""
    res = _POOL_SIM.simulate(pose, seed=seed, prev_pose=prev, with_rgb=with_rgb, frame_index=frame_index,
                             timestamp_s=timestamp_s)
    if not keep_draws:
        res.draws = {}
    arrays = _result_arrays(res)
    need = sum(-(-a.nbytes // 64) * 64 for _, a in arrays)
    if need > slot_size:
        return ("pickle", res)
    shm = _POOL_SLOTS.get(slot_name)
    if shm is None:  # the pool (parent) owns and unlinks the slot; spawned workers share its
        # resource tracker, so attaching here (which registers the name again) leaks nothing
        from multiprocessing.shared_memory import SharedMemory
        shm = _POOL_SLOTS[slot_name] = SharedMemory(name=slot_name)
    meta, off = [], 0
    for key, a in arrays:
        np.ndarray(a.shape, a.dtype, buffer=shm.buf, offset=off)[...] = a
        meta.append((key, a.dtype.str, a.shape, off))
        _set_result_array(res, key, None)
        off += -(-a.nbytes // 64) * 64
    return ("shm", res, meta)


def _unpack_result(packed, slot) -> SimResult:
    """Parent side of :func:`_pool_simulate`: the result with its arrays copied out of the slot."""
    if packed[0] == "pickle":
        return packed[1]
    _, res, meta = packed
    for key, dtype, shape, off in meta:
        _set_result_array(res, key, np.ndarray(shape, np.dtype(dtype), buffer=slot.buf, offset=off).copy())
    return res


_DRAW_EXECUTOR: list = []
"""[(pid, ThreadPoolExecutor)] of the draws made while rendering (one thread per process)."""


def _draw_executor():
    """The process's background thread for early draws (a new one after a fork: a forked
    child has no threads of its parent's executor)."""
    from concurrent.futures import ThreadPoolExecutor
    if not _DRAW_EXECUTOR or _DRAW_EXECUTOR[0][0] != os.getpid():
        _DRAW_EXECUTOR[:] = [(os.getpid(), ThreadPoolExecutor(1, thread_name_prefix="realgap-draws"))]
    return _DRAW_EXECUTOR[0][1]


def _draw_all(effects, seed: int, ctx) -> dict:
    return {e.name: e.sample(e.rng(seed), ctx) for e in effects}


def _check_pose(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise RealgapError(f"{name} must be a finite 4x4 matrix, got shape {T.shape}")
    return T


def list_presets() -> list[str]:
    return sorted(PRESETS)
