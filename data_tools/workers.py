"""Worker processes that do not outlive the command that started them.

A killed command (SIGKILL, an out-of-memory kill, a closed terminal) runs no clean-up, so the
worker processes of its pools (``synth sequence --workers``, ``batch``) would keep running as
orphans, holding CPU and memory (seen: a killed ``batch`` left its worker finishing a SLAM run
into the folder that the re-run was resuming). Every pool initialiser calls
:func:`exit_with_parent`: a daemon thread polls the parent's process id twice a second and ends
the worker when the parent is gone. (``prctl(PR_SET_PDEATHSIG)`` is not used: it fires when the
parent *thread* that spawned the worker ends, which would kill healthy workers spawned from a
short-lived thread.)
"""
from __future__ import annotations

import os
import threading
import time

__all__ = ["exit_with_parent", "keep_freed_memory"]


def exit_with_parent(poll_s: float = 0.5) -> None:
    """Make this (worker) process end, within ``poll_s`` seconds, when its parent process ends."""
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(1)
    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def keep_freed_memory(limit_bytes: int = 1 << 30) -> bool:
    """Let this (worker) process reuse the memory it frees instead of returning it to the kernel.

    glibc's malloc serves every allocation above 128 kB-32 MB (its adaptive mmap threshold) by a
    fresh ``mmap`` and gives it back with ``munmap`` on free, so a worker that allocates the same
    few dozen VGA arrays per frame pays a page fault for every 4 kB page of each of them, every
    frame (measured on the sensor simulator: ~15 ms of system CPU per frame, ~10 % of the frame).
    Raising the mmap threshold to 32 MB and the trim threshold to ``limit_bytes`` (``mallopt``) keeps the
    pages in the heap for reuse; the process's resident memory stays at its peak instead of
    shrinking between frames. Linux/glibc only; returns False (and changes nothing) elsewhere."""
    import ctypes
    import ctypes.util
    import sys
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
    ok = mallopt(M_MMAP_THRESHOLD, 32 << 20) == 1     # glibc's largest allowed value on 64-bit: arrays up to 32 MB
    ok &= mallopt(M_TRIM_THRESHOLD, int(limit_bytes)) == 1
    ok &= mallopt(M_TOP_PAD, 64 << 20) == 1
    return bool(ok)
