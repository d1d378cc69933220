"""Generate an ideal synthetic RGB-D sequence: scene -> trajectory -> ray-cast frames -> TUM folder.

:func:`generate_sequence` builds the scene (:func:`synth.scenes.build_scene`), a camera
trajectory (:data:`synth.trajectories.TRAJECTORY_KINDS`, optionally with hand-held jitter),
renders every pose with :class:`synth.render.IdealRenderer` and streams the frames to a
TUM-layout folder (``rgb/``, ``depth/``, ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``,
``camera.json`` without a ``sensor`` block since the depth is ideal, ``scene.json`` +
``meshes/``) plus ``config.json`` holding the effective :class:`SequenceConfig`.

Interrupted runs resume: with ``resume=True`` the frames already in the folder are kept and
rendering continues after them (the trajectory is regenerated identically from the saved
configuration, which must match).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from data_tools.camera import Camera, Intrinsics
from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.sequence import Frame, SequenceWriter, read_index

CONFIG_FILE = "config.json"
"""Name of the effective-configuration file written into the sequence folder."""


@dataclass(frozen=True)
class SequenceConfig:
    """Everything that determines a generated sequence (saved as ``OUT/config.json``)."""

    scene: str = "room"
    """Registered scene name (``realgap synth scenes`` lists them)."""
    scene_params: dict = field(default_factory=dict)
    """Extra keyword parameters of the scene builder, e.g. ``{"path": ".../room.obj"}``."""
    frames: int = 300
    """Number of frames to render."""
    fps: float = 30.0
    """Frame rate, frames per second (timestamps are i / fps seconds)."""
    trajectory: str = "walkthrough"
    """Trajectory kind: a name in :data:`synth.trajectories.TRAJECTORY_KINDS`."""
    seed: int = 0
    """Seed of the scene builder, the trajectory and the jitter."""
    jitter_trans_m: float = 0.002
    """Hand-held shake added to the trajectory: translation std per axis, metres (0 = off)."""
    jitter_rot_rad: float = 0.002
    """Hand-held shake: rotation std per axis, radians (0 = off)."""
    width: int = 640
    """Image width, pixels (Kinect v1-like default)."""
    height: int = 480
    """Image height, pixels."""
    fx: float = 580.0
    """Focal length along x, pixels."""
    fy: float = 580.0
    """Focal length along y, pixels."""
    cx: float = 319.5
    """Principal point x, pixels (pixel centres at integer coordinates)."""
    cy: float = 239.5
    """Principal point y, pixels."""
    depth_scale: float = 5000.0
    """Depth PNG units per metre (5000: TUM convention, 0.2 mm steps, 13.1 m range)."""

    def __post_init__(self) -> None:
        if not isinstance(self.scene_params, dict):
            raise ConfigError(f"scene_params must be a mapping, got {type(self.scene_params).__name__}")
        if int(self.frames) != self.frames or self.frames < 1:
            raise ConfigError(f"frames must be a positive integer, got {self.frames!r}")
        if not self.fps > 0:
            raise ConfigError(f"fps must be positive, got {self.fps}")
        if self.jitter_trans_m < 0 or self.jitter_rot_rad < 0:
            raise ConfigError("jitter_trans_m and jitter_rot_rad must be >= 0")
        if not self.depth_scale > 0:
            raise ConfigError(f"depth_scale must be positive, got {self.depth_scale}")
        try:
            self.intrinsics()
        except FormatError as e:
            raise ConfigError(f"bad camera in sequence config: {e.problem}") from None

    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    def camera(self) -> Camera:
        """camera.json content: intrinsics, depth scale, no sensor block (ideal depth)."""
        return Camera(self.intrinsics(), float(self.depth_scale), None)

    def with_resolution(self, width: int, height: int) -> "SequenceConfig":
        """The same camera resampled to ``width`` x ``height`` pixels (focal lengths and
        principal point scaled, pixel-centre convention kept)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
                       cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict, path: str | Path | None = None) -> "SequenceConfig":
        if not isinstance(d, dict):
            raise FormatError(path, "sequence config must be a JSON object")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise FormatError(path, f"unknown sequence config key(s): {', '.join(unknown)}")
        try:
            return cls(**d)
        except (TypeError, ValueError) as e:
            raise FormatError(path, f"bad sequence config ({e})") from None
        except ConfigError as e:
            raise FormatError(path, str(e)) from None


SEQUENCE_PRESETS: dict[str, SequenceConfig] = {
    "kinect_v1": SequenceConfig(),
    "small": SequenceConfig(frames=30).with_resolution(320, 240),
}
"""Named starting configurations: ``kinect_v1`` = the defaults (640x480, f = 580 px, 300
frames at 30 fps); ``small`` = 30 frames at 320x240 for quick looks."""


@dataclass
class GenerateResult:
    """What :func:`generate_sequence` did."""

    out_dir: Path
    """The sequence folder."""
    frames_total: int
    """Frames in the folder now."""
    frames_written: int
    """Frames rendered and written by this call."""
    frames_skipped: int
    """Frames already present and kept (resume)."""
    empty_frames: int
    """Frames written by this call in which no pixel saw geometry (all-zero depth)."""
    render_ms_mean: float
    """Mean ray-casting time per written frame, milliseconds (NaN if none written)."""
    seconds: float
    """Wall time of the call, seconds."""
    config: SequenceConfig
    """The effective configuration."""

    def to_json(self) -> dict:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        d["config"] = self.config.to_json()
        return d


def _check_resume_config(out_dir: Path, config: SequenceConfig) -> None:
    p = out_dir / CONFIG_FILE
    if not p.exists():
        return
    try:
        old = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise FormatError(p, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    new = json.loads(json.dumps(config.to_json()))
    diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    if diff:
        raise ConfigError(f"{out_dir}: cannot resume, the configuration differs from {p.name} in "
                          f"{', '.join(diff)} (use --overwrite to start again)")


def make_sequence_trajectory(config: SequenceConfig, scene):
    """The trajectory of a configuration: the registered kind plus hand-held jitter."""
    from synth.trajectories import handheld_jitter, make_trajectory
    traj = make_trajectory(config.trajectory, scene, config.frames, seed=config.seed, fps=config.fps)
    if config.jitter_trans_m > 0 or config.jitter_rot_rad > 0:
        shaken = handheld_jitter(traj, seed=config.seed + 1, trans_sigma_m=config.jitter_trans_m,
                                 rot_sigma_rad=config.jitter_rot_rad)
        if config.trajectory == "planar":       # a ground robot shakes in x, y and yaw only
            shaken = _keep_planar(traj, shaken)
        traj = shaken
    return traj


def _keep_planar(ref, shaken):
    """``shaken`` with the height, pitch and roll of ``ref`` (its x, y and yaw kept)."""
    import math

    from data_tools.geometry import look_at
    from data_tools.trajectory import Trajectory
    poses = shaken.poses.copy()
    for i, (a, b) in enumerate(zip(ref.poses, shaken.poses)):
        f_ref, f_new = a[:3, 2], b[:3, 2]
        yaw = math.atan2(f_new[1], f_new[0])
        h = math.hypot(f_ref[0], f_ref[1])
        eye = np.array([b[0, 3], b[1, 3], a[2, 3]])
        poses[i] = look_at(eye, eye + np.array([h * math.cos(yaw), h * math.sin(yaw), f_ref[2]]))
    return Trajectory(shaken.timestamps.copy(), poses)


def _check_ideal_dir(config: SequenceConfig, out_dir: str | Path, resume: bool, overwrite: bool) -> Path:
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise RealgapError(f"{out_dir}: exists and is not a folder")
    if resume and overwrite:
        raise ConfigError("choose either resume or overwrite, not both")
    if resume:
        _check_resume_config(out_dir, config)
    return out_dir


def _open_ideal(config: SequenceConfig, out_dir: str | Path, resume: bool, overwrite: bool, camera=None,
                scene=None):
    """Checks, scene, trajectory and the ideal sequence's writer (config.json written); returns
    (out_dir, scene, trajectory, writer, frames already there). ``camera``: that of the folder
    (default the configuration's)."""
    from synth.scenes import build_scene
    out_dir = _check_ideal_dir(config, out_dir, resume, overwrite)
    if scene is None:
        scene = build_scene(config.scene, seed=config.seed, **config.scene_params)
    traj = make_sequence_trajectory(config, scene)
    writer = SequenceWriter(out_dir, camera or config.camera(), scene=scene, resume=resume, overwrite=overwrite,
                            expected_frames=len(traj), command="realgap synth sequence")
    from data_tools.results import atomic_write_json
    atomic_write_json(out_dir / CONFIG_FILE, config.to_json())
    start = len(writer)
    if start > len(traj):
        raise ConfigError(f"{out_dir}: holds {start} frames, more than the {len(traj)} configured")
    if start:
        last = read_index(out_dir / "depth.txt")[0][-1]
        if not np.isclose(last, traj.timestamps[start - 1], atol=1e-6):
            raise ConfigError(f"{out_dir}: last written timestamp {last:.6f} does not match frame {start} "
                              f"of the configured trajectory ({traj.timestamps[start - 1]:.6f})")
    return out_dir, scene, traj, writer, start


def generate_sequence(config: SequenceConfig, out_dir: str | Path, resume: bool = False,
                      overwrite: bool = False, progress: bool = True) -> GenerateResult:
    """Render ``config`` into the sequence folder ``out_dir`` (see the module docstring).

    ``resume`` keeps the frames already written and continues after them (the saved
    config.json must match ``config``); ``overwrite`` starts again in an existing folder;
    with neither, an existing sequence is an error. Frames whose view holds no geometry are
    written too (all-zero depth) and counted in ``empty_frames``.
    """
    from data_tools.progress import progress_bar
    from synth.render import IdealRenderer

    t_start = time.perf_counter()
    out_dir, scene, traj, writer, start = _open_ideal(config, out_dir, resume, overwrite)
    renderer = IdealRenderer(scene)
    intr = config.intrinsics()
    empty = 0
    render_s = 0.0
    with progress_bar(total=len(traj), initial=start, desc=f"synth {config.scene}", unit="frame",
                      enabled=progress) as bar:
        for i in range(start, len(traj)):
            t0 = time.perf_counter()
            res = renderer.render(traj.poses[i], intr, with_rgb=True)
            render_s += time.perf_counter() - t0
            if not res.hit.any():
                empty += 1
            writer.write(Frame(float(traj.timestamps[i]), res.depth, res.rgb, traj.poses[i], i))
            bar.update(1)
    n_written = len(traj) - start
    return GenerateResult(out_dir, len(writer), n_written, start, empty,
                          render_s / n_written * 1e3 if n_written else float("nan"),
                          time.perf_counter() - t_start, config)


def generate_sensor_sequence(config: SequenceConfig, ideal_dir: str | Path, sim_dir: str | Path,
                             sensor="kinect_v1", effects=None, *, resume: bool = False,
                             overwrite: bool = False, progress: bool = True,
                             workers: int = 1) -> tuple[GenerateResult, int]:
    """Render ``config`` into ``ideal_dir`` (ground truth, ideal depth and colour, as
    :func:`generate_sequence` writes them) and simulate the depth sensor on the same poses into
    ``sim_dir`` (TUM layout with ``sensor_config.json``; frame i uses seed ``config.seed + i``, see
    :func:`synth.sensor.simulate_trajectory`). ``sensor`` and ``effects`` are those of
    :class:`synth.sensor.SensorSimulator` (a preset name or a SensorConfig, 'physical',
    'direct' or effect names); ``resume`` / ``overwrite`` apply to both folders; ``workers`` > 1
    simulates frames in parallel processes (same frames).

    One pass: the simulator's own ideal render of each frame (depth and colour, in the sensor's
    image grid, whatever the configuration's size) is the ideal sequence's frame, so every view is
    rendered once and the colour image is encoded once (the
    simulated sequence's ``rgb/`` files are hard links to the ideal ones, copies where the file
    system has no links). Each folder continues from its own last frame. Returns (the ideal
    sequence's :class:`GenerateResult`, frames simulated now)."""
    from data_tools.camera import Camera
    from synth.scenes import build_scene
    from synth.sensor import SensorSimulator, simulate_trajectory
    t_start = time.perf_counter()
    ideal_dir, sim_dir = Path(ideal_dir), Path(sim_dir)
    resume_ideal = resume and (ideal_dir / "depth.txt").exists()
    scene = build_scene(config.scene, seed=config.seed, **config.scene_params)
    sim = SensorSimulator(sensor, effects, scene)
    # the ideal frames are rendered on the sensor's grid: ideal/config.json says so (not the preset's size)
    k = sim.preset.intrinsics
    config = replace(config, width=int(k.width), height=int(k.height), fx=float(k.fx), fy=float(k.fy),
                     cx=float(k.cx), cy=float(k.cy))
    _check_ideal_dir(config, ideal_dir, resume_ideal, overwrite)
    # the ideal frames are the simulator's renders: the sensor's image grid (pixel-aligned with
    # the simulated depth), no sensor block
    ideal_cam = Camera(sim.preset.intrinsics, sim.camera().depth_scale)
    ideal_dir, scene, traj, iw, i_start = _open_ideal(config, ideal_dir, resume_ideal, overwrite, ideal_cam, scene)
    stats = {"empty": 0, "render_ms": 0.0}

    def write_ideal(i: int, res) -> Path | None:
        """The ideal frame i from the simulation result; returns its colour file (to link)."""
        if not res.ideal_depth.any():
            stats["empty"] += 1
        stats["render_ms"] += float(res.log.get("timings_ms", {}).get("render", float("nan")))
        enc = res.encoded or {}
        iw.write(Frame(float(traj.timestamps[i]), res.ideal_depth, res.rgb, traj.poses[i], i,
                       encoded={"depth": enc.get("ideal_depth"), "rgb": enc.get("rgb"),
                                "depth_scale": enc.get("depth_scale")}))
        return iw.last_rgb_path

    with SequenceWriter(sim_dir, sim.camera(), scene, resume=resume, overwrite=overwrite,
                        expected_frames=len(traj), command="realgap synth sequence --sensor") as w:
        sim.config.save(sim_dir / "sensor_config.json")
        n = simulate_trajectory(sim, traj.poses, traj.timestamps, w, seed=config.seed, progress=progress,
                                workers=workers, ideal=(i_start, write_ideal))
    n_ideal = len(traj) - i_start
    ideal_res = GenerateResult(ideal_dir, len(iw), n_ideal, i_start, stats["empty"],
                               stats["render_ms"] / n_ideal if n_ideal else float("nan"),
                               time.perf_counter() - t_start, config)
    return ideal_res, n


def generate_simulated_sequence(config: SequenceConfig, out_dir: str | Path, sensor="kinect_v1", effects=None, *,
                                resume: bool = False, overwrite: bool = False, progress: bool = True,
                                workers: int = 1) -> tuple[GenerateResult, int]:
    """``synth sequence --sensor``: the simulated sequence in ``out_dir`` and the ideal one (ground
    truth, ideal depth) in ``out_dir/ideal`` (:func:`generate_sensor_sequence`). ``overwrite``
    removes ``out_dir`` first. Returns (the ideal sequence's result, frames simulated now)."""
    import shutil
    out = Path(out_dir)
    if overwrite and out.exists():
        shutil.rmtree(out)
    return generate_sensor_sequence(config, out / "ideal", out, sensor, effects, resume=resume, workers=workers,
                                    progress=progress)
