"""The number of compute threads of a SLAM run (Open3D's OpenMP kernels and realgap's numba kernels).

Results do not depend on it: the TSDF integration and the ray casts write independent voxels and
pixels, and the registration sums use a fixed order (:mod:`slam.backends._p2p_kernel`); the
thread count only sets the speed (tests/test_slam_determinism.py checks 1 against 2 threads).
"""
from __future__ import annotations

from contextlib import contextmanager


def max_threads() -> int:
    """Threads numba may use in this process (NUMBA_NUM_THREADS, by default the CPU count)."""
    from numba import config
    return int(config.NUMBA_NUM_THREADS)


@contextmanager
def compute_threads(n: int):
    """Run the block with ``n`` threads for Open3D and numba kernels (capped at
    :func:`max_threads`), restoring the previous counts afterwards."""
    import numba

    from slam.tsdf import o3d_quiet
    o3d = o3d_quiet()
    n = max(1, min(int(n), max_threads()))
    before_o3d, before_nb = o3d.utility.get_max_threads(), numba.get_num_threads()
    o3d.utility.set_max_threads(n)
    numba.set_num_threads(n)
    try:
        yield n
    finally:
        o3d.utility.set_max_threads(before_o3d)
        numba.set_num_threads(before_nb)
