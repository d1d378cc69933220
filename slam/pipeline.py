"""The SLAM run loop: register every frame with a backend, fuse it into a TSDF, save a RUN folder.

RUN folder (the contract read by ``realgap eval run`` and ``realgap slam render``)::

    RUN/config.json      effective configuration (SlamConfig as JSON) + the sequence path
    RUN/camera.json      the camera used (intrinsics, depth scale)
    RUN/trajectory.txt   TUM, camera-to-world, one line per *registered* frame
    RUN/stats.json       backend, frames_per_second, per_frame [{timestamp, fitness,
                         inlier_rmse, failed, ...}], failed_timestamps, timings
    RUN/mesh.ply         mesh of the fused TSDF (vertex colours when colour is fused)
    RUN/volume.npz       the TSDF itself (only with ``save_volume``)
    RUN/checkpoint.json  while a run is unfinished: poses and backend state so far

Failed frames are listed in ``stats.json`` (``failed_timestamps``, ``per_frame``) and are not
in ``trajectory.txt``: evaluation sees only poses the backend vouches for, and the failures
are reported next to the accuracy.

Resuming: every ``checkpoint_every`` frames (and on Ctrl-C) the poses, per-frame statistics
and the backend state are written to ``checkpoint.json`` (atomically). Running the same
command again re-integrates the checkpointed frames into a fresh TSDF with their saved poses
(the fusion is deterministic, so the volume is the same as before the interruption) and
continues with the next frame. A finished run is not recomputed.

Offline backends (``colmap``) compute every pose in one go; an interruption during that step
starts it again, an interruption while fusing their poses resumes like an online run.

Overlap (``overlap``, on by default; :mod:`slam.overlap`): while frame t is tracked, frame t+1 is
read and frame t-1 fused on helper threads. Every read of the volume waits for a pending fusion
first, so the run gives the same bits as without overlap.

``frames_per_second`` counts the frames processed divided by the time spent reading,
registering and fusing them (not the re-integration after a resume, nor the final mesh
extraction).
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from data_tools.camera import Camera, read_camera_json, write_camera_json
from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.mesh import save_mesh
from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
from data_tools.sequence import SequenceReader
from data_tools.trajectory import Trajectory, read_tum, write_tum
from slam.registration import (TrackResult, check_positive, config_from_dict, config_to_dict,
                               get_backend)
from slam.loop_closure import LoopClosureConfig
from slam.overlap import BackgroundFusion, FrameReadAhead
from slam.tsdf import TSDFConfig, TSDFVolume

RUN_FILES = ("config.json", "camera.json", "checkpoint.json", "trajectory.txt", "trajectory_odometry.txt", "stats.json",
             "mesh.ply", "volume.npz", "volume.npz.json")
"""Files a run writes (and ``overwrite`` removes)."""


# --------------------------------------------------------------------------------------------
# configuration


@dataclass
class SlamConfig:
    """Everything that determines a SLAM run (saved as RUN/config.json)."""

    backend: str = "icp"
    """Registration backend: a module name of ``slam.backends`` (icp, rgbd_odometry, colmap)."""
    tsdf: TSDFConfig = field(default_factory=TSDFConfig)
    """TSDF fusion options (also the model that ``icp`` tracks against)."""
    backend_config: Any = None
    """Options of the chosen backend (its ``Config`` dataclass; None = its defaults)."""
    frame_step: int = 1
    """Use every n-th frame of the sequence."""
    max_frames: int = 0
    """The first N frames (after ``frame_step``); 0 = every frame (the command line's --max-frames takes N >= 1)."""
    checkpoint_every: int = 100
    """Write a resumable checkpoint every this many frames."""
    save_volume: bool = False
    """Also save the TSDF volume (RUN/volume.npz; large) for rendering from the volume."""
    overlap: bool = True
    """Read the next frame and fuse the last one on helper threads while a frame is tracked
    (online backends). The voxels are updated in the same order and every read of the volume
    waits for the fusion before it, so the results are the same bits as with ``false``; only
    the run time differs (the stages overlap on a second core)."""
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    """Loop closure after tracking (:mod:`slam.loop_closure`): keyframes, ORB candidates verified
    by ICP, a pose graph, the TSDF re-integrated with the corrected poses."""

    def __post_init__(self) -> None:
        if self.backend_config is None or isinstance(self.backend_config, dict):
            cls = get_backend(self.backend).Config
            self.backend_config = config_from_dict(cls, self.backend_config or {}, "backend_config")

    def validate(self) -> "SlamConfig":
        check_positive(self, "frame_step", "checkpoint_every")
        check_positive(self, "max_frames", allow_zero=True)
        self.tsdf.validate()
        self.loop_closure.validate()
        cls = get_backend(self.backend).Config
        if not isinstance(self.backend_config, cls):
            raise ConfigError(f"backend_config is a {type(self.backend_config).__name__}, backend "
                              f"{self.backend!r} needs {cls.__name__}")
        v = getattr(self.backend_config, "validate", None)
        if callable(v):
            v()
        return self

    def to_dict(self) -> dict:
        return config_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "config", strict: bool = False) -> "SlamConfig":
        """Build from JSON data (missing keys keep defaults; unknown keys are errors). ``strict``
        (data read from a file): a string where a number or boolean belongs is an error."""
        if not isinstance(d, dict):
            raise ConfigError(f"{where}: expected a JSON object")
        return config_from_dict(cls, d, where, strict=strict)


PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "fast": {"tsdf.voxel_size_m": 0.02, "tsdf.trunc_voxel_multiplier": 3.0},
    "fine": {"tsdf.voxel_size_m": 0.006, "tsdf.trunc_voxel_multiplier": 6.0, "tsdf.block_resolution": 16},
}
"""Named presets as dotted overrides of the defaults: ``default`` (1 cm voxels), ``fast``
(2 cm voxels: about 3x faster fusion and ray casting, coarser mesh and tracking model) and
``fine`` (6 mm voxels, for small objects / short range; 16-voxel blocks keep them about
10 cm wide: Open3D's ray caster leaves more holes with blocks of a few centimetres)."""


def make_config(backend: str = "icp", preset: str = "default", overrides: dict[str, Any] | None = None,
                base: dict | None = None) -> SlamConfig:
    """SlamConfig for ``backend`` from a preset (or a full JSON ``base``) plus dotted overrides
    such as ``{"tsdf.voxel_size_m": 0.02, "backend_config.min_fitness": 0.3}``."""
    if base is not None:
        cfg = SlamConfig.from_dict(base, strict=True)
        if backend and backend != cfg.backend:
            d = cfg.to_dict()
            d["backend"], d["backend_config"] = backend, {}
            cfg = SlamConfig.from_dict(d)
    else:
        if preset not in PRESETS:
            raise ConfigError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
        cfg = SlamConfig(backend=backend)
        if PRESETS[preset]:
            cfg = _apply(cfg, PRESETS[preset])
    if overrides:
        cfg = _apply(cfg, overrides)
    return cfg.validate()


def read_config_file(path: str | os.PathLike) -> dict:
    """The SlamConfig data of a JSON file: a saved config, or a run's config.json (its "config").
    Its types are checked strictly (a string where a number belongs is an error naming the file)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except json.JSONDecodeError as e:
        raise FormatError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    data = data.get("config", data) if isinstance(data, dict) else data
    try:
        SlamConfig.from_dict(data, strict=True)
    except ConfigError as e:
        raise FormatError(path, str(e)) from None
    return data


def _apply(cfg: SlamConfig, dotted: dict[str, Any]) -> SlamConfig:
    d = cfg.to_dict()
    for key, value in dotted.items():
        parts = key.split(".")
        node = d
        for p in parts[:-1]:
            if not isinstance(node, dict) or not isinstance(node.get(p), dict):
                raise ConfigError(f"unknown option {key!r}")
            node = node[p]
        if not isinstance(node, dict) or parts[-1] not in node:
            raise ConfigError(f"unknown option {key!r}")
        node[parts[-1]] = value
    return SlamConfig.from_dict(d)


# --------------------------------------------------------------------------------------------
# results


@dataclass
class SlamResult:
    """What a run produced (also readable back from a RUN folder with :func:`load_run`)."""

    run_dir: Path
    trajectory: Trajectory | None
    """Registered frames (camera-to-world); None while the run is incomplete."""
    stats: dict
    """Content of stats.json (or of the checkpoint while incomplete)."""
    config: SlamConfig
    camera: Camera
    complete: bool = True

    @property
    def failed_timestamps(self) -> list[float]:
        return list(self.stats.get("failed_timestamps", []))

    @property
    def frames_per_second(self) -> float:
        return float(self.stats.get("frames_per_second", float("nan")))


def _atomic_write(path: Path, text: str) -> None:
    from data_tools.results import atomic_write_text
    atomic_write_text(path, text)


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except json.JSONDecodeError as e:
        raise FormatError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None


def load_run(run_dir: str | os.PathLike) -> SlamResult:
    """Read a RUN folder written by :func:`run_slam` (finished or not)."""
    run = Path(run_dir)
    if not (run / "config.json").is_file():
        raise FormatError(run, "not a SLAM run folder (config.json missing)")
    meta = _read_json(run / "config.json")
    cfg = SlamConfig.from_dict(meta.get("config", {}), str(run / "config.json"))
    camera = read_camera_json(run / "camera.json")
    if (run / "stats.json").is_file():
        stats = _read_json(run / "stats.json")
        traj = read_tum(run / "trajectory.txt") if stats.get("frames_tracked", 0) > 0 else None
        return SlamResult(run, traj, stats, cfg, camera, bool(stats.get("complete", True)))
    stats = _read_json(run / "checkpoint.json") if (run / "checkpoint.json").is_file() else {}
    return SlamResult(run, None, stats, cfg, camera, False)


# --------------------------------------------------------------------------------------------
# the run loop


class _Progress:
    """A progress display on stderr (:func:`data_tools.progress.progress_bar`) or nothing."""

    def __init__(self, enabled: bool, total: int, initial: int, desc: str):
        self.bar = None
        if enabled:
            from data_tools.progress import progress_bar
            self.bar = progress_bar(total=total, initial=initial, desc=desc, unit="frame")

    def update(self, n=1, **post):
        if self.bar is not None:
            if post:
                self.bar.set_postfix(post, refresh=False)
            self.bar.update(n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _prepare_run_dir(out: Path, meta: dict, resume: bool, overwrite: bool) -> str:
    """'new', 'resume' or 'done'; raises when ``out`` holds something else."""
    if overwrite and out.exists():
        for name in RUN_FILES:
            (out / name).unlink(missing_ok=True)
    if (out / "config.json").is_file():
        old = _read_json(out / "config.json")
        if old.get("config") != meta["config"] or old.get("sequence") != meta["sequence"] \
                or old.get("camera") != meta["camera"]:
            diff = [k for k in ("sequence", "camera") if old.get(k) != meta[k]]
            if old.get("config") != meta["config"]:
                a, b = _flatten(old.get("config", {})), _flatten(meta["config"])
                diff += sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            raise RealgapError(f"{out}: holds a run with a different configuration ({', '.join(diff[:6])}); "
                               f"use --overwrite to replace it or choose another --out")
        if not resume:
            raise RealgapError(f"{out}: already holds a run (use --overwrite, or resume it)")
        stats_path = out / "stats.json"
        if stats_path.is_file() and _read_json(stats_path).get("complete"):
            return "done"
        return "resume" if (out / "checkpoint.json").is_file() else "new"
    if out.exists() and any(out.iterdir()):
        leftovers = [p.name for p in out.iterdir() if p.name in RUN_FILES]
        if leftovers:
            raise RealgapError(f"{out}: holds run files but no config.json ({', '.join(leftovers)}); use --overwrite")
    return "new"


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _make_backend(backend_cls, config, intr, tsdf_config, sensor):
    """``backend_cls(config, intr, tsdf_config, sensor=sensor)``; a backend written before the
    ``sensor`` argument existed (three-argument ``__init__``) gets it as an attribute."""
    import inspect
    params = inspect.signature(backend_cls.__init__).parameters
    if "sensor" in params or any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return backend_cls(config, intr, tsdf_config, sensor=sensor)
    backend = backend_cls(config, intr, tsdf_config)
    backend.sensor = sensor
    return backend


TRACKED_FRACTION_MIN = 0.5
"""A run that registers fewer than this fraction of its frames is a failed run (loud summary,
``slam run`` exit code 3, ``batch`` marks it failed): its trajectory and map are not usable."""


def poor_tracking(stats: dict) -> str | None:
    """The one-line reason a finished run counts as failed (fewer than
    :data:`TRACKED_FRACTION_MIN` of its frames registered), or None."""
    n, ok = int(stats.get("frames") or 0), int(stats.get("frames_tracked") or 0)
    if n and ok < TRACKED_FRACTION_MIN * n:
        return (f"only {ok} of {n} frames registered ({100 * ok / n:.0f} % < {100 * TRACKED_FRACTION_MIN:.0f} %): "
                f"the trajectory and map are not usable")
    return None


def run_slam(sequence: str | os.PathLike | SequenceReader, out: str | os.PathLike,
             config: SlamConfig | None = None, camera: Camera | None = None, resume: bool = True,
             overwrite: bool = False, progress: bool = True, stop_after: int | None = None,
             skip_unreadable: bool = False,
             on_frame: Callable[[int, TrackResult], None] | None = None) -> SlamResult:
    """Run registration + TSDF fusion over ``sequence`` and write the RUN folder ``out``.

    ``camera`` overrides the sequence's camera.json. With ``resume`` (default) an unfinished
    run in ``out`` with the same configuration is continued, a finished one is returned as is;
    ``overwrite`` starts afresh. ``stop_after`` processes at most that many new frames, then
    checkpoints and returns an incomplete result (used to test resuming). ``on_frame(index,
    result)`` is called after every frame. One writer at a time: ``out/lock.json`` holds the
    writer's pid (:class:`data_tools.outputs.output_lock`). A sequence folder marked incomplete
    (a generator still running or killed) gives a warning.
    """
    from data_tools.errors import warn

    from data_tools.outputs import incomplete_text, output_lock, read_incomplete
    cfg = (config or SlamConfig()).validate()
    check_output_dir(out, what="run folder")
    if not isinstance(sequence, SequenceReader):
        marker = read_incomplete(sequence)
        if marker is not None:
            warn(f"{sequence}: the sequence is unfinished ({incomplete_text(marker)}); the run uses the "
                          f"frames written so far")
    with output_lock(out, "realgap slam run"):
        return _run_slam(sequence, out, cfg, camera, resume, overwrite, progress, stop_after, skip_unreadable,
                         on_frame)


def _run_slam(sequence, out, cfg, camera, resume, overwrite, progress, stop_after, skip_unreadable,
              on_frame) -> SlamResult:
    reader = sequence if isinstance(sequence, SequenceReader) else SequenceReader(sequence, camera=camera)
    cam = reader.camera
    intr = cam.intrinsics
    out = Path(out)
    meta = {"sequence": str(Path(reader.path).resolve()), "camera": cam.to_json(), "config": cfg.to_dict()}
    state = _prepare_run_dir(out, meta, resume, overwrite)
    if state == "done":
        return load_run(out)
    out.mkdir(parents=True, exist_ok=True)
    _atomic_write(out / "config.json", json.dumps(meta, indent=2) + "\n")
    write_camera_json(out / "camera.json", cam)

    indices = list(range(0, len(reader), cfg.frame_step))
    if cfg.max_frames:
        indices = indices[: cfg.max_frames]
    backend_cls = get_backend(cfg.backend)
    backend = _make_backend(backend_cls, cfg.backend_config, intr, cfg.tsdf, cam.sensor)
    volume = TSDFVolume(cfg.tsdf)

    records: list[dict] = []
    poses: list[list[float] | None] = []
    timing = {"read_s": 0.0, "track_s": 0.0, "integrate_s": 0.0}
    pos = 0
    if state == "resume":
        ck = _read_json(out / "checkpoint.json")
        records, poses = ck["records"], ck["poses"]
        timing.update(ck.get("timing", {}))
        pos = int(ck["next"])
        if pos > len(indices) or len(records) != pos or len(poses) != pos:
            raise FormatError(out / "checkpoint.json", "inconsistent checkpoint (frame counts differ)")
        _reintegrate(reader, volume, records, poses, cfg, intr, progress)
        if backend_cls.online:
            backend.load_state(ck.get("backend_state", {}), reader, volume)

    def checkpoint(next_pos: int) -> None:
        _atomic_write(out / "checkpoint.json", json.dumps(
            {"next": next_pos, "records": records, "poses": poses, "timing": timing,
             "backend_state": backend.state_dict() if backend_cls.online else {}}) + "\n")
        mark_incomplete(out, "realgap slam run", next_pos, len(indices))

    mark_incomplete(out, "realgap slam run", pos, len(indices))

    if not backend_cls.online:
        if pos < len(indices):
            _run_offline(backend, reader, indices, volume, records, poses, timing, cfg, intr, progress)
            save = getattr(backend, "save_outputs", None)
            if save is not None:        # backend-specific outputs (the neural memory's snapshots)
                save(out)
            pos = len(indices)
            checkpoint(pos)
    else:
        bar = _Progress(progress, len(indices), pos, f"slam {cfg.backend}")
        n_new = 0
        frames = FrameReadAhead(reader, indices, cfg.overlap)
        fusing = BackgroundFusion(volume) if cfg.overlap else volume

        def settle() -> None:           # the pending background fusion finished
            if cfg.overlap:
                fusing.wait()
        try:
            while pos < len(indices):
                if stop_after is not None and n_new >= stop_after:
                    settle()
                    checkpoint(pos)
                    bar.close()
                    return load_run(out)
                i = indices[pos]
                try:
                    res = _process(frames, pos, backend, fusing, cfg, intr, timing, skip_unreadable)
                except FormatError:
                    settle()
                    checkpoint(pos)  # the frames before it are kept: a re-run continues here
                    bar.close()
                    raise
                records.append(res.record(reader.timestamps[i], i))
                poses.append(None if res.failed else res.pose.reshape(-1).tolist())
                pos += 1
                n_new += 1
                if on_frame is not None:
                    on_frame(i, res)
                spent = sum(timing.values())
                bar.update(1, fps=f"{pos / spent:.1f}" if spent > 0 else "-",
                           failed=sum(r["failed"] for r in records))
                if pos % cfg.checkpoint_every == 0 and pos < len(indices):
                    checkpoint(pos)
        except KeyboardInterrupt:
            settle()
            checkpoint(pos)
            bar.close()
            raise
        finally:
            frames.close()
        t0 = time.perf_counter()
        settle()
        timing["integrate_s"] += time.perf_counter() - t0
        if isinstance(getattr(backend, "stage_times", None), dict) and cfg.overlap:
            # waits for the background fusion inside the tracker (part of its time)
            backend.stage_times["fusion_wait"] = fusing.wait_s
        bar.close()
    # ---- loop closure (slam/loop_closure.py): after tracking, on the finished odometry
    loop_stats = None
    if backend_cls.online and cfg.loop_closure.applies_to(cfg.backend) and any(p is not None for p in poses):
        from slam.loop_closure import close_loops
        t0 = time.perf_counter()
        odometry = poses
        poses, new_volume, loop_stats = close_loops(reader, records, poses, cfg, intr, progress)
        timing["loop_s"] = time.perf_counter() - t0
        if new_volume is not None:
            volume = new_volume
            ok = [(r["timestamp"], np.asarray(p).reshape(4, 4)) for r, p in zip(records, odometry) if p is not None]
            write_tum(out / "trajectory_odometry.txt", Trajectory([t for t, _ in ok], [p for _, p in ok]),
                      header=f"realgap slam {cfg.backend}: odometry poses before loop closure")
    return _finish(out, reader, cfg, cam, volume, records, poses, timing, meta, backend, loop_stats)


def _process(frames, pos, backend, volume, cfg, intr, timing, skip_unreadable: bool = False) -> TrackResult:
    """Read, track and (every ``fuse_every``-th frame) fuse the frame at position ``pos``;
    ``volume`` is a TSDFVolume or its :class:`slam.overlap.BackgroundFusion`."""
    t0 = time.perf_counter()
    i = frames.indices[pos]
    try:
        frame = frames.get(pos)
    except FormatError as e:
        if not skip_unreadable:  # bad input is an error; --skip-unreadable makes it a failed frame
            raise FormatError(e.path, f"{e.problem} (frame {i}; pass --skip-unreadable to register the "
                                      f"sequence without it)") from None
        timing["read_s"] += time.perf_counter() - t0
        return TrackResult(None, None, None, True, f"unreadable frame: {e}")
    t1 = time.perf_counter()
    timing["read_s"] += t1 - t0
    res = backend.track(frame, volume)
    t2 = time.perf_counter()
    timing["track_s"] += t2 - t1
    if not res.failed and _fused(cfg, i):
        volume.integrate(frame.depth, frame.rgb, intr, res.pose)
        timing["integrate_s"] += time.perf_counter() - t2
    return res


def _fused(cfg: SlamConfig, index: int) -> bool:
    """Whether the registered frame ``index`` (of the sequence) is fused: every frame, or every
    n-th with a backend option ``fuse_every`` = n (counted after ``frame_step``)."""
    every = int(getattr(cfg.backend_config, "fuse_every", 1) or 1)
    return (index // cfg.frame_step) % every == 0


def _reintegrate(reader, volume, records, poses, cfg, intr, progress) -> None:
    todo = [(r["index"], p) for r, p in zip(records, poses) if p is not None and _fused(cfg, r["index"])]
    bar = _Progress(progress and len(todo) > 0, len(todo), 0, "resume: re-integrating")
    for i, p in todo:
        f = reader[i]
        volume.integrate(f.depth, f.rgb, intr, np.asarray(p, dtype=np.float64).reshape(4, 4))
        bar.update(1)
    bar.close()


def _run_offline(backend, reader, indices, volume, records, poses, timing, cfg, intr, progress) -> None:
    t0 = time.perf_counter()
    results = backend.run_offline(reader, indices, progress=progress)
    timing["track_s"] += time.perf_counter() - t0
    if len(results) != len(indices):
        raise RealgapError(f"backend {backend.name} returned {len(results)} results for {len(indices)} frames")
    bar = _Progress(progress, len(indices), 0, f"fusing ({backend.name} poses)")
    for i, res in zip(indices, results):
        records.append(res.record(reader.timestamps[i], i))
        poses.append(None if res.failed else res.pose.reshape(-1).tolist())
        if not res.failed and _fused(cfg, i):
            t1 = time.perf_counter()
            f = reader[i]
            t2 = time.perf_counter()
            volume.integrate(f.depth, f.rgb, intr, res.pose)
            timing["read_s"] += t2 - t1
            timing["integrate_s"] += time.perf_counter() - t2
        bar.update(1)
    bar.close()


def _finish(out, reader, cfg, cam, volume, records, poses, timing, meta, backend=None,
            loop_stats=None) -> SlamResult:
    ok = [(r["timestamp"], np.asarray(p).reshape(4, 4)) for r, p in zip(records, poses) if p is not None]
    failed = [r["timestamp"] for r in records if r["failed"]]
    spent = sum(timing.values())
    n = len(records)
    traj = Trajectory([t for t, _ in ok], [p for _, p in ok]) if ok else None
    mesh_info = None
    t_write = time.perf_counter()
    if traj is not None:
        write_tum(out / "trajectory.txt", traj,
                  header=f"realgap slam {cfg.backend}: camera-to-world poses of the registered frames")
        mesh = volume.extract_mesh()
        if len(mesh.triangles):
            save_mesh(out / "mesh.ply", mesh)
        mesh_info = {"vertices": int(len(mesh.vertices)), "triangles": int(len(mesh.triangles))}
        if cfg.save_volume:
            volume.save(out / "volume.npz")
    stats = {
        "backend": cfg.backend,
        "sequence": meta["sequence"],
        "frames": n,
        "frames_tracked": len(ok),
        "frames_failed": len(failed),
        "frames_relocalised": int(sum(r.get("relocalised", False) for r in records)),
        "frames_per_second": (n / spent) if spent > 0 else None,
        "seconds": spent,
        "timing_ms_per_frame": {k.removesuffix("_s"): (1000 * v / n if n else None) for k, v in timing.items()},
        "stage_ms_per_frame": {k: (1000 * v / n if n else None)
                               for k, v in getattr(backend, "stage_times", {}).items()},
        "write_s": time.perf_counter() - t_write,
        "failed_timestamps": failed,
        "mesh": mesh_info,
        "complete": True,
        "per_frame": records,
    }
    if loop_stats is not None:
        stats["loop_closure"] = loop_stats
    from data_tools.results import make_header, write_result
    header = make_header("slam.run", inputs={"sequence": meta["sequence"]}, parameters=cfg.to_dict(),
                         timings_s={k: v for k, v in timing.items()},
                         metrics={k: stats[k] for k in ("frames", "frames_tracked", "frames_failed",
                                                        "frames_relocalised", "frames_per_second")})
    write_result(out / "stats.json", header, stats, indent=1)
    (out / "checkpoint.json").unlink(missing_ok=True)
    clear_incomplete(out)
    if traj is None:
        raise RealgapError(f"{reader.path}: no frame could be registered ({len(failed)} failed; "
                           f"see {out / 'stats.json'})")
    return SlamResult(out, traj, stats, cfg, cam, True)
