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

__all__ = ["exit_with_parent"]


def exit_with_parent(poll_s: float = 0.5) -> None:
    """Make this (worker) process end, within ``poll_s`` seconds, when its parent process ends."""
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(1)
    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
