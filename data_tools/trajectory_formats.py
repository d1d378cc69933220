"""Trajectory files in the formats evo and Open3D read and write: TUM, KITTI, EuRoC and Open3D ``.log``.

Every format holds camera-to-world poses in metres; they differ in how time is written:

==========  ==============================================================  ====================
format      one pose                                                        time
==========  ==============================================================  ====================
``tum``     ``timestamp tx ty tz qx qy qz qw`` (space separated)            seconds
``kitti``   the first 3 rows of the 4x4 matrix, row-major, 12 numbers        none: pose k gets t = k
``euroc``   ``timestamp_ns,px,py,pz,qw,qx,qy,qz[,...]`` (``data.csv`` of     nanoseconds
            EuRoC's ``state_groundtruth_estimate0``; extra columns ignored)
``log``     ``i j k`` then 4 lines of the 4x4 matrix (Open3D's reconstruction  none: pose k gets t = k
            system and ``PinholeCameraTrajectory``; the matrix is the pose)
==========  ==============================================================  ====================

As in evo, formats without time (KITTI, ``.log``) are associated pose by pose: pose k gets the
timestamp k (seconds), so two such files of equal length pair up entry by entry.

:func:`detect_format` takes the format from the extension (``.csv`` EuRoC, ``.log`` Open3D,
``.kitti`` KITTI) and for ``.txt`` from the first data line (8 values TUM, 12 values KITTI).
Every reader checks what a silent garbage result would hide (NaN, unsorted or duplicated
timestamps, non-unit quaternions, rotation matrices that are not rotations) and names the file
and line.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError, RealgapError
from data_tools.geometry import UNIT_QUAT_TOL, matrix_to_quat, pose_from_tum
from data_tools.trajectory import Trajectory, check_timestamps, read_tum, write_tum

__all__ = ["FORMATS", "detect_format", "read_trajectory", "write_trajectory"]

FORMATS = ("tum", "kitti", "euroc", "log")
"""Trajectory formats known to :func:`read_trajectory` / :func:`write_trajectory`."""

ROTATION_TOL = 1e-3
"""Largest allowed deviation of R^T R from I (and of det R from 1) in a matrix read from a file."""


def _text_rows(path: Path, sep: str | None = None) -> list[tuple[int, list[str]]]:
    from data_tools.outputs import check_input_file
    check_input_file(path, "trajectory file")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise FormatError(path, "not a text file") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        parts = [p.strip() for p in body.split(sep)] if sep else body.replace(",", " ").split()
        rows.append((lineno, [p for p in parts if p != ""]))
    return rows


def detect_format(path: str | os.PathLike) -> str:
    """The format of a trajectory file from its extension, or for ``.txt`` from its first data line."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".csv":
        return "euroc"
    if ext == ".log":
        return "log"
    if ext == ".kitti":
        return "kitti"
    rows = _text_rows(p)
    if not rows:
        raise FormatError(p, "no poses in trajectory file")
    n = len(rows[0][1])
    if n == 8:
        return "tum"
    if n == 12:
        return "kitti"
    raise FormatError(p, f"line {rows[0][0]}: {n} values: not TUM (8: 'timestamp tx ty tz qx qy qz qw') nor "
                         f"KITTI (12: 3x4 matrix); name the format with --format")


def _floats(path: Path, lineno: int, parts: list[str]) -> np.ndarray:
    try:
        v = np.array([float(x) for x in parts])
    except ValueError:
        raise FormatError(path, f"line {lineno}: not a number in {' '.join(parts)!r}") from None
    if not np.all(np.isfinite(v)):
        raise FormatError(path, f"line {lineno}: NaN or infinite value in pose")
    return v


def _check_rotation(path: Path, where: str, R: np.ndarray) -> None:
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if dev > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        raise FormatError(path, f"{where}: the 3x3 block is not a rotation (|R^T R - I| = {dev:.2g}, det = {det:.4f})")


def _read_kitti(path: Path) -> Trajectory:
    rows = _text_rows(path)
    if not rows:
        raise FormatError(path, "no poses in trajectory file")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    for k, (lineno, s) in enumerate(rows):
        if len(s) != 12:
            raise FormatError(path, f"line {lineno}: expected 12 values (KITTI: 3x4 matrix, row-major), got {len(s)}")
        poses[k, :3, :] = _floats(path, lineno, s).reshape(3, 4)
        _check_rotation(path, f"line {lineno}", poses[k, :3, :3])
    return Trajectory(np.arange(len(rows), dtype=np.float64), poses)


def _read_euroc(path: Path) -> Trajectory:
    rows = _text_rows(path, sep=",")
    if not rows:
        raise FormatError(path, "no poses in trajectory file")
    data = np.empty((len(rows), 8))
    for k, (lineno, s) in enumerate(rows):
        if len(s) < 8:
            raise FormatError(path, f"line {lineno}: expected at least 8 values 'timestamp_ns,px,py,pz,qw,qx,qy,qz', "
                                    f"got {len(s)}")
        data[k] = _floats(path, lineno, s[:8])
        qn = np.linalg.norm(data[k, 4:8])
        if abs(qn - 1.0) > UNIT_QUAT_TOL:
            raise FormatError(path, f"line {lineno}: quaternion is not unit length (|q| = {qn:.6f})")
    ts = data[:, 0] / 1e9
    check_timestamps(ts, path)
    txyz_qxyzw = np.concatenate([data[:, 1:4], data[:, 5:8], data[:, 4:5]], axis=1)
    return Trajectory(ts, pose_from_tum(txyz_qxyzw))


def _read_log(path: Path) -> Trajectory:
    rows = _text_rows(path)
    if not rows:
        raise FormatError(path, "no poses in trajectory file")
    if len(rows) % 5:
        raise FormatError(path, f"{len(rows)} data lines: an Open3D .log holds blocks of 5 (a 'i j k' line, then "
                                f"4 rows of the 4x4 pose)")
    poses = np.empty((len(rows) // 5, 4, 4))
    for k in range(len(poses)):
        lineno, head = rows[5 * k]
        if len(head) != 3:
            raise FormatError(path, f"line {lineno}: expected the 3 numbers of an entry header, got {len(head)}")
        for r in range(4):
            ln, s = rows[5 * k + 1 + r]
            if len(s) != 4:
                raise FormatError(path, f"line {ln}: expected 4 values of a matrix row, got {len(s)}")
            poses[k, r] = _floats(path, ln, s)
        if not np.allclose(poses[k, 3], [0, 0, 0, 1], atol=1e-6):
            raise FormatError(path, f"line {rows[5 * k + 4][0]}: the last matrix row must be 0 0 0 1")
        _check_rotation(path, f"entry at line {lineno}", poses[k, :3, :3])
    return Trajectory(np.arange(len(poses), dtype=np.float64), poses)


def read_trajectory(path: str | os.PathLike, fmt: str = "auto", drop_duplicate_timestamps: bool = True) -> Trajectory:
    """Read a trajectory file in ``fmt`` (one of :data:`FORMATS`, or ``auto``: :func:`detect_format`).

    Every problem is a FormatError naming the file (and line). ``drop_duplicate_timestamps``
    applies to the timestamped formats (see :func:`data_tools.trajectory.read_tum`).
    """
    p = Path(path)
    if fmt not in FORMATS + ("auto",):
        raise RealgapError(f"unknown trajectory format {fmt!r} (known: auto, {', '.join(FORMATS)})")
    if fmt == "auto":
        fmt = detect_format(p)
    if fmt == "tum":
        from data_tools.outputs import check_input_file
        check_input_file(p, "trajectory file")
        return read_tum(p, drop_duplicate_timestamps=drop_duplicate_timestamps)
    if fmt == "euroc":
        return _read_euroc(p)
    return _read_kitti(p) if fmt == "kitti" else _read_log(p)


def write_trajectory(path: str | os.PathLike, traj: Trajectory, fmt: str = "auto", header: str | None = None) -> Path:
    """Write ``traj`` in ``fmt`` (``auto``: from the extension; ``.txt`` is TUM). KITTI and
    ``.log`` have no time (the timestamps are dropped); EuRoC writes nanoseconds. Atomic."""
    from data_tools.results import atomic_write_text
    p = Path(path)
    if fmt == "auto":
        fmt = {".csv": "euroc", ".log": "log", ".kitti": "kitti"}.get(p.suffix.lower(), "tum")
    if fmt not in FORMATS:
        raise RealgapError(f"unknown trajectory format {fmt!r} (known: {', '.join(FORMATS)})")
    if fmt == "tum":
        write_tum(p, traj, header=header)
        return p
    lines = []
    if fmt == "kitti":
        for T in traj.poses:
            lines.append(" ".join(f"{x:.9e}" for x in T[:3, :].reshape(-1)))
    elif fmt == "euroc":
        lines.append("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []")
        q = matrix_to_quat(traj.poses[:, :3, :3])  # x y z w
        for t, T, qq in zip(traj.timestamps, traj.poses, q):
            vals = [*T[:3, 3], qq[3], qq[0], qq[1], qq[2]]
            lines.append(f"{int(round(t * 1e9))}," + ",".join(f"{x:.9g}" for x in vals))
    else:  # Open3D .log, as PinholeCameraTrajectory writes it: "i i i+1" then the pose
        for k, T in enumerate(traj.poses):
            lines.append(f"{k} {k} {k + 1}")
            lines.extend(" ".join(f"{x:.8f}" for x in row) for row in T)
    atomic_write_text(p, "\n".join(lines) + "\n")
    return p
