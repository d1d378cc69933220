"""Plots of trajectory evaluations (PNG files).

matplotlib is imported inside the functions and drives an Agg canvas directly (no pyplot, no
global backend state), so importing this module is cheap and works without a display.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from data_tools.trajectory import Trajectory

AXIS_NAMES = ("x", "y", "z")


def _figure(width_in: float, height_in: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=110)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | os.PathLike) -> Path:
    from data_tools.results import atomic_save_figure
    return atomic_save_figure(fig, path)


def top_view_axes(*trajectories: Trajectory) -> tuple[int, int]:
    """The two world axes (indices, ascending) along which the positions extend the most."""
    pts = np.concatenate([t.positions for t in trajectories if len(t)], axis=0)
    extent = pts.max(axis=0) - pts.min(axis=0)
    a, b = sorted(np.argsort(-extent, kind="stable")[:2].tolist())
    return a, b


def plot_top_view(path: str | os.PathLike, reference: Trajectory, estimate: Trajectory, *,
                  title: str = "", labels: tuple[str, str] = ("reference", "estimate (aligned)"),
                  axes: tuple[int, int] | None = None, markers: np.ndarray | None = None,
                  marker_label: str = "registration failed") -> Path:
    """Both trajectories projected on two world axes (default: the two of largest extent).

    markers: optional (K, 3) world positions (metres) drawn as red crosses, e.g. where frames
    failed. Equal aspect ratio, axes in metres. Returns the PNG path.
    """
    a, b = axes if axes is not None else top_view_axes(reference, estimate)
    fig = _figure(7.0, 6.0)
    ax = fig.add_subplot(1, 1, 1)
    P, E = reference.positions, estimate.positions
    ax.plot(P[:, a], P[:, b], "-", color="0.25", lw=1.5, label=labels[0])
    ax.plot(E[:, a], E[:, b], "-", color="tab:blue", lw=1.0, alpha=0.9, label=labels[1])
    ax.plot(P[:1, a], P[:1, b], "o", color="0.25", ms=6, label="start")
    ax.plot(E[:1, a], E[:1, b], "o", color="tab:blue", ms=4)
    if markers is not None and len(markers):
        m = np.asarray(markers, dtype=np.float64).reshape(-1, 3)
        ax.plot(m[:, a], m[:, b], "x", color="red", ms=7, mew=1.5, label=f"{marker_label} ({len(m)})")
    ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=9)
    ax.set_title(title or f"top view ({AXIS_NAMES[a]}-{AXIS_NAMES[b]})", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def plot_errors_over_time(path: str | os.PathLike,
                          series: Sequence[tuple[str, np.ndarray, np.ndarray, str]], *,
                          t0: float | None = None, failed_timestamps: Sequence[float] | None = None,
                          title: str = "") -> Path:
    """One panel per error series, over time since ``t0`` (seconds), sharing the time axis.

    series: (label, timestamps (M,) s, errors (M,), unit) per panel; the panel shows the rmse
    as a dashed line. failed_timestamps: frames where registration failed, marked by red
    vertical lines in every panel. Returns the PNG path.
    """
    series = list(series)
    if not series:
        raise ValueError("plot_errors_over_time: no series")
    failed = np.asarray(failed_timestamps if failed_timestamps is not None else [], dtype=np.float64)
    if t0 is None:
        starts = [float(np.min(ts)) for _, ts, _, _ in series if len(ts)]
        t0 = min(starts + ([float(failed.min())] if failed.size else []))
    fig = _figure(8.0, 2.4 * len(series) + 0.8)
    axs = fig.subplots(len(series), 1, sharex=True, squeeze=False)[:, 0]
    for ax, (label, ts, err, unit) in zip(axs, series):
        ts = np.asarray(ts, dtype=np.float64) - t0
        err = np.asarray(err, dtype=np.float64)
        u = f" [{unit}]" if unit else ""
        ax.plot(ts, err, "-", color="tab:blue", lw=1.0, label=label)
        rmse = float(np.sqrt(np.mean(err ** 2))) if err.size else float("nan")
        ax.axhline(rmse, color="tab:orange", ls="--", lw=1.0, label=f"rmse {rmse:.4g} {unit}".rstrip())
        if failed.size:
            ax.vlines(failed - t0, 0, 1, transform=ax.get_xaxis_transform(), colors="red", lw=0.8,
                      alpha=0.6, label=f"registration failed ({failed.size} frames)")
        ax.set_ylabel(f"{label}{u}")
        ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("time since start [s]")
    if title:
        axs[0].set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def plot_backend_comparison(path: str | os.PathLike, sequences: Sequence[str], backends: Sequence[str],
                            values: dict[tuple[str, str], dict[str, float | None]], *, title: str = "",
                            align: str = "") -> Path:
    """The batch report's comparison: one panel per metric (ATE rmse [cm], APE median [cm], frames/s), a group of
    bars per sequence, one colour per backend. ``values[(sequence, backend)]``: ``ate_rmse_m``, ``ape_median_m``
    (metres) and ``frames_per_second``; a missing pair or a None value (a failed run) is left out and marked
    "n/a" at the bar's place. ``align``: the alignment the absolute errors were computed after, named in
    their axis labels. Returns the PNG path."""
    how = f"\n(align {align})" if align else ""
    metrics = (("ate_rmse_m", f"ATE rmse [cm]{how}", 100.0), ("ape_median_m", f"APE median [cm]{how}", 100.0),
               ("frames_per_second", "frames/s", 1.0))
    fig = _figure(max(6.0, 1.2 + 0.9 * len(sequences) * max(1, len(backends)) / 2), 7.5)
    axs = fig.subplots(len(metrics), 1, sharex=True, squeeze=False)[:, 0]
    x = np.arange(len(sequences), dtype=np.float64)
    width = 0.8 / max(1, len(backends))
    for ax, (key, label, scale) in zip(axs, metrics):
        for j, b in enumerate(backends):
            xs = x - 0.4 + width * (j + 0.5)
            v = [values.get((s, b), {}).get(key) for s in sequences]
            h = np.array([np.nan if u is None else float(u) * scale for u in v])
            ax.bar(xs, np.nan_to_num(h), width, label=b, color=f"C{j}")
            for xi, hi in zip(xs, h):
                if np.isnan(hi):
                    ax.text(xi, 0, "n/a", ha="center", va="bottom", fontsize=7, rotation=90)
        ax.set_ylabel(label)
        ax.grid(True, axis="y", alpha=0.3)
    axs[0].legend(loc="best", fontsize=8, title="backend", title_fontsize=8)
    axs[-1].set_xticks(x)
    axs[-1].set_xticklabels(sequences, rotation=30 if len(sequences) > 4 else 0, ha="right" if len(sequences) > 4
                            else "center", fontsize=8)
    axs[-1].set_xlabel("sequence")
    if title:
        axs[0].set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
