"""numba plumbing and the thread count shared by realgap's compiled kernels and ray queries
(synth.render, synth.sensor).

:func:`kernel` compiles a function on first use and caches the machine code on disk
(``cache=True``: later processes load it in ~0.1 s), releases the GIL (``nogil=True``) so that
:func:`run_row_bands` can run image row bands in threads, and keeps strict IEEE float
semantics (no ``fastmath``). numba is a required dependency (pyproject). On a broken install
without it, :func:`available` is False, the ideal renderer falls back to Open3D's ray cast,
and the sensor kernels run as plain Python: the same results, about 100x slower, with a
warning at import.
"""
from __future__ import annotations

import os

try:
    import numba as _nb
except ImportError:  # pragma: no cover - exercised only on a broken install
    _nb = None
    from data_tools.errors import warn
    warn("numba is not installed: the sensor simulator's kernels run as plain Python "
                  "(about 100x slower); install the project's dependencies (make setup)")


THREADS: int | None = None
"""Threads for realgap's parallel work (Open3D ray queries, row bands of the compiled kernels);
None = the CPUs this process may use. Set to 1 in worker processes that each simulate their own
frame (:class:`synth.sensor.pool.SimulationPool`)."""


def n_threads() -> int:
    """:data:`THREADS`, or the CPUs this process may use (Open3D's automatic choice counts the
    host's CPUs and oversubscribes a restricted container)."""
    if THREADS:
        return int(THREADS)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def available() -> bool:
    """True when numba is importable (the compiled kernels can run)."""
    return _nb is not None


def kernel(fn):
    """Decorator: ``numba.njit(cache=True, nogil=True)`` (plain Python without numba)."""
    return _nb.njit(cache=True, nogil=True, fastmath=False)(fn) if _nb is not None else fn


def run_row_bands(fn, H: int, n_threads: int, block: int = 16) -> None:
    """Call ``fn(r0, r1)`` over the rows [0, H) in bands, on ``n_threads`` threads when > 1
    (``fn`` must write only its own rows). Bands are interleaved in blocks of ``block`` rows so
    that the work of a view whose content sits in one part of the image is still shared evenly."""
    n = max(1, min(int(n_threads), H))
    if n == 1:
        fn(0, H)
        return
    blk = max(1, int(block))
    edges = list(range(0, H, blk)) + [H]
    chunks = [(edges[i], edges[i + 1]) for i in range(len(edges) - 1)]

    def run(j: int) -> None:
        for a, b in chunks[j::n]:
            fn(a, b)

    list(thread_pool(n).map(run, range(n)))


def thread_pool(n: int):
    """The process's shared ThreadPoolExecutor with at least ``n`` threads (a new one after a
    fork: a forked child has none of its parent's threads). Tasks run on it must not wait for
    other tasks of it (no nesting: that could deadlock)."""
    global _POOL
    from concurrent.futures import ThreadPoolExecutor
    if _POOL is None or _POOL._max_workers < n:
        if _POOL is not None:
            _POOL.shutdown(wait=False)
        _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="realgap-bands")
    return _POOL


_POOL = None


def _forget_pool() -> None:
    """After a fork the pool's threads do not exist in the child: start a new pool there."""
    global _POOL
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
