"""The sensor simulator: a preset + an ordered list of effects applied to ideal renders.

    sim = SensorSimulator("kinect_v1", scene=scene)          # full physical pipeline
    res = sim.simulate(pose_c2w, seed=3)                     # SimResult (depth, ir, valid, ...)
    again = sim.simulate(pose_c2w, seed=3)                   # identical
    replay = sim.simulate(pose_c2w, draws=res.draws)         # identical, from the stored draws
    direct = SensorSimulator("kinect_v1", effects="direct", scene=scene)
    custom = SensorSimulator("kinect_v1", effects=["axial_noise", "disparity_quantization"], scene=scene)

A model is just the preset plus a list of ``{"name", "enabled", "params"}`` entries;
:class:`~synth.sensor.config.SensorConfig` round-trips it through JSON (``sensor_config.json``
next to outputs). Many frames: :mod:`synth.sensor.pool` (trajectories, worker processes).
"""
from __future__ import annotations


import json
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from data_tools.camera import Camera, Intrinsics, SensorSpec
from data_tools.errors import ConfigError, RealgapError
from synth.sensor.presets import PRESETS, SensorPreset
from synth.sensor.config import SensorConfig
from synth.sensor.registry import Effect


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
    encoded: dict = field(default_factory=dict)
    """PNG bytes of ``depth``, ``ideal_depth`` and ``rgb`` (and their ``depth_scale``) when
    :meth:`encode` ran (``SimulationPool.map(..., encode_depth_scale=...)``), else empty."""

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
        enc = self.encoded or {}
        encoded = {"depth": enc.get("depth"), "rgb": enc.get("rgb"), "depth_scale": enc.get("depth_scale")}
        return Frame(float(timestamp), self.depth, self.rgb, self.pose_c2w, index, extra, encoded)

    def encode(self, depth_scale: float) -> None:
        """Encode ``depth``, ``ideal_depth`` and ``rgb`` as the PNG files a sequence writer writes
        (into ``encoded``; a worker process does it so that the writing process only copies bytes)."""
        from data_tools.sequence import encode_depth_png, encode_rgb_png
        self.encoded = {"depth": encode_depth_png(self.depth, depth_scale),
                        "ideal_depth": encode_depth_png(self.ideal_depth, depth_scale),
                        "rgb": encode_rgb_png(self.rgb) if self.rgb is not None else None,
                        "depth_scale": float(depth_scale)}


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
        shared: a dict shared by the simulators of one scene and renderer (e.g. every model a fit
            evaluates on a measured sequence): the pattern, reference images, ray grids and the
            seeded background draws they compute are kept there, keyed by everything they depend
            on (preset, effect parameters, seed), so a new simulator of another model does not
            rebuild them (the results are the same: the same inputs give the same arrays).
    """

    SHARED_REFERENCES = 8
    """Most reference images kept in a ``shared`` dict (the most recently used)."""
    SHARED_DRAWS = 12
    """Most frames whose background draws (``DRAW_FROM_SHAPE`` effects) a ``shared`` dict keeps (the
    most recently used; ~5 MB per VGA frame of a physical model)."""

    def __init__(self, preset_or_config: Any = "kinect_v1", effects=None, scene=None, *, renderer=None,
                 pattern=None, shared: dict | None = None):
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
        self._shared = shared

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
        if self._pattern is None and self._shared is not None and self._pattern_override is None:
            p = self.preset
            key = ("pattern", repr((p.pattern, p.pattern_size_px, p.pattern_tiles, p.pattern_density,
                                    p.pattern_seed)))
            if key not in self._shared:
                self._shared[key] = self._load_pattern()
            self._pattern = self._shared[key]
        if self._pattern is None:
            self._pattern = self._load_pattern()
        return self._pattern

    def _load_pattern(self):
        """The pattern of the preset (or the override), loaded or generated now."""
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
        return pat

    def ray_dirs(self) -> np.ndarray:
        if self._rays is None:
            key = ("rays", repr(self.preset.intrinsics))
            if self._shared is not None and key in self._shared:
                self._rays = self._shared[key]
            elif self.renderer is not None and hasattr(self.renderer, "ray_dirs_cam"):
                self._rays = self.renderer.ray_dirs_cam(self.preset.intrinsics)
            else:
                from synth.render import pinhole_ray_dirs
                self._rays = pinhole_ray_dirs(self.preset.intrinsics)
            if self._shared is not None:
                self._shared[key] = self._rays
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
        shared = self._shared if self._pattern_override is None else None
        skey = ("reference", key + repr(p))
        if shared is not None and skey in shared:
            self._reference_key, self._reference = key, shared.pop(skey)
            shared[skey] = self._reference                     # most recently used last
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
        if shared is not None:
            shared[skey] = st.ir8
            refs = [k for k in shared if k[0] == "reference"]
            for k in refs[:max(len(refs) - self.SHARED_REFERENCES, 0)]:
                del shared[k]
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
        names = {e.name for e in effects}
        if self._shared is None:
            return _draw_executor().submit(_draw_all, effects, int(seed), ctx), names
        # shared: the draws depend on the seed, the effect and the context only (the lab's common
        # random numbers: never on the parameters), so a model evaluated again on the same frame
        # reuses them; the effects never write into their draws
        key = ("draws", int(seed), repr(ctx), tuple(sorted((e.name, type(e).__qualname__) for e in effects)))
        fut = self._shared.pop(key, None)
        if fut is None:
            fut = _draw_executor().submit(_draw_all, effects, int(seed), ctx)
        self._shared[key] = fut                              # most recently used last
        draws = [k for k in self._shared if k[0] == "draws"]
        for k in draws[:max(len(draws) - self.SHARED_DRAWS, 0)]:
            del self._shared[k]
        return fut, names

    def simulate_sequence(self, poses_c2w: np.ndarray, seed: int = 0, motion: bool = True):
        """Yield one SimResult per pose; frame i uses seed ``seed + i`` and, with ``motion``,
        the previous pose for rolling shutter / motion blur."""
        prev = None
        for i, T in enumerate(np.asarray(poses_c2w)):
            yield self.simulate(T, seed=seed + i, prev_pose=prev if motion else None, frame_index=i)
            prev = T


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
