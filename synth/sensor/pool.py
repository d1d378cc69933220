"""Simulating many frames: :func:`simulate_trajectory` (a trajectory into a sequence writer,
resumable) and :class:`SimulationPool` (frames in worker processes, results through shared memory;
identical to serial frames)."""
from __future__ import annotations


import numpy as np

from data_tools.errors import ConfigError, RealgapError
from synth.sensor.config import SensorConfig
from synth.sensor.simulator import SensorSimulator, SimResult

__all__ = ["simulate_trajectory", "SimulationPool"]


def simulate_trajectory(sim: SensorSimulator, poses_c2w: np.ndarray, timestamps: np.ndarray, writer,
                        seed: int = 0, motion: bool = True, with_rgb: bool = True, progress: bool = True,
                        workers: int = 1, ideal=None) -> int:
    """Simulate every pose and append the frames to a :class:`data_tools.sequence.SequenceWriter`
    (open it with ``camera=sim.camera()``); frames already in the writer (``len(writer)``, a
    resumed run) are skipped, so the result is identical to an uninterrupted run (frame i
    always uses seed ``seed + i`` and pose i - 1 as its previous pose; where that implies more
    than ``sim.config.motion`` allows, the frame is a cut - static - and the progress bar counts
    it). Returns the number of frames written now. ``workers`` > 1 simulates that many frames
    at once in worker processes (:class:`SimulationPool`: more frames per second when cores are
    free, identical frames, a few seconds of start-up); frames are still written in order.
    ``ideal = (start, write)``: also hand every result of frame i >= start to ``write(i, result)``
    (the ideal sequence of ``synth sequence --sensor``), which returns the colour file it wrote
    (linked, not encoded again, into this writer's sequence) or None; simulation starts at the
    first frame either sequence lacks.

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
    sim_start = len(writer)
    ideal_start, write_ideal = ideal if ideal is not None else (len(poses), None)
    start = min(sim_start, ideal_start)
    idx = range(start, len(poses))
    if progress:
        from data_tools.progress import progress_bar
        idx = progress_bar(idx, desc=f"simulating {sim.preset.name}", initial=start, total=len(poses), unit="frame")
    prevs = [poses[i - 1] if (motion and i > 0) else None for i in range(len(poses))]
    n_workers = min(int(workers), len(poses) - start)   # no more processes than frames left
    pool = SimulationPool(sim, workers=n_workers) if n_workers > 1 else None
    from data_tools.workers import keep_freed_memory
    keep_freed_memory()     # this process copies every frame out of the pool / simulates it: no page faults
    if pool is None:
        results = (sim.simulate(poses[i], seed=seed + i, prev_pose=prevs[i], with_rgb=with_rgb, frame_index=i,
                                timestamp_s=float(ts[i])) for i in range(start, len(poses)))
    else:
        results = pool.map(poses[start:], [seed + i for i in range(start, len(poses))], prevs[start:],
                           with_rgb=with_rgb, keep_draws=False,  # frames are written, draws not kept
                           frame_indices=range(start, len(poses)), timestamps=ts[start:],
                           encode_depth_scale=float(writer.camera.depth_scale))  # PNGs made in the workers
    n = cuts = 0
    try:
        for i, res in zip(idx, results):
            rgb_file = write_ideal(i, res) if write_ideal is not None and i >= ideal_start else None
            if i < sim_start:
                continue
            writer.write(res.to_frame(ts[i], i), rgb_link=rgb_file)
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
            with_rgb: bool = False, keep_draws: bool = True, frame_indices=None, timestamps=None,
            encode_depth_scale: float | None = None):
        """Yield ``simulate(poses_c2w[i], seed=seeds[i], prev_pose=prev_poses[i], with_rgb=with_rgb,
        frame_index=frame_indices[i], timestamp_s=timestamps[i])`` in order, with at most ``max_in_flight`` (default 2 x workers) frames submitted ahead.
        ``keep_draws=False`` returns results with empty ``draws`` (a caller that only writes the
        frames saves shipping them: ~20 % of each VGA result). ``encode_depth_scale``: the workers
        also encode the result's images as the PNG files of a sequence with that depth scale
        (:meth:`SimResult.encode`), so the writing process only copies bytes; then only ``depth``,
        ``valid``, ``ideal_depth`` and ``rgb`` of the arrays come back (``normals``,
        ``instance_ids``, ``ir`` and ``disparity`` are None: what a sequence writer needs)."""
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
                                            self.slot_bytes, with_rgb, keep_draws, idx[i], ts[i],
                                            encode_depth_scale), slot))
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
    from data_tools.workers import exit_with_parent, keep_freed_memory
    exit_with_parent()
    keep_freed_memory()
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
                   keep_draws: bool = True, frame_index: int | None = None, timestamp_s: float | None = None,
                   encode_depth_scale: float | None = None):
    """Simulate one frame (its draws dropped unless ``keep_draws``); its arrays go into the
    shared-memory slot when they fit: ("shm", result without them, [(key, dtype, shape,
    offset)]), else ("pickle", result)."""
    res = _POOL_SIM.simulate(pose, seed=seed, prev_pose=prev, with_rgb=with_rgb, frame_index=frame_index,
                             timestamp_s=timestamp_s)
    if not keep_draws:
        res.draws = {}
    if encode_depth_scale is not None:    # a sequence writer's frame: the PNGs, depth, ideal depth and colour
        res.encode(float(encode_depth_scale))
        res.normals = res.instance_ids = res.ir = res.disparity = None
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
