"""Timestamped trajectories and the TUM trajectory format.

A line is ``timestamp tx ty tz qx qy qz qw`` (camera-to-world, metres); ``#`` starts a
comment. Reading validates what a silent garbage result would hide: unsorted or duplicated
timestamps, NaN/inf values, quaternions that are not unit length.
"""
from __future__ import annotations

import os
from data_tools.errors import warn
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError, RealgapError
from data_tools.geometry import UNIT_QUAT_TOL, pose_from_tum, pose_to_tum

DEFAULT_MAX_DT = 0.02
"""TUM's association rule: nearest timestamp within 0.02 s."""


@dataclass
class Trajectory:
    """A sequence of poses with timestamps."""

    timestamps: np.ndarray
    """(N,) float64 seconds, strictly increasing."""
    poses: np.ndarray
    """(N, 4, 4) float64 camera-to-world transforms, metres."""

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise RealgapError(f"trajectory has {len(self.timestamps)} timestamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame, metres."""
        return self.poses[:, :3, 3]

    def subset(self, idx: np.ndarray) -> "Trajectory":
        return Trajectory(self.timestamps[idx], self.poses[idx])

    def transformed(self, T_left: np.ndarray) -> "Trajectory":
        """The trajectory with every pose left-multiplied by T_left (a change of world frame)."""
        return Trajectory(self.timestamps.copy(), np.einsum("ij,njk->nik", T_left, self.poses))

    def path_length(self) -> float:
        """Total travelled distance, metres."""
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum()) if len(self) > 1 else 0.0


def check_timestamps(ts: np.ndarray, path: str | os.PathLike | None, what: str = "timestamps") -> None:
    """Raise a FormatError naming ``path`` for NaN, unsorted or duplicated timestamps."""
    ts = np.asarray(ts, dtype=np.float64)
    if not np.all(np.isfinite(ts)):
        bad = int(np.flatnonzero(~np.isfinite(ts))[0])
        raise FormatError(path, f"{what}: non-finite timestamp at entry {bad + 1}")
    d = np.diff(ts)
    if np.any(d == 0):
        i = int(np.flatnonzero(d == 0)[0])
        raise FormatError(path, f"{what}: duplicated timestamp {ts[i]:.6f} (entries {i + 1} and {i + 2})")
    if np.any(d < 0):
        i = int(np.flatnonzero(d < 0)[0])
        raise FormatError(path, f"{what}: timestamps are not sorted ({ts[i]:.6f} then {ts[i + 1]:.6f} at entries {i + 1}-{i + 2})")


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except UnicodeDecodeError:
        raise FormatError(path, "not a text file") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.split("#", 1)[0].replace(",", " ").split()
        if s:
            rows.append((lineno, s))
    return rows


def read_tum(path: str | os.PathLike, drop_duplicate_timestamps: bool = True) -> Trajectory:
    """Read a TUM trajectory file; every problem is a FormatError naming the file and line.

    A pose whose timestamp exactly repeats the previous pose's is dropped (the first one is
    kept), as evo reads such files, with one ``UserWarning`` naming the file, the timestamp and
    the line (../shared/FORMATS.md section 5): the official TUM ``fr2/desk`` ground truth has one
    such repeated stamp with two different poses. ``drop_duplicate_timestamps=False`` makes a
    repeat an error instead. Unsorted timestamps are always an error.
    """
    path = Path(path)
    rows = _data_lines(path)
    if not rows:
        raise FormatError(path, "no poses in trajectory file")
    data = np.empty((len(rows), 8))
    for i, (lineno, s) in enumerate(rows):
        if len(s) != 8:
            raise FormatError(path, f"line {lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(s)}")
        try:
            data[i] = [float(x) for x in s]
        except ValueError:
            raise FormatError(path, f"line {lineno}: not a number in {' '.join(s)!r}") from None
        if not np.all(np.isfinite(data[i])):
            raise FormatError(path, f"line {lineno}: NaN or infinite value in pose")
        qn = np.linalg.norm(data[i, 4:8])
        if abs(qn - 1.0) > UNIT_QUAT_TOL:
            raise FormatError(path, f"line {lineno}: quaternion is not unit length (|q| = {qn:.6f})")
    if drop_duplicate_timestamps and len(data) > 1:
        keep = np.concatenate([[True], np.diff(data[:, 0]) != 0])
        dropped = np.flatnonzero(~keep)
        if len(dropped):
            first = int(dropped[0])
            more = f" (and {len(dropped) - 1} more)" if len(dropped) > 1 else ""
            warn(f"{path}: line {rows[first][0]}: timestamp {data[first, 0]:.6f} repeats the previous "
                          f"pose's; kept the first, dropped this one{more}")
            data = data[keep]
    check_timestamps(data[:, 0], path)
    return Trajectory(data[:, 0], pose_from_tum(data[:, 1:]))


def write_tum(path: str | os.PathLike, traj: Trajectory, header: str | None = None) -> None:
    """Write a TUM trajectory file (timestamps with 6 decimals, poses with 9 significant digits)."""
    rows = pose_to_tum(traj.poses)
    lines = [f"# {header}"] if header else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for t, r in zip(traj.timestamps, rows):
        lines.append(f"{t:.6f} " + " ".join(f"{x:.9g}" for x in r))
    from data_tools.results import atomic_write_text
    atomic_write_text(path, "\n".join(lines) + "\n")


def associate(ts_a: np.ndarray, ts_b: np.ndarray, max_dt: float = DEFAULT_MAX_DT,
              offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Match two sorted timestamp arrays by nearest time, each entry used at most once.

    Candidate pairs with |a - (b + offset)| <= max_dt are accepted greedily from the
    smallest difference (the rule of TUM's associate.py, also used by evo). Returns index
    arrays (ia, ib) sorted by ia.
    """
    a = np.asarray(ts_a, dtype=np.float64)
    b = np.asarray(ts_b, dtype=np.float64) + offset
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    # candidates: for every a the neighbours in b within max_dt (b is sorted)
    lo = np.searchsorted(b, a - max_dt, side="left")
    hi = np.searchsorted(b, a + max_dt, side="right")
    cand_a, cand_b = [], []
    for i in range(len(a)):
        for j in range(lo[i], hi[i]):
            cand_a.append(i)
            cand_b.append(j)
    if not cand_a:
        return np.zeros(0, int), np.zeros(0, int)
    ca, cb = np.array(cand_a), np.array(cand_b)
    diff = np.abs(a[ca] - b[cb])
    order = np.lexsort((cb, ca, diff))
    used_a = np.zeros(len(a), bool)
    used_b = np.zeros(len(b), bool)
    ia, ib = [], []
    for k in order:
        i, j = ca[k], cb[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            ia.append(i)
            ib.append(j)
    ia, ib = np.array(ia, int), np.array(ib, int)
    s = np.argsort(ia)
    return ia[s], ib[s]
