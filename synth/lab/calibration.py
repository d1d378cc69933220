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

The noise-vs-distance curve as a term of the fit's objective (:func:`noise_curve`,
:func:`curve_term`; :class:`synth.lab.objective.Objective` with ``FitConfig.noise_curve_weight``):
The noise-vs-distance curve of planar-target captures, as a term of the fit's objective.

Sensor people calibrate noise against distance first (Khoshelham & Elberink 2012; Nguyen et al.
2012): the spread of the depth about the target plane, per distance. The lab's gap compares error
*distributions* per feature bin, pooled with other features; on a plane capture a model can lower
the gap while its noise is 1.3-1.7 x too high far away. Where a sequence has a planar reference
(``plane_reference.json``, written by ``realgap data make-reference --plane``), :func:`noise_curve`
measures the curve of the measured and of the simulated depth the same way, and
:func:`curve_term` scores their mismatch; :class:`synth.lab.objective.Objective` adds it to the gap
(``FitConfig.noise_curve_weight``).

The curve. Target pixels (ideal depth > 0: inside the frame's mask) are binned by their ideal
depth into ``BIN_EDGES_M`` (0.5-3.0 m, 0.25 m wide). In each (frame, bin) group the residuals
depth - ideal of the valid pixels are taken about the group's own local plane
(:func:`local_plane_residuals`; :data:`LOCAL_PLANE`): a per-frame offset or tilt of the reference
plane is a bias, not noise - the plane fit per target patch of a calibration removes it too - then
per bin the pooled residuals give the robust std 1.4826 x MAD (outliers such as flying pixels do
not dominate it).
A bin counts only when both sides have at least ``MIN_PIXELS`` valid residuals.

The term: the mean over counted bins of |ln(s_simulated / s_measured)| (0.095 for a 10 % error
in every bin; symmetric in too high / too low), plus the same over the grazing cells: each
distance bin's pixels seen at 60-75 and 75-90 degrees between the camera ray and the target's
normal (``GRAZING_EDGES_DEG``). A few planes seen at grazing incidence fill the far bins of a room
capture (7-Scenes chess), and their noise grows with the angle (Nguyen et al. 2012), which a
curve in distance alone averages away; the cells let the fit separate axial noise's incidence
term from its distance terms. The reported table stays per distance bin.

The curve's sampling spread: :func:`curve_groups` keeps the residuals per (frame, bin) and
:func:`curve_uncertainty` bootstraps frames (``benchmarks/bench_plane_noise.py`` prints the
intervals beside each ratio): a bin filled by a few grazing views moves by tens of percent between
two sets of frames, more than the 10 % a fit is asked to meet.

Why a local plane and not the median alone: the frame's reference plane is fitted on all of the
frame's target pixels, which the near ones dominate; where a floor or table is seen at 60-80 deg
beyond 2.5 m, a 0.25 m bin is a long strip across the image, and the reference's tilt error, the
sensor's low-frequency depth distortion and the surface's own shape put a ramp along that strip
that the median leaves in. The measured side then counts it as noise while the simulated side
(rendered from the reference plane itself) has none. The local plane takes it out of both alike,
and leaves the pixel noise: it is 3 parameters over tens to thousands of pixels, and a spatially
correlated noise (the matcher's window, a few pixels) varies far faster than a plane over the
strip. What is left of a curved misfit over one strip (its second order) stays in.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["plane_noise_table", "mean_residual_maps", "khoshelham_sigma_m", "nguyen_sigma_m", "calibration_section",
           "BIN_EDGES_M", "INCIDENCE_EDGES_DEG", "GRAZING_EDGES_DEG", "noise_curve", "storage_quantum_m", "curve_term", "curve_table", "noise_curve_report",
           "incidence_cells", "curve_groups", "curve_uncertainty"]


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
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4, frameon=False)  # off the points
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


# ------------------------------------------------------------------------------------------
# The noise-vs-distance curve as a fit term
# ------------------------------------------------------------------------------------------

BIN_EDGES_M = tuple(round(0.5 + 0.25 * k, 2) for k in range(11))
"""Distance bin edges, metres: 0.5, 0.75, ..., 3.0."""
INCIDENCE_EDGES_DEG = (0.0, 60.0, 75.0, 90.5)
"""Incidence classes of the fit's noise curve, degrees (ray vs target normal): Nguyen et al. 2012's
incidence term theta^2 / (pi/2 - theta)^2 is under 4 below 60 deg, 4-25 at 60-75, above 25 beyond."""
GRAZING_EDGES_DEG = INCIDENCE_EDGES_DEG[1:]
"""The grazing classes alone (60-75, 75-90 deg): the fit's term adds their cells to the distance
curve, so a capture without grazing views is fitted as by the distance curve alone."""
MIN_PIXELS = 200
"""Fewest valid residuals a bin needs on each side to count."""
LOCAL_PLANE = True
"""The noise curve's residuals are taken about a local plane per (frame, bin) group
(:func:`local_plane_residuals`), on the measured and the simulated side alike: the axial noise is
the spread about the surface, not the reference plane's misfit far from the pixels that fitted it
(docs/sensor_lab.md, "Noise against distance on a real plane"). False: the median per group alone."""


def _pixels(o, max_pixels: int | None, seed: int) -> np.ndarray:
    """Flat indices of the target pixels of observation ``o`` (a seeded subset of ``max_pixels``)."""
    flat = np.flatnonzero(o.ideal.ravel() > 0)
    if max_pixels is not None and flat.size > max_pixels:
        rng = np.random.default_rng([int(seed), int(o.index), 7])
        flat = np.sort(rng.choice(flat, size=int(max_pixels), replace=False))
    return flat


STORAGE_QUANTA_M = (1e-3, 5e-4, 2.5e-4, 2e-4, 1e-4)
"""Depth quanta a stored depth image may carry, metres (largest first): 1 mm (7-Scenes, ROS mm
PNGs), 1/5000 m (TUM PNGs) and finer."""


def storage_quantum_m(depth: np.ndarray, share: float = 0.99) -> float:
    """The depth quantum the valid values of ``depth`` (m) were stored with: the largest of
    :data:`STORAGE_QUANTA_M` that ``share`` of them are whole multiples of; 0 when none (float
    depth). A 7-Scenes capture converted to a TUM-layout 1/5000 m PNG still holds whole mm."""
    v = np.asarray(depth, np.float64).ravel()
    v = v[v > 0]
    if v.size < 50:
        return 0.0
    for q in STORAGE_QUANTA_M:
        x = v / q
        if np.mean(np.abs(x - np.round(x)) < 2e-3) >= share:
            return float(q)
    return 0.0


def noise_curve(observations: Sequence, side: str, max_pixels: int | None = 20000, seed: int = 0,
                edges: Sequence[float] = BIN_EDGES_M,
                incidence_edges: Sequence[float] | None = None,
                local_plane: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(robust std per bin (m, NaN where a bin has too few pixels), valid pixels per bin) of the
    ``side`` ("measured" or "simulated") depth of FrameObservations (module docstring).

    ``incidence_edges`` (degrees, e.g. :data:`INCIDENCE_EDGES_DEG`): each distance bin is split
    further by the angle between the camera ray and the target's normal, and the result is per
    (distance bin, incidence class), flattened distance-major (len(edges) - 1) x
    (len(incidence_edges) - 1): the curve the fit's objective compares, so a noise that grows at
    grazing incidence (Nguyen et al. 2012) is not averaged into the distance curve.

    The simulated depth is rounded to the measured depth's storage quantum
    (:func:`storage_quantum_m`) first, as the device's driver and file did to the measurement: a
    1 mm quantum adds 0.29 mm of spread, +28 % on the 0.36 mm of Kinect v1 noise at 0.5 m, which a
    float simulation lacks (its near bins then read low against the measurement)."""
    groups = curve_groups(observations, side, max_pixels, seed, edges, incidence_edges, local_plane)
    std = np.full(len(groups), np.nan)
    count = np.zeros(len(groups), int)
    for k, parts in enumerate(groups):
        if parts:
            r = np.concatenate([p for _, p in parts])
            count[k] = r.size
            if r.size >= MIN_PIXELS:
                std[k] = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return std, count


def curve_groups(observations: Sequence, side: str, max_pixels: int | None = 20000, seed: int = 0,
                 edges: Sequence[float] = BIN_EDGES_M,
                 incidence_edges: Sequence[float] | None = None,
                 local_plane: bool | None = None) -> list[list[tuple[int, np.ndarray]]]:
    """Per bin (or cell, as :func:`noise_curve`): [(position of the observation in
    ``observations``, its residuals depth - ideal (m) about their local plane, median 0), ...] for every
    observation with at least 10 valid pixels there: what :func:`noise_curve` pools, kept per frame
    so a frame-level bootstrap (:func:`curve_uncertainty`) can resample frames.

    ``local_plane`` (None: :data:`LOCAL_PLANE`): each group's residuals are taken about its own
    local plane (:func:`local_plane_residuals`), else about their median alone."""
    if local_plane is None:
        local_plane = LOCAL_PLANE
    e = np.asarray(edges, float)
    ie = None if incidence_edges is None else np.asarray(incidence_edges, float)
    nj = 1 if ie is None else len(ie) - 1
    ncell = (len(e) - 1) * nj
    groups: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(ncell)]
    for pos, o in enumerate(observations):
        flat = _pixels(o, max_pixels, seed)
        z = o.ideal.reshape(-1)[flat].astype(np.float64)
        d = getattr(o, side).reshape(-1)[flat].astype(np.float64)
        if side == "simulated":
            q = storage_quantum_m(o.measured.reshape(-1)[flat])
            if q > 0:
                d = np.where(d > 0, np.maximum(np.round(d / q), 1.0) * q, d)
        ok = d > 0
        b = np.searchsorted(e, z, side="right") - 1
        if ie is not None:
            from synth.lab.feature_maps import incidence_angle_deg
            a = incidence_angle_deg(o.normals, o.intrinsics, idx=flat)
            j = np.clip(np.searchsorted(ie, np.nan_to_num(a, nan=-1.0), side="right") - 1, -1, nj)
            ok &= (j >= 0) & (j < nj)
            b = np.where((b >= 0) & (b < len(e) - 1), b * nj + j, -1)
        if local_plane:
            v, u = np.divmod(flat, o.ideal.shape[1])
            uv = np.stack([(u - 0.5 * o.ideal.shape[1]) / o.ideal.shape[1],
                           (v - 0.5 * o.ideal.shape[0]) / o.ideal.shape[1]], 1)
        for k in range(ncell):
            sel = ok & (b == k)
            if sel.sum() < 10:
                continue
            r = d[sel] - z[sel]
            if local_plane:
                r = local_plane_residuals(r, z[sel], uv[sel])
            groups[k].append((pos, r - np.median(r)))
    return groups


LOCAL_PLANE_MIN_PIXELS = 30
"""Fewest valid pixels a (frame, bin) group needs for its local plane to be removed (fewer: its median
alone); 3 parameters are fitted, which lowers the std of n pixels by sqrt(1 - 3 / n) on both sides alike."""


def local_plane_residuals(r: np.ndarray, z: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The residuals ``r`` (N,) = depth - ideal (m) of one (frame, bin) group less their local plane.

    A plane that is off the reference plane (tilted by the reference's fit, which the near pixels
    dominate, or by the sensor's low-frequency depth distortion over the strip the bin cuts out of a
    grazing floor) differs from it by an affine function of the pixel in *inverse* depth:
    1 / z' - 1 / z = a + b u + c v, i.e. in depth z' - z = -z^2 (a + b u + c v) to first order. That
    is fitted by least squares on columns z^2, z^2 u, z^2 v (``z`` (N,) ideal depth m, ``uv`` (N, 2)
    pixel coordinates relative to the image centre over the image width) and removed - the local
    plane fit per target patch of Khoshelham & Elberink 2012 and Nguyen et al. 2012, whose axial
    noise is the spread about the patch's own plane. The pixels beyond 5 robust std of the median
    (flying pixels, mixed edges) are left out of the fit. ``r`` itself, less its median, when fewer
    than :data:`LOCAL_PLANE_MIN_PIXELS`."""
    r = np.asarray(r, np.float64)
    if r.size < LOCAL_PLANE_MIN_PIXELS:
        return r - np.median(r)
    r0 = r - np.median(r)
    s = 1.4826 * float(np.median(np.abs(r0)))
    keep = np.abs(r0) <= 5.0 * s if s > 0 else np.ones(r.size, bool)
    if keep.sum() < LOCAL_PLANE_MIN_PIXELS:
        return r0
    z2 = np.asarray(z, np.float64) ** 2
    A = np.stack([z2, z2 * uv[:, 0], z2 * uv[:, 1]], 1)
    x, *_ = np.linalg.lstsq(A[keep], r[keep], rcond=None)
    return r - A @ x


def _robust_std(r: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) if r.size >= MIN_PIXELS else float("nan")


def curve_uncertainty(measured: list[list[tuple[int, np.ndarray]]],
                      simulated: Sequence[list[list[tuple[int, np.ndarray]]]], n_frames: int,
                      n_boot: int = 200, level: float = 0.95, seed: int = 0,
                      max_pixels_per_bin: int = 40000, block: int = 1) -> list[dict]:
    """The sampling spread of the noise curve over frames: a frame-level bootstrap.

    ``measured``: :func:`curve_groups` of the measured side of ``n_frames`` observations;
    ``simulated``: the same of one or more simulations of those frames (their stds are averaged,
    as a benchmark averages seeds). Each of ``n_boot`` replicates draws ``n_frames`` frames with
    replacement (one draw for every bin: a frame's pixels at all distances stay together) and
    recomputes, per bin, the pooled robust std of the measured residuals and the simulated /
    measured ratio on the same frames. Pixels within a frame are far from independent (one frame's
    plane, incidence and noise level), so the frame, not the pixel, is the unit that is resampled.

    Per bin: {"frames": frames with residuals there, "measured_ci": (lo, hi) m, "ratio_ci":
    (lo, hi)}: the central ``level`` percentile interval (NaN where fewer than half the replicates
    have the bin). Each bin's groups are thinned uniformly at random to about
    ``max_pixels_per_bin`` residuals in all (the same share of every frame: the frames keep their
    weights), which leaves the frame-level spread and bounds the cost. ``block`` > 1: a moving-block
    bootstrap's simplest form - runs of ``block`` consecutive frames are drawn together (neighbouring
    frames of a slow hand-held sweep see nearly the same view, so they are not independent)."""
    rng = np.random.default_rng([int(seed), 43])
    nb = len(measured)

    def thin(groups, rate, salt):
        r2 = np.random.default_rng([int(seed), salt])
        return {pos: (g if rate >= 1 else g[r2.random(g.size) < rate]) for pos, g in groups}
    meas, sims = [], []
    for k in range(nb):
        tot = sum(g.size for _, g in measured[k])
        rate = min(1.0, max_pixels_per_bin / tot) if tot else 1.0
        meas.append(thin(measured[k], rate, 2 * k))
        sims.append([thin(s[k], rate, 2 * k + 1 + 1000 * j) for j, s in enumerate(simulated)])
    nblk = -(-int(n_frames) // max(int(block), 1))
    bc = rng.multinomial(nblk, np.full(nblk, 1.0 / nblk), size=int(n_boot))
    counts = np.repeat(bc, max(int(block), 1), axis=1)[:, :int(n_frames)]
    out = []
    a = 100 * (1 - level) / 2
    for k in range(nb):
        m_s, r_s = [], []
        for c in counts:
            mr = [np.repeat(g, c[p]) if c[p] > 1 else g for p, g in meas[k].items() if c[p] > 0]
            m = _robust_std(np.concatenate(mr)) if mr else float("nan")
            ss = []
            for sk in sims[k]:
                sr = [np.repeat(g, c[p]) if c[p] > 1 else g for p, g in sk.items() if c[p] > 0]
                ss.append(_robust_std(np.concatenate(sr)) if sr else float("nan"))
            m_s.append(m)
            r_s.append(float(np.mean(ss)) / m if ss and m > 0 else float("nan"))
        m_s, r_s = np.array(m_s), np.array(r_s)
        ok_m, ok_r = np.isfinite(m_s), np.isfinite(r_s)
        nan2 = (float("nan"), float("nan"))
        out.append({"frames": len(meas[k]),
                    "measured_ci": tuple(np.percentile(m_s[ok_m], [a, 100 - a])) if ok_m.mean() >= 0.5 else nan2,
                    "ratio_ci": tuple(np.percentile(r_s[ok_r], [a, 100 - a])) if ok_r.mean() >= 0.5 else nan2})
    return out


def curve_term(measured_std: np.ndarray, simulated_std: np.ndarray) -> float:
    """Mean |ln(simulated / measured)| over the bins both sides have (0 when none; a simulation
    without a valid pixel in a bin the measurement has counts ln 10 there)."""
    m = np.asarray(measured_std, float)
    s = np.asarray(simulated_std, float)
    has = np.isfinite(m) & (m > 0)
    if not has.any():
        return 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.abs(np.log(s[has] / m[has]))
    lr = np.where(np.isfinite(lr), lr, np.log(10.0))
    return float(np.mean(lr))


def curve_table(observations: Sequence, max_pixels: int | None = 20000, seed: int = 0,
                edges: Sequence[float] = BIN_EDGES_M) -> list[dict]:
    """Per bin with measured pixels: {"bin_m": [lo, hi], "measured_mm", "simulated_mm", "ratio",
    "pixels"} (the fit report's noise curve)."""
    m, n = noise_curve(observations, "measured", max_pixels, seed, edges)
    s, _ = noise_curve(observations, "simulated", max_pixels, seed, edges)
    out = []
    for k in range(len(edges) - 1):
        if np.isfinite(m[k]):
            out.append({"bin_m": [float(edges[k]), float(edges[k + 1])], "measured_mm": 1000 * float(m[k]),
                        "simulated_mm": 1000 * float(s[k]) if np.isfinite(s[k]) else None,
                        "ratio": float(s[k] / m[k]) if np.isfinite(s[k]) and m[k] > 0 else None,
                        "pixels": int(n[k])})
    return out


def noise_curve_report(weight: float, before, after, max_pixels, seed: int) -> dict:
    """``FitResult.noise_curve`` from the evaluation set's (term, observations) of the start and the fit."""
    tb, ta = curve_table(before[1], max_pixels, seed), curve_table(after[1], max_pixels, seed)
    for row, rb in zip(ta, tb):
        row["simulated_mm_before"] = rb["simulated_mm"]
    return {"weight": float(weight), "term_before": float(before[0]), "term": float(after[0]), "bins": ta}


def incidence_cells(observations: Sequence, max_pixels: int | None = 20000, seed: int = 0,
                    edges: Sequence[float] = BIN_EDGES_M,
                    incidence_edges: Sequence[float] = INCIDENCE_EDGES_DEG,
                    z_exponent: float = -0.5) -> tuple[np.ndarray, np.ndarray]:
    """(mean ideal depth m, mean incidence factor theta^2 / (pi/2 - theta)^2 z^z_exponent) per
    (distance bin, incidence class) cell of :func:`noise_curve` (same pixels, flattened the same way;
    NaN where a cell has no measured pixel): where in a cell the axial noise's terms are evaluated
    (``z_exponent``: the incidence term's distance law, ``axial_noise.incidence_z_exponent``)."""
    from synth.lab.feature_maps import incidence_angle_deg
    from synth.sensor.effects.axial_noise import incidence_factor
    e, ie = np.asarray(edges, float), np.asarray(incidence_edges, float)
    nj = len(ie) - 1
    n = (len(e) - 1) * nj
    sz, sg, cnt = np.zeros(n), np.zeros(n), np.zeros(n)
    for o in observations:
        flat = _pixels(o, max_pixels, seed)
        z = o.ideal.reshape(-1)[flat].astype(np.float64)
        a = incidence_angle_deg(o.normals, o.intrinsics, idx=flat)
        ok = (o.measured.reshape(-1)[flat] > 0) & np.isfinite(a)
        b = np.searchsorted(e, z, side="right") - 1
        j = np.searchsorted(ie, np.nan_to_num(a, nan=-1.0), side="right") - 1
        ok &= (b >= 0) & (b < len(e) - 1) & (j >= 0) & (j < nj)
        c = (b * nj + j)[ok]
        g = incidence_factor(np.radians(a[ok])) * np.maximum(z[ok], 0.05) ** float(z_exponent)
        np.add.at(sz, c, z[ok])
        np.add.at(sg, c, g)
        np.add.at(cnt, c, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, sz / cnt, np.nan), np.where(cnt > 0, sg / cnt, np.nan)


def curve_start(config, objective, specs, cells: bool = True) -> dict[str, float]:
    """A starting point that puts the model's noise curve on the measured one, when the model
    has ``axial_noise`` (of its fitted ``specs``): the classic planar calibration (Nguyen et al.
    2012's form sigma0 + sigma2 (z - z_offset)^2 + incidence_m theta^2 / (pi/2 - theta)^2 z^p, their
    p = -0.5)
    fitted to the measured curve per (distance bin, incidence class) cell, less what the model's
    other effects already contribute.

    ``objective`` (a :class:`synth.lab.objective.Objective` with the noise-curve term on) gives the
    curves of ``config`` (its last evaluation's, or one more simulation); per cell (its pixels' mean
    depth z and mean incidence factor G, :func:`incidence_cells`) the measured std m and the
    simulated s give the axial part wanted, a = sqrt(max(m^2 - (s^2 - a_now^2), 0)) - independent
    noise sources add in variance (an approximation for the robust std) - less the model's own
    sigma1 z. sigma0, sigma2, incidence_m >= 0 (those fitted) then minimise the relative squared
    error (the term's log ratio to first order) by non-negative least squares for each z_offset on
    a 0.025 m grid over its bounds and, when ``axial_noise.incidence_z_exponent`` is fitted, for each
    distance law p of the incidence term in -0.5 (Nguyen's), 0, 1, 2 (constant in disparity), each
    clipped to its search bounds (a mean factor per cell stands for the mixture of the cell's angles:
    an approximation the search refines). {} when
    axial_noise is not fitted, the term is off, or fewer than 3 cells have data; with ``cells``
    also when the incidence term is not fitted or no grazing cell (``GRAZING_EDGES_DEG``) has data.

    ``cells`` False: the same on the distance bins alone, with the incidence term at 0 (a capture
    whose few grazing pixels would pull the per-cell start; :func:`synth.lab.fit.fit_model` keeps
    the better of the two by the objective)."""
    from scipy.optimize import nnls
    keys = {s.key: s for s in specs}
    k0, k2, ko, ki, kp = ("axial_noise.sigma0_m", "axial_noise.sigma2_per_m", "axial_noise.z_offset_m",
                          "axial_noise.incidence_m", "axial_noise.incidence_z_exponent")
    if k2 not in keys or getattr(objective, "noise_weight", 0) <= 0:
        return {}
    obs = objective.curve(config)[1]
    px, seed = objective.compare_config.max_pixels_per_frame, objective.seed
    if cells and (ki not in keys or not np.isfinite(noise_curve(obs, "measured", px, seed,
                                                                 incidence_edges=GRAZING_EDGES_DEG)[0]).any()):
        return {}       # no incidence term to start, or no grazing views to start it from
    ie = INCIDENCE_EDGES_DEG if cells else None
    m, _ = noise_curve(obs, "measured", px, seed, incidence_edges=ie)
    s, _ = noise_curve(obs, "simulated", px, seed, incidence_edges=ie)
    p = next(x for x in config.effects if x.name == "axial_noise").params
    exponents = [p.incidence_z_exponent]
    if cells and kp in keys:        # the incidence term's distance law: Nguyen's, 0, z, constant in disparity
        exponents = sorted({min(max(v, keys[kp].low), keys[kp].high) for v in (-0.5, 0.0, 1.0, 2.0)})
    e = np.asarray(BIN_EDGES_M)
    zc = incidence_cells(obs, px, seed)[0] if cells else 0.5 * (e[:-1] + e[1:])
    zz = np.nan_to_num(zc, nan=1.0)
    now_g = np.nan_to_num(incidence_cells(obs, px, seed, z_exponent=p.incidence_z_exponent)[1]) if cells else 0.0
    now = p.sigma0_m + p.sigma1 * zz + p.sigma2_per_m * (zz - p.z_offset_m) ** 2 + p.incidence_m * now_g
    other2 = np.where(np.isfinite(s), np.maximum(np.nan_to_num(s) ** 2 - now ** 2, 0.0), 0.0)
    want = np.sqrt(np.maximum(m ** 2 - other2, 0.0)) - p.sigma1 * zz
    ok = np.isfinite(m) & np.isfinite(zc) & (want > 0)
    if ok.sum() < 3:
        return {}
    z, t = zc[ok], want[ok]
    lo, hi = (keys[ko].low, keys[ko].high) if ko in keys else (p.z_offset_m, p.z_offset_m)
    best = None
    for ex in exponents:
        g = (np.nan_to_num(incidence_cells(obs, px, seed, z_exponent=ex)[1]) if cells else np.zeros(len(zc)))[ok]
        for off in np.unique(np.clip(np.arange(lo, hi + 1e-9, 0.025), lo, hi)):
            cols = ([np.ones_like(z)] if k0 in keys else []) + [(z - off) ** 2] + ([g] if ki in keys and cells else [])
            A = np.stack(cols, 1) / t[:, None]
            x, r = nnls(A, np.ones_like(t))
            if best is None or r < best[0] - 1e-12:
                best = (r, off, x, ex)
    _, off, x, ex = best
    x = list(x)
    out = {}
    if cells and kp in keys:
        out[kp] = float(ex)
    if k0 in keys:
        out[k0] = float(x.pop(0))
    out[k2] = float(x.pop(0))
    if ki in keys:
        out[ki] = float(x.pop(0)) if cells else 0.0
    if ko in keys:
        out[ko] = float(off)
    return {k: float(min(max(v, keys[k].low), keys[k].high)) for k, v in out.items()}
