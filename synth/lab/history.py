"""Gap history of the sensor lab: "add an effect and watch the error fall".

``DIR/history.json`` holds one entry per compare run, oldest first::

    {"version": 1,
     "entries": [{"step": 0, "timestamp": "2025-01-01T12:00:00+00:00",
                  "effects": ["noise"], "gap": 0.83, "label": "noise only"}, ...]}

``timestamp`` is ISO 8601 UTC, ``effects`` the names of the simulator effects switched on for
that run, ``gap`` the :attr:`CompareResult.gap`, ``label`` optional free text. A run in a new
folder can continue the history of an earlier folder (``compare_against``).
"""
from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path

from data_tools.errors import FormatError, RealgapError

HISTORY_FILE = "history.json"
HISTORY_VERSION = 1


def _history_path(path: str | os.PathLike) -> Path:
    p = Path(path)
    return p if p.suffix == ".json" else p / HISTORY_FILE


def _check_entry(e, path: Path, k: int) -> dict:
    if not isinstance(e, dict):
        raise FormatError(path, f"entry {k} is not an object")
    for key in ("timestamp", "effects", "gap"):
        if key not in e:
            raise FormatError(path, f"entry {k} has no '{key}'")
    if not isinstance(e["effects"], list) or not all(isinstance(x, str) for x in e["effects"]):
        raise FormatError(path, f"entry {k}: 'effects' must be a list of names")
    try:
        gap = float(e["gap"])
    except (TypeError, ValueError):
        raise FormatError(path, f"entry {k}: 'gap' is not a number ({e['gap']!r})") from None
    if not math.isfinite(gap) or gap < 0:
        raise FormatError(path, f"entry {k}: 'gap' must be a finite number >= 0, got {gap}")
    label = e.get("label")
    return {"step": k, "timestamp": str(e["timestamp"]), "effects": list(e["effects"]), "gap": gap,
            "label": None if label is None else str(label)}


def load_history(path: str | os.PathLike) -> list[dict]:
    """Entries of ``path/history.json`` (or of the given ``.json`` file); [] when there is none."""
    p = _history_path(path)
    if not p.exists():
        return []
    try:
        d = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise FormatError(p, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    entries = d.get("entries") if isinstance(d, dict) else None
    if not isinstance(entries, list):
        raise FormatError(p, "history file needs an 'entries' list")
    return [_check_entry(e, p, k) for k, e in enumerate(entries)]


def save_history(out_dir: str | os.PathLike, entries: Sequence[dict]) -> Path:
    """Write ``out_dir/history.json`` atomically (renumbering the steps)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = out / HISTORY_FILE
    clean = [_check_entry(dict(e), p, k) for k, e in enumerate(entries)]
    from data_tools.results import atomic_write_text
    return atomic_write_text(p, json.dumps({"version": HISTORY_VERSION, "entries": clean}, indent=1) + "\n")


def append_history(out_dir: str | os.PathLike, effects: Sequence[str], gap: float,
                   label: str | None = None, *, compare_against: str | os.PathLike | None = None,
                   timestamp: str | None = None) -> list[dict]:
    """Append one run to ``out_dir/history.json`` and return the whole history.

    compare_against: a previous lab folder (or its history.json) whose history this run
    continues; the result is written to ``out_dir``. Without it, ``out_dir``'s own history
    (if any) is continued.
    """
    if isinstance(effects, str):
        raise RealgapError("append_history: effects must be a list of effect names, not one string")
    g = float(gap)
    if not math.isfinite(g) or g < 0:
        raise RealgapError(f"append_history: gap must be a finite number >= 0, got {gap}")
    if compare_against is not None:
        src = _history_path(compare_against)
        if not src.exists():
            raise FormatError(src, "no history to compare against (file not found)")
        base = load_history(src)
    else:
        base = load_history(out_dir)
    ts = timestamp or datetime.now(timezone.utc).isoformat(timespec="seconds")
    entries = base + [{"timestamp": ts, "effects": [str(e) for e in effects], "gap": g, "label": label}]
    save_history(out_dir, entries)
    return load_history(out_dir)


def step_labels(entries: Sequence[dict]) -> list[str]:
    """Tick label per step: its label, else the effects added (+) / removed (-) since the
    previous step, else all its effects ("ideal" when none)."""
    out = []
    prev: list[str] | None = None
    for e in entries:
        eff = list(e.get("effects", []))
        if e.get("label"):
            out.append(str(e["label"]))
        elif prev is None:
            out.append(", ".join(eff) if eff else "ideal")
        else:
            added = [x for x in eff if x not in prev]
            removed = [x for x in prev if x not in eff]
            parts = [f"+{x}" for x in added] + [f"-{x}" for x in removed]
            out.append(", ".join(parts) if parts else (", ".join(eff) or "ideal") + " (again)")
        prev = eff
    return out
