"""A measured RGB-D sequence plus its ideal geometry, ready for simulation and comparison.

:class:`MeasuredSequence` loads a TUM-layout sequence with ``camera.json`` and ``scene.json``
(../shared/FORMATS.md), keeps the frames that have a ground-truth pose, derives a sensor preset
from ``camera.json`` and ray-casts the ideal geometry of every kept frame **once** (renders are
cached for the lifetime of the object, so a fit that simulates the sequence hundreds of times
never casts a camera ray again)::

    ms = MeasuredSequence.load("SEQ", max_frames=24)
    cfg = ms.default_config(["axial_noise", "range_limits"])
    sim = ms.simulate(cfg, seed=0)                 # simulated depth per kept frame
    obs = ms.observations(sim)                     # FrameObservation per kept frame
    result = compare(obs)

Preset derivation. The sensor block of ``camera.json`` picks the starting preset (``kinect_v1``
for ``structured_light``, ``realsense_d435`` for ``active_stereo``, ``kinect_v2`` for ``tof``;
``preset=`` overrides the choice); its intrinsics, baseline, projector offset and distortion are
replaced by the file's values. Everything else (range, matcher, pattern, per-effect defaults)
stays the preset's. Without a sensor block the preset's geometry is kept except the intrinsics.

Frame indices. ``frame_indices[k]`` is the index of kept frame k in the sequence (the
:class:`~data_tools.sequence.SequenceReader` order); frame k is always simulated with the seed
``seed + frame_indices[k]``, so a subset of frames gets exactly the draws it gets inside the
full sequence.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from data_tools.camera import Camera, Intrinsics
from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.scene_spec import SceneSpec
from data_tools.sequence import spread_indices
from synth.lab.compare import CompareCache
from synth.lab.features import FrameObservation, material_table_from_scene

__all__ = ["MeasuredSequence", "DEFAULT_PRESET_FOR_TYPE", "preset_from_camera"]

DEFAULT_PRESET_FOR_TYPE = {"structured_light": "kinect_v1", "active_stereo": "realsense_d435",
                           "tof": "kinect_v2"}
"""Starting preset per ``camera.json`` sensor type."""


def preset_from_camera(camera: Camera, preset: str | None = None, path: str | os.PathLike | None = None):
    """The :class:`~synth.sensor.presets.SensorPreset` of a measured camera (see the module docstring).

    ``path`` names the camera.json in errors (FormatError when the file's sensor geometry is
    impossible for the chosen preset, e.g. a structured-light projector off the x axis).
    """
    from synth.sensor.presets import get_preset

    stype = camera.sensor.type if camera.sensor is not None else None
    name = preset or DEFAULT_PRESET_FOR_TYPE.get(stype or "structured_light", "kinect_v1")
    try:
        pre = get_preset(name)
    except ConfigError as e:
        if preset:  # the user's --preset, not the file
            raise ConfigError(f"--preset: {e} ('realgap sensor presets' lists them)") from None
        raise FormatError(path, str(e)) from None
    i = camera.intrinsics
    changes = dict(width=int(i.width), height=int(i.height), fx=float(i.fx), fy=float(i.fy),
                   cx=float(i.cx), cy=float(i.cy))
    if i.distortion and any(float(x) for x in i.distortion):
        changes["distortion"] = tuple(float(x) for x in i.distortion)
    if camera.sensor is not None:
        s = camera.sensor
        if s.type != pre.type:
            changes["type"] = s.type
        changes["baseline_m"] = float(s.baseline_m)
        changes["projector_offset_m"] = tuple(float(x) for x in s.projector_offset_m)
        if s.type == "tof":
            changes["matcher"] = "none"
    changes["depth_scale"] = float(camera.depth_scale)
    try:
        return pre.replace(**changes)
    except ConfigError as e:
        raise FormatError(path, f"sensor geometry does not fit preset {pre.name!r}: {e}") from None
    except TypeError as e:  # pragma: no cover - dataclass field mismatch
        raise FormatError(path, f"cannot derive a sensor preset ({e})") from None


def parse_frame_slice(text: str) -> slice:
    """``START:STOP:STEP`` (Python slice syntax, each part optional, STEP > 0) -> slice; a one-line
    ConfigError naming ``--frame-slice`` otherwise."""
    parts = str(text).split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        vals = [int(x) if x.strip() else None for x in parts]
    except ValueError:
        raise ConfigError(f"--frame-slice {text!r}: expected START:STOP[:STEP] with integers, e.g. 0::2") from None
    if len(vals) == 3 and vals[2] is not None and vals[2] < 1:
        raise ConfigError(f"--frame-slice {text!r}: STEP must be >= 1")
    return slice(*vals)


class MeasuredSequence:
    """A measured RGB-D sequence (TUM layout + camera.json + scene.json, ../shared/FORMATS.md)
    with the ideal geometry rendered at its ground-truth poses (cached: one ray cast per frame,
    ever). Build it with :meth:`load`."""

    seq_dir: Path
    """The sequence folder."""
    camera: Camera
    """camera.json content."""
    intrinsics: Intrinsics
    """Pinhole intrinsics of the depth images and of the ideal renders (distortion dropped:
    a lens distortion is a sensor effect to be modelled, the renders are ideal)."""
    scene: SceneSpec
    """Reference geometry (scene.json)."""
    preset: object
    """The derived :class:`~synth.sensor.presets.SensorPreset`."""
    frame_indices: list[int]
    """Index in the sequence of each kept frame."""
    timestamps: np.ndarray
    """(N,) seconds of the kept frames."""
    poses: np.ndarray
    """(N, 4, 4) camera-to-world ground-truth poses of the kept frames."""
    prev_poses: list
    """Per kept frame: the pose of the previous sequence frame ((4, 4)) when it has one and lies
    at most 1.5 frame periods (of the preset's frame rate) earlier; else, when the next frame does,
    the constant-velocity extrapolation one frame period back from the next frame's motion (the
    first frame of a moving sequence moves too); else None (static frame). Motion effects (rolling
    shutter, motion blur) use it as the pose one frame period earlier."""
    skipped_no_pose: int
    """Frames left out because no ground-truth pose lies within 0.02 s."""
    compare_cache: object
    """A :class:`~synth.lab.compare.CompareCache` for comparisons of this sequence's frames
    (sampled pixels, edge distance transforms, measured errors per frame); the fit objectives
    and :func:`~synth.lab.diagnose.diagnose` pass it to :func:`~synth.lab.compare.compare`."""

    def __init__(self, seq_dir, camera, scene, preset, reader, frame_indices, prev_poses, skipped):
        self.seq_dir = Path(seq_dir)
        self.camera = camera
        self.scene = scene
        self.preset = preset
        self.intrinsics = preset.intrinsics
        self._reader = reader
        self.frame_indices = [int(i) for i in frame_indices]
        self.timestamps = np.asarray(reader.timestamps[self.frame_indices], dtype=np.float64)
        self.poses = np.asarray(reader.poses[self.frame_indices], dtype=np.float64)
        self.prev_poses = prev_poses
        self.skipped_no_pose = int(skipped)
        self._depth: dict[int, np.ndarray] = {}
        self._render: dict[int, object] = {}
        self._renderer = None
        self._material_names = material_table_from_scene(scene)
        self.compare_cache = CompareCache()
        self._sim_shared: dict = {}
        """What the simulators of this sequence's models share (pattern, reference images, rays, draws:
        :class:`~synth.sensor.simulator.SensorSimulator` ``shared``)."""

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, seq_dir: str | os.PathLike, *, max_frames: int | None = None,
             preset: str | None = None, frame_slice: str | None = None,
             frames: Sequence[int] | None = None) -> "MeasuredSequence":
        """Open a measured sequence (see the module docstring).

        frame_slice: ``START:STOP:STEP`` (Python slice syntax) over the frames with a pose, applied
        first, e.g. ``0::2`` / ``1::2`` to fit on half of the frames and test on the other half.
        frames: positions among the frames with a pose (after ``frame_slice``) to keep, in that
        order - a selection no slice writes, such as a cross-validation fold's complement.
        max_frames: keep at most this many frames, evenly spread over those (with a pose, in the slice).
        FormatError (naming the file) when the folder, depth index, camera.json, scene.json
        or the ground-truth poses are missing or bad.
        """
        from data_tools.sequence import SequenceReader

        seq_dir = Path(seq_dir)
        from data_tools.outputs import check_input_dir
        check_input_dir(seq_dir, "sequence folder")
        cam_file = seq_dir / "camera.json"
        if not cam_file.is_file():
            raise FormatError(cam_file, "file not found (the sensor lab needs the depth camera's intrinsics)")
        reader = SequenceReader(seq_dir)
        if not reader.has_scene:
            raise FormatError(seq_dir / "scene.json", "file not found (the sensor lab needs the reference geometry)")
        scene = reader.scene
        if not scene.meshes:
            raise FormatError(seq_dir / "scene.json", "holds no meshes")
        gt = seq_dir / "groundtruth.txt"
        if not reader.has_groundtruth:
            raise FormatError(gt, "file not found (the sensor lab needs ground-truth poses)")
        ok = np.all(np.isfinite(reader.poses.reshape(len(reader), -1)), axis=1)
        if not ok.any():
            raise FormatError(gt, "no ground-truth pose lies within 0.02 s of a depth frame")
        with_pose = np.flatnonzero(ok)
        if frame_slice:
            with_pose = with_pose[parse_frame_slice(frame_slice)]
            if not len(with_pose):
                raise ConfigError(f"--frame-slice {frame_slice}: selects none of the {int(ok.sum())} frames with a pose")
        if frames is not None:
            pick = [int(k) for k in frames]
            if not pick:
                raise ConfigError(f"{seq_dir}: no frame positions given")
            if min(pick) < 0 or max(pick) >= len(with_pose):
                raise ConfigError(f"{seq_dir}: frame positions {min(pick)}..{max(pick)} outside "
                                  f"0..{len(with_pose) - 1} (the frames with a pose)")
            with_pose = with_pose[pick]
        if max_frames is not None:
            if int(max_frames) < 1:
                raise ConfigError(f"max_frames must be >= 1, got {max_frames}")
            if len(with_pose) > int(max_frames):
                with_pose = with_pose[spread_indices(len(with_pose), int(max_frames))]
        pre = preset_from_camera(reader.camera, preset, cam_file)
        prev = [_previous_pose(reader.poses, reader.timestamps, int(i), 1.0 / pre.fps) for i in with_pose]
        return cls(seq_dir, reader.camera, scene, pre, reader, with_pose.tolist(), prev, int((~ok).sum()))

    def __len__(self) -> int:
        return len(self.frame_indices)

    # ------------------------------------------------------------------ data
    @property
    def renderer(self):
        """The :class:`synth.render.IdealRenderer` of the scene (built once)."""
        if self._renderer is None:
            from synth.render import IdealRenderer
            self._renderer = IdealRenderer(self.scene)
        return self._renderer

    @property
    def material_names(self) -> dict[int, str]:
        """Instance id -> material name of the scene."""
        return self._material_names

    def _frames(self, frames) -> list[int]:
        if frames is None:
            return list(range(len(self)))
        out = [int(k) for k in frames]
        for k in out:
            if not 0 <= k < len(self):
                raise RealgapError(f"{self.seq_dir}: frame position {k} outside 0..{len(self) - 1}")
        return out

    def measured_depth(self, k: int) -> np.ndarray:
        """(H, W) float32 measured depth of kept frame k, metres, 0 invalid (cached)."""
        d = self._depth.get(k)
        if d is None:
            d = self._reader.read_depth(self.frame_indices[k])
            if not np.all(np.isfinite(d)):
                raise FormatError(self.seq_dir / self._reader.depth_files[self.frame_indices[k]],
                                  "depth contains NaN or inf")
            self._depth[k] = d = d.astype(np.float32, copy=False)
        return d

    @property
    def has_masks(self) -> bool:
        """The sequence has per-frame masks (e.g. a planar-target capture)."""
        return bool(self._reader.has_masks)

    @property
    def has_plane_reference(self) -> bool:
        """The sequence is a planar-target capture with its reference (``plane_reference.json``, written
        by ``realgap data make-reference --plane``): fits add the noise-vs-distance term
        (:mod:`synth.lab.calibration`)."""
        return (self.seq_dir / "plane_reference.json").is_file()

    def mask(self, k: int) -> np.ndarray | None:
        """(H, W) bool mask of kept frame k (FORMATS.md section 4), None when the sequence has none.
        Comparisons, fits and diagnoses use only masked-in pixels: :meth:`observation` sets the
        ideal depth to 0 (no reference geometry) outside the mask; simulation ignores masks."""
        if not self._reader.has_masks:
            return None
        if not hasattr(self, "_masks"):
            self._masks = {}
        m = self._masks.get(k)
        if m is None:
            m = self._masks[k] = self._reader.read_mask(self.frame_indices[k])
        return m

    def render(self, k: int):
        """Cached ideal :class:`synth.render.RenderResult` of kept frame k (no colour)."""
        r = self._render.get(k)
        if r is None:
            r = self._render[k] = self.renderer.render(self.poses[k], self.intrinsics, with_rgb=False)
        return r

    def _masked_ideal(self, k: int) -> np.ndarray:
        """The ideal depth of kept frame k, 0 outside its mask when the sequence has masks (only the
        masked-in pixels have reference geometry). Cached: the same array object every call, so
        the :class:`~synth.lab.compare.CompareCache` (keyed by array identity) serves the frame's
        comparisons of a fit from its cache."""
        r = self.render(k)
        mask = self.mask(k)
        if mask is None:
            return r.depth
        if not hasattr(self, "_ideal_masked"):
            self._ideal_masked = {}
        d = self._ideal_masked.get(k)
        if d is None:
            d = self._ideal_masked[k] = np.where(mask, r.depth, np.float32(0.0)).astype(r.depth.dtype, copy=False)
        return d

    def default_config(self, effects=None):
        """``SensorConfig.build(self.preset, effects)``."""
        from synth.sensor.config import SensorConfig
        return SensorConfig.build(self.preset, effects)

    def simulator(self, config):
        """A :class:`~synth.sensor.simulator.SensorSimulator` of ``config`` sharing this
        sequence's renderer (its image size must be the measured one)."""
        from synth.sensor.simulator import SensorSimulator
        if tuple(config.preset.intrinsics.shape) != tuple(self.intrinsics.shape):
            raise RealgapError(f"{self.seq_dir}: the sensor model images {config.preset.width}x{config.preset.height} "
                               f"px but the measured depth is {self.intrinsics.width}x{self.intrinsics.height} px")
        return SensorSimulator(config, scene=self.scene, renderer=self.renderer, shared=self._sim_shared)

    def simulate(self, config, seed: int = 0, frames: Sequence[int] | None = None,
                 simulator=None) -> list[np.ndarray]:
        """Simulated (H, W) float32 depth (metres, 0 invalid) of each kept frame in ``frames``
        (positions into the kept frames; default all). Frame k uses the seed
        ``seed + frame_indices[k]`` and the cached ideal render."""
        sim = simulator if simulator is not None else self.simulator(config)
        out = []
        for k in self._frames(frames):
            res = sim.simulate(self.poses[k], seed=int(seed) + self.frame_indices[k],
                               prev_pose=self.prev_poses[k], render=self.render(k),
                               frame_index=self.frame_indices[k], timestamp_s=float(self.timestamps[k]))
            out.append(res.depth)
        return out

    def observation(self, k: int, simulated: np.ndarray) -> FrameObservation:
        """The :class:`FrameObservation` of kept frame k with a simulated depth image."""
        r = self.render(k)
        off = None if self.preset.type == "tof" else tuple(self.preset.projector_offset_m)
        if off is not None and not any(off):
            off = None
        ideal = self._masked_ideal(k)
        return FrameObservation(self.measured_depth(k), simulated, ideal, r.normals_cam, r.instance_ids,
                                self._material_names, self.intrinsics, off, self.frame_indices[k],
                                float(self.timestamps[k]))

    def observations(self, simulated: Sequence[np.ndarray], frames: Sequence[int] | None = None
                     ) -> list[FrameObservation]:
        """FrameObservations pairing measured and ``simulated`` depth (one per frame of
        ``frames``, default all kept frames, in that order)."""
        ks = self._frames(frames)
        if len(simulated) != len(ks):
            raise RealgapError(f"{self.seq_dir}: {len(simulated)} simulated images for {len(ks)} frames")
        return [self.observation(k, s) for k, s in zip(ks, simulated)]

    def describe(self) -> dict:
        """JSON-able summary (folder, frames kept/skipped, preset)."""
        return {"sequence": str(self.seq_dir), "frames": len(self), "frame_indices": self.frame_indices,
                "skipped_no_pose": self.skipped_no_pose, "preset": self.preset.name,
                "sensor_type": self.preset.type, "size": [self.intrinsics.width, self.intrinsics.height]}


def _previous_pose(poses: np.ndarray, times: np.ndarray, i: int, period: float) -> np.ndarray | None:
    """The pose one frame period before frame ``i`` for :attr:`MeasuredSequence.prev_poses`: the
    previous frame's (within 1.5 periods), else the next frame's motion extrapolated back (constant
    velocity, :func:`synth.sensor.state.interpolate_pose`), else None."""
    def usable(j: int) -> bool:
        return 0 <= j < len(poses) and bool(np.all(np.isfinite(poses[j]))) and abs(times[j] - times[i]) <= 1.5 * period
    if usable(i - 1):
        return np.array(poses[i - 1], copy=True)
    if usable(i + 1) and times[i + 1] > times[i]:
        from synth.sensor.state import interpolate_pose
        # the next frame sits at s = -1 of the path through it and frame i; one period back is s = +period/dt
        return interpolate_pose(poses[i], poses[i + 1], period / float(times[i + 1] - times[i]))
    return None

