"""One progress display for every long job: a tqdm bar on a terminal, plain lines elsewhere.

A tqdm bar redraws itself with carriage returns, which fill a log file (``realgap ... 2> log``, a
CI job, a batch system) with hundreds of partial lines. :func:`progress_bar` gives tqdm only when
stderr is a terminal; otherwise a :class:`LineProgress` that writes one line when it starts, one
per ``LINE_STEP`` of the work but never more often than every ``LINE_MIN_SECONDS`` (a log of a
fast job gets its first and last line only), at least every ``LINE_SECONDS``, and one when it
closes::

    synth room: 0/100 frame
    synth room: 10/100 frame (9.8 s, 0.98 s/frame)
    ...
    synth room: 100/100 frame done (97.6 s)

Both have ``update(n)``, ``set_postfix_str(text)``, ``close()``, iteration (with ``iterable``) and
``with``. ``enabled=False`` gives a silent object with the same interface; so does every bar after
:func:`set_progress_enabled` (False) — the CLI's ``--no-progress`` — or with ``REALGAP_NO_PROGRESS=1``.
"""
from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable

__all__ = ["progress_bar", "LineProgress", "LINE_STEP", "LINE_SECONDS", "LINE_MIN_SECONDS", "set_progress_enabled"]

_ENABLED = True


def set_progress_enabled(enabled: bool) -> None:
    """Switch every progress display of this process on or off (``--no-progress``)."""
    global _ENABLED
    _ENABLED = bool(enabled)


def _globally_enabled() -> bool:
    return _ENABLED and os.environ.get("REALGAP_NO_PROGRESS", "") in ("", "0")

LINE_STEP = 0.1
"""A line every this fraction of the total (10 %)."""
LINE_SECONDS = 60.0
"""... and at least this often while work goes on, seconds."""
LINE_MIN_SECONDS = 5.0
"""... but never more often than this, seconds (a log is not a frame counter)."""


class LineProgress:
    """Progress as whole lines (for logs); see the module docstring."""

    def __init__(self, iterable: Iterable | None = None, total: int | None = None, desc: str = "",
                 unit: str = "it", initial: int = 0, enabled: bool = True, file=None):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable) + initial
        self.total, self.desc, self.unit, self.n = total, desc, unit, int(initial)
        self.enabled, self.file = enabled, file
        self.postfix = ""
        self._t0 = self._last_t = time.perf_counter()
        self._start_n = self.n
        self._next = self._step_after(self.n)
        self._closed = False
        self._print("")

    def _step_after(self, n: int) -> float:
        if not self.total:
            return float("inf")
        step = max(1, int(round(self.total * LINE_STEP)))
        return (n // step + 1) * step

    def _print(self, extra: str) -> None:
        if not self.enabled:
            return
        tot = f"/{self.total}" if self.total else ""
        post = f" [{self.postfix}]" if self.postfix else ""
        print(f"{self.desc}: {self.n}{tot} {self.unit}{extra}{post}", file=self.file or sys.stderr, flush=True)

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        now = time.perf_counter()
        since = now - self._last_t
        if (self.n >= self._next and since >= LINE_MIN_SECONDS) or since >= LINE_SECONDS:
            self._next = self._step_after(self.n)
            self._last_t = now
            el = now - self._t0
            done = self.n - self._start_n
            rate = f", {el / done:.3g} s/{self.unit}" if done > 0 else ""
            self._print(f" ({el:.1f} s{rate})")

    def set_postfix_str(self, text: str, refresh: bool = False) -> None:
        self.postfix = str(text)

    def set_postfix(self, values: dict, refresh: bool = False) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._print(f" done ({time.perf_counter() - self._t0:.1f} s)")

    def __iter__(self):
        for x in self.iterable:
            yield x
            self.update(1)
        self.close()

    def __enter__(self) -> "LineProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress_bar(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "", unit: str = "it",
                 initial: int = 0, enabled: bool = True, leave: bool = True, file=None):
    """tqdm on stderr when it is a terminal, else :class:`LineProgress`; ``enabled=False``: silent."""
    out = file or sys.stderr
    enabled = enabled and _globally_enabled()
    if enabled and getattr(out, "isatty", lambda: False)():
        from tqdm import tqdm
        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, leave=leave, file=out,
                    dynamic_ncols=True)
    return LineProgress(iterable, total=total, desc=desc, unit=unit, initial=initial, enabled=enabled, file=out)
