"""The classic calibration figures of planar-target captures (sequences with masks, made by
``realgap data make-reference --plane``), added to the lab report:

* noise vs distance: per frame, the spread of (depth - reference plane) over the target's pixels
  (1.4826 x median absolute deviation, mm) against the frame's median distance, for the measured
  and the simulated depth, beside the published Kinect v1 models: Khoshelham & Elberink 2012,
  sigma = 1.425e-3 z^2 m (their theoretical random error, 1.43 mm at 1 m), and Nguyen, Izadi &
  Lovell 2012, sigma = 1.2 mm + 1.9 mm/m^2 (z - 0.4 m)^2;
* the mean residual map: per pixel, the mean of (measured - reference) over every frame where
  the pixel is on the target, mm - the fixed spatial pattern (Smisek et al. 2011; Herrera et al.
  2012's disparity distortion) that a per-frame noise figure averages away; the same for the
  simulation beside it.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["plane_noise_table", "mean_residual_maps", "khoshelham_sigma_m", "nguyen_sigma_m", "calibration_section"]


def khoshelham_sigma_m(z: np.ndarray) -> np.ndarray:
    return 1.425e-3 * np.asarray(z, float) ** 2


def nguyen_sigma_m(z: np.ndarray) -> np.ndarray:
    return 0.0012 + 0.0019 * (np.asarray(z, float) - 0.4) ** 2


def _spread(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r)))) if r.size else float("nan")


def plane_noise_table(observations: Sequence) -> list[dict]:
    """Per frame: median distance (m), measured and simulated spread (mm) over the target's pixels."""
    rows = []
    for o in observations:
        on = o.ideal > 0
        m, s = on & (o.measured > 0), on & (o.simulated > 0)
        if m.sum() < 50:
            continue
        rows.append({"frame": int(o.index), "distance_m": float(np.median(o.ideal[on])),
                     "measured_mm": 1000 * _spread(o.measured[m] - o.ideal[m]),
                     "simulated_mm": 1000 * _spread(o.simulated[s] - o.ideal[s]) if s.sum() >= 50 else float("nan")})
    return rows


def mean_residual_maps(observations: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """(measured, simulated) (H, W) mean residual over the frames, mm; NaN where never on target."""
    acc = {"measured": None, "simulated": None}
    out = []
    for key in acc:
        total = cnt = None
        for o in observations:
            d = getattr(o, key)
            ok = (o.ideal > 0) & (d > 0)
            r = np.where(ok, d - o.ideal, 0.0)
            total = r if total is None else total + r
            cnt = ok.astype(np.int32) if cnt is None else cnt + ok
        with np.errstate(invalid="ignore", divide="ignore"):
            out.append(np.where(cnt > 0, 1000.0 * total / np.maximum(cnt, 1), np.nan))
    return out[0], out[1]


def calibration_section(observations: Sequence, figs: str | os.PathLike) -> str:
    """Write the two figures into ``figs`` and return the report's HTML section."""
    from data_tools.results import atomic_save_figure as save_figure
    from data_tools.results import new_figure as figure
    figs = Path(figs)
    rows = plane_noise_table(observations)
    if not rows:
        return "<h2>Planar target</h2><p>No frame has enough target pixels with a measurement.</p>"
    z = np.array([r["distance_m"] for r in rows])
    fig = figure(6.0, 3.8)
    ax = fig.add_subplot()
    zz = np.linspace(max(0.4, z.min() * 0.9), z.max() * 1.1, 100)
    ax.plot(zz, 1000 * khoshelham_sigma_m(zz), "k--", lw=1, label="Khoshelham & Elberink 2012")
    ax.plot(zz, 1000 * nguyen_sigma_m(zz), "k:", lw=1.2, label="Nguyen et al. 2012")
    ax.plot(z, [r["measured_mm"] for r in rows], "o", color="tab:blue", label="measured")
    ax.plot(z, [r["simulated_mm"] for r in rows], "s", mfc="none", color="tab:red", label="simulated")
    ax.set_xlabel("distance to the target (m)")
    ax.set_ylabel("spread about the plane (mm, 1.48 MAD)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, figs / "plane_noise.png")
    meas, sim = mean_residual_maps(observations)
    both = np.concatenate([meas[np.isfinite(meas)], sim[np.isfinite(sim)]])
    lim = float(np.percentile(np.abs(both), 98)) if both.size else 1.0
    fig = figure(10.0, 3.6)
    for k, (img, title) in enumerate(((meas, "measured - reference"), (sim, "simulated - reference"))):
        a = fig.add_subplot(1, 2, k + 1)
        im = a.imshow(img, cmap="RdBu_r", vmin=-lim, vmax=lim)
        a.set_title(f"mean {title} over {len(observations)} frames", fontsize=9)
        a.set_xticks([])
        a.set_yticks([])
        fig.colorbar(im, ax=a, fraction=0.035, label="mm")
    save_figure(fig, figs / "plane_residual_map.png")
    table = "".join(f"<tr><td>{r['frame']}</td><td>{r['distance_m']:.3f}</td><td>{r['measured_mm']:.2f}</td>"
                    f"<td>{r['simulated_mm']:.2f}</td><td>{1000 * nguyen_sigma_m(r['distance_m']):.2f}</td></tr>"
                    for r in rows)
    return ("<h2>Planar target: the classic calibration figures</h2>"
            "<p>Spread of the depth about the fitted target plane against distance, with the published "
            "Kinect v1 noise models (Khoshelham &amp; Elberink 2012: 1.425e-3 z<sup>2</sup> m; Nguyen et al. 2012: "
            "1.2 mm + 1.9 mm/m<sup>2</sup> (z - 0.4 m)<sup>2</sup>), and the mean residual map over all frames (the fixed spatial pattern "
            "a per-frame figure averages away).</p>"
            "<img src='figures/plane_noise.png' alt='noise vs distance'>"
            "<img src='figures/plane_residual_map.png' alt='mean residual map'>"
            "<table><tr><th>frame</th><th>distance (m)</th><th>measured (mm)</th><th>simulated (mm)</th>"
            f"<th>Nguyen (mm)</th></tr>{table}</table>")
