"""Overlapping the stages of the run loop on helper threads, without changing a bit of the result.

While frame t is tracked, frame t+1 is read (:class:`FrameReadAhead`) and frame t-1 fused
(:class:`BackgroundFusion`) on helper threads: image decoding and Open3D's integration release the
GIL, so on two cores they run beside the tracker. The fusion is made invisible to the result: a
volume read of any kind waits for the pending fusion first, and fusions run one at a time in
frame order, so the voxels see the same updates in the same order, and the tracker the same model,
as without overlap (``tests/test_slam_determinism.py`` compares the bytes).
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

_FUSION_POOL: ThreadPoolExecutor | None = None


def _fusion_pool() -> ThreadPoolExecutor:
    """The one helper thread of background fusions (created on first use)."""
    global _FUSION_POOL
    if _FUSION_POOL is None:
        _FUSION_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tsdf-fusion")
    return _FUSION_POOL


class BackgroundFusion:
    """A :class:`slam.tsdf.TSDFVolume` whose :meth:`integrate` runs on a helper thread.

    Every other attribute is the volume's, read after the pending fusion has finished (so the
    tracker's ray cast, the mesh and a save see every frame fused so far); ``frames_integrated``
    counts the frames handed over, pending or not, and is read without waiting (the tracker asks
    it every frame to decide whether its model view is current). An error of a background fusion
    is raised by the next wait."""

    def __init__(self, volume):
        self._volume = volume
        self._pending = None
        self.frames_integrated = volume.frames_integrated
        """Frames fused so far, counting one still being fused."""
        self.wait_s = 0.0
        """Seconds spent waiting for a fusion to finish (the part that did not overlap other work)."""

    @property
    def volume(self):
        """The wrapped volume, after any pending fusion."""
        self.wait()
        return self._volume

    def wait(self) -> None:
        """Finish the pending fusion (re-raising its error, if any)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            t0 = time.perf_counter()
            try:
                pending.result()
            finally:
                self.wait_s += time.perf_counter() - t0

    def integrate(self, depth_m, rgb, intr, pose_c2w) -> None:
        """Hand one frame to the helper thread (the arguments of :meth:`TSDFVolume.integrate`;
        the caller must not modify the arrays afterwards) and return at once."""
        self.wait()
        self._pending = _fusion_pool().submit(self._volume.integrate, depth_m, rgb, intr, pose_c2w)
        self.frames_integrated += 1

    def __getattr__(self, name: str):
        if name.startswith("__") or name in ("_volume", "_pending"):
            raise AttributeError(name)
        self.wait()
        return getattr(self._volume, name)


class FrameReadAhead:
    """The frames ``reader[indices[pos]]`` of a run in order; with ``ahead``, the next frame is read
    on a helper thread while the current one is processed. A read error surfaces when its frame is
    asked for, as without read-ahead."""

    def __init__(self, reader, indices: list[int], ahead: bool):
        self.reader, self.indices, self._next = reader, indices, None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="slam-read") if ahead else None

    def get(self, pos: int):
        """The frame at position ``pos`` of ``indices`` (raises the reader's errors)."""
        if self._pool is None:
            return self.reader[self.indices[pos]]
        nxt, self._next = self._next, None
        if nxt is not None and nxt[0] == pos:
            fut = nxt[1]
        else:
            fut = self._pool.submit(self.reader.__getitem__, self.indices[pos])
        if pos + 1 < len(self.indices):
            self._next = (pos + 1, self._pool.submit(self.reader.__getitem__, self.indices[pos + 1]))
        return fut.result()

    def close(self) -> None:
        """Stop the helper thread (a frame read ahead is dropped)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
