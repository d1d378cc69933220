"""The sensor-lab report: ``report.html`` with its PNGs next to it, plus ``metrics.json``.

Layout of ``out_dir``::

    report.html            self-contained page (relative links to figures/)
    metrics.json           CompareResult.to_json()  (gap, breakdowns, per-frame gaps, config)
    compare_config.json    effective CompareConfig
    regions.json           the ranked worst regions (bins and image blocks)
    history.json           gap history (written by append_history / run_lab)
    figures/frame_XXX.png  measured, simulated, error map (mm) and validity disagreement
    figures/breakdown_<feature>.png   binned bias / std / invalid fraction / gap term
    figures/history.png    gap per step, effect names as tick labels

matplotlib is imported inside the functions and drives an Agg canvas directly (no pyplot, no
global backend state). The diagnosis page (``diagnosis.html``, signature figures) is
:mod:`synth.lab.signatures`.
"""
from __future__ import annotations

import html
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from data_tools.errors import RealgapError
from data_tools.sequence import spread_indices
from synth.lab.compare import CompareConfig, CompareResult, compare
from synth.lab.features import FrameObservation
from synth.lab.history import append_history, load_history, step_labels
from synth.lab.regions import VALIDITY_LABELS, Region, error_map, validity_map, worst_bins, worst_blocks

__all__ = ["write_report", "run_lab", "plot_frame", "plot_breakdown", "plot_history", "REPORT_FILE", "figure",
           "save_figure", "html_table", "fmt_number", "REPORT_CSS"]

REPORT_FILE = "report.html"
VALIDITY_COLOURS = ("#d9d9d9", "#1f77b4", "#d62728", "#252525")
"""Colours of the validity codes: both valid (light grey), measured only (blue), simulated only
(red), both invalid (black)."""


def figure(width_in: float, height_in: float):
    """:func:`data_tools.results.new_figure`."""
    from data_tools.results import new_figure
    return new_figure(width_in, height_in)


def save_figure(fig, path: str | os.PathLike) -> Path:
    path = Path(path)
    from data_tools.results import atomic_save_figure
    return atomic_save_figure(fig, path)


def plot_frame(path: str | os.PathLike, obs: FrameObservation, regions: Sequence[Region] = ()) -> Path:
    """Measured and simulated depth (m), measured - simulated (mm, colour bar) and the
    validity-disagreement map (legend) of one frame; ``regions`` (blocks of this frame) are
    drawn as numbered rectangles on the two lower panels."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Rectangle

    h, w = obs.shape
    aspect = h / w
    fig = figure(11, 11 * aspect + 1.2)
    axs = fig.subplots(2, 2)
    valid = np.concatenate([obs.measured[obs.measured > 0], obs.simulated[obs.simulated > 0]])
    vmin, vmax = (np.percentile(valid, [1, 99]) if valid.size else (0.0, 1.0))
    for ax, img, name in ((axs[0, 0], obs.measured, "measured"), (axs[0, 1], obs.simulated, "simulated")):
        im = ax.imshow(np.where(img > 0, img, np.nan), cmap="viridis", vmin=vmin, vmax=vmax,
                       interpolation="nearest")
        ax.set_title(f"{name} depth, frame {obs.index} (white: invalid)")
        fig.colorbar(im, ax=ax, label="depth [m]", shrink=0.9)
    err = error_map(obs) * 1000.0
    fin = np.isfinite(err)
    lim = float(np.percentile(np.abs(err[fin]), 98)) if fin.any() else 1.0
    lim = max(lim, 1.0)
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="#bbbbbb")
    ax = axs[1, 0]
    im = ax.imshow(np.ma.masked_invalid(err), cmap=cmap, vmin=-lim, vmax=lim, interpolation="nearest")
    ax.set_title("measured − simulated (grey: invalid in either)")
    fig.colorbar(im, ax=ax, label="measured − simulated [mm]", shrink=0.9)
    ax = axs[1, 1]
    im = ax.imshow(validity_map(obs), cmap=ListedColormap(VALIDITY_COLOURS), vmin=-0.5, vmax=3.5,
                   interpolation="nearest")
    ax.set_title("valid / invalid disagreement")
    # categorical colour bar = the legend of the four codes
    cb = fig.colorbar(im, ax=ax, ticks=[0, 1, 2, 3], shrink=0.9)
    cb.ax.set_yticklabels([label.replace(" valid only", "\nvalid only") for label in VALIDITY_LABELS], fontsize=8)
    cb.set_label("pixel validity (legend)")
    for ax in axs.ravel():
        ax.set_xlabel("u [px]")
        ax.set_ylabel("v [px]")
    for r in regions:
        if r.bbox is None:
            continue
        x0, y0, x1, y1 = r.bbox
        for ax in (axs[1, 0], axs[1, 1]):
            ax.add_patch(Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0, y1 - y0, fill=False, edgecolor="#ff7f0e",
                                   linewidth=2))
            ax.text(x0, y0 - 1, f"#{r.rank}", color="#d95f02", fontsize=9, fontweight="bold", va="bottom",
                    bbox=dict(facecolor="white", alpha=0.7, pad=1, edgecolor="none"))
    return save_figure(fig, path)


def _x_positions(b: dict):
    """x values and tick labels of a breakdown: bin centres for finite numeric bins, indices otherwise."""
    edges = b.get("edges")
    if b.get("categorical") or edges is None or any(not math.isfinite(e) for e in edges):
        return np.arange(len(b["labels"]), dtype=float), list(b["labels"])
    return np.asarray(b["centres"], dtype=float), None


def plot_breakdown(path: str | os.PathLike, feature: str, b: dict) -> Path:
    """Measured vs simulated bias, robust std (mm), invalid fraction and the gap term per bin."""
    x, ticks = _x_positions(b)
    bars = bool(b.get("categorical"))
    unit = f" [{b['unit']}]" if b.get("unit") else ""
    xlabel = f"{b.get('title', feature)}{unit}"
    fig = figure(11, 7.5)
    axs = fig.subplots(2, 2)
    series = (("bias", "median error vs ideal [mm]", 1000.0, "bias"),
              ("std", "robust std (IQR/1.349) [mm]", 1000.0, "spread"),
              ("invalid_fraction", "invalid fraction [–]", 1.0, "invalid pixels"))
    width = 0.38 * (np.min(np.diff(x)) if len(x) > 1 else 1.0)
    for ax, (key, ylabel, scale, what) in zip(axs.ravel()[:3], series):
        for side, colour, off in (("measured", "#1f77b4", -1), ("simulated", "#d62728", 1)):
            y = np.asarray(b[side][key], dtype=float) * scale
            if bars:
                ax.bar(x + off * width / 2, np.nan_to_num(y), width=width, color=colour, label=side)
            else:
                ax.plot(x, y, "o-", color=colour, label=side, markersize=4)
        ax.set_title(f"{what} per bin: {feature}")
        ax.set_ylabel(ylabel)
        ax.set_xlabel(xlabel)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    ax = axs[1, 1]
    et = np.nan_to_num(np.asarray(b["error_term"], dtype=float))
    it = np.nan_to_num(np.asarray(b["invalid_term"], dtype=float))
    bw = 0.8 * (np.min(np.diff(x)) if len(x) > 1 else 1.0)
    ax.bar(x, et, width=bw, color="#9467bd", label="error-distribution term (W1)")
    ax.bar(x, it, width=bw, bottom=et, color="#8c564b", label="invalid-fraction term")
    if "noise_floor" in b:
        fl = np.asarray(b["noise_floor"], dtype=float)
        ax.plot(x, 3 * fl, "k_", markersize=12, markeredgewidth=2, label="3x sampling-noise floor")
    ax.set_title(f"gap term per bin: {feature} (feature term {b.get('feature_term', float('nan')):.3f})")
    ax.set_ylabel("term [–]")
    ax.set_xlabel(xlabel)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    if ticks is not None:
        rot = 45 if len(ticks) > 6 else 0
        for a in axs.ravel():
            a.set_xticks(x)
            a.set_xticklabels(ticks, rotation=rot, ha="right" if rot else "center", fontsize=8)
    else:
        used = np.flatnonzero(np.asarray(b["measured"]["count"]) > 0)
        if used.size:
            e = np.asarray(b["edges"], dtype=float)
            for a in axs.ravel():
                a.set_xlim(e[used[0]], e[used[-1] + 1])
    return save_figure(fig, path)


def plot_history(path: str | os.PathLike, entries: Sequence[dict]) -> Path:
    """Gap per lab step, the effects added at each step as tick labels."""
    if not entries:
        raise RealgapError("plot_history: empty history")
    gaps = [float(e["gap"]) for e in entries]
    x = np.arange(len(gaps))
    fig = figure(max(6.0, 1.1 * len(gaps) + 3), 4.5)
    ax = fig.subplots()
    ax.plot(x, gaps, "o-", color="#2ca02c", label="gap")
    for xi, g in zip(x, gaps):
        ax.annotate(f"{g:.3f}", (xi, g), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    ax.set_xticks(x)
    import textwrap
    labels = ["\n".join(textwrap.wrap(lb, 28, max_lines=4, placeholder=" …")) or lb for lb in step_labels(entries)]
    ax.set_xticklabels(labels, rotation=30, ha="right", fontsize=8)
    ax.set_xlabel("lab step (effects added)")
    ax.set_ylabel("gap [–]")
    ax.set_title("gap history: add an effect, watch the error fall")
    ax.set_ylim(bottom=0, top=max(gaps) * 1.15 + 1e-9)
    ax.legend()
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def html_table(rows: Sequence[Sequence], header: Sequence[str]) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def fmt_number(x) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    return "n/a" if not math.isfinite(x) else f"{x:.4f}"


REPORT_CSS = """body{font-family:sans-serif;margin:2em;max-width:1200px}table{border-collapse:collapse;margin:1em 0}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}img{max-width:100%;border:1px solid #eee}
h2{border-bottom:1px solid #ccc}.gap{font-size:1.6em}"""


def write_report(result: CompareResult, observations_subset: Sequence[FrameObservation],
                 out_dir: str | os.PathLike, history: Sequence[dict] | str | os.PathLike | None = None, *,
                 regions: Sequence[Region] | None = None, top_bins: int = 5, top_blocks: int = 5,
                 block_px: int = 32, title: str = "Sensor lab report",
                 calibration: Sequence[FrameObservation] | None = None, fit: dict | None = None) -> Path:
    """Write ``out_dir/report.html`` (+ figures, metrics.json, regions.json); returns its path.

    observations_subset: the frames to show (error maps, worst image blocks); usually a few.
    history: entries, or a folder / history.json path to read them from; None = read
    ``out_dir/history.json`` if present. regions: precomputed worst regions (default: the
    ``top_bins`` worst bins of ``result`` and the ``top_blocks`` worst blocks of the subset).
    calibration: every frame of a planar-target capture (masked sequence): adds noise vs distance
    and the mean residual map (:mod:`synth.lab.calibration`). fit: the fit record
    (``FitResult.to_json()``) of the model being compared: adds the fitted parameters with their
    profile intervals and the ones that ended on a bound.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figs = out / "figures"
    obs = list(observations_subset)
    if history is None or isinstance(history, (str, os.PathLike)):
        entries = load_history(out if history is None else history)
    else:
        entries = list(history)
    if regions is None:
        cfg = CompareConfig.from_dict(result.config) if result.config else CompareConfig()
        regions = worst_bins(result, top_bins) + (worst_blocks(obs, cfg, top_blocks, block_px) if obs else [])
    regions = list(regions)
    result.save(out)
    from data_tools.results import atomic_write_json
    atomic_write_json(out / "regions.json", [r.to_json() for r in regions], indent=1)

    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{REPORT_CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    parts.append(f"<p class='gap'>gap = <b>{fmt_number(result.gap)}</b></p>")
    summary = [("effects", ", ".join(result.effects) or "(none given)"), ("label", result.label or ""),
               ("frames", len(result.frame_gaps)), ("sampled geometry pixels", result.n_samples),
               ("spatial term S (weighted in the gap)", fmt_number(result.spatial_term))]
    summary += [(f"feature term {f}" + ("" if f in result.gap_features else " (not in gap)"), fmt_number(t))
                for f, t in result.feature_terms.items()]
    summary += [(f"skipped feature {f}", why) for f, why in result.skipped_features.items()]
    uv = result.diagnostics.get("unmodelled_valid_fraction", {})
    if uv:
        summary.append(("valid where the model has no geometry (measured / simulated)",
                        f"{fmt_number(uv.get('measured'))} / {fmt_number(uv.get('simulated'))}"))
    parts.append("<h2>Summary</h2>" + html_table(summary, ("quantity", "value")))
    parts.append("<p>Definition: see <code>synth/lab/compare.py</code>; numbers in "
                 "<a href='metrics.json'>metrics.json</a>, configuration in "
                 "<a href='compare_config.json'>compare_config.json</a>.</p>")

    parts.append("<h2>Where the model fails worst</h2>"
                 "<p>Feature bins and image blocks whose disagreement exceeds 3x the level that "
                 "sampling noise alone produces when the model is right; score = excess over "
                 "that noise floor.</p><ol>")
    for r in regions:
        parts.append(f"<li>[{html.escape(r.kind)} #{r.rank}, score {fmt_number(r.score)}] {html.escape(r.description)}</li>")
    parts.append("</ol>")
    for kind, what in (("bin", "feature bin"), ("block", "image block")):
        if not any(r.kind == kind for r in regions):
            parts.append(f"<p>No {what} differs from the measurement beyond sampling noise.</p>")

    if entries:
        plot_history(figs / "history.png", entries)
        parts.append("<h2>Gap history</h2><img src='figures/history.png' alt='gap history'>")
        parts.append(html_table([(e["step"], e["timestamp"], ", ".join(e["effects"]), fmt_number(e["gap"]), e.get("label") or "")
                             for e in entries], ("step", "time (UTC)", "effects", "gap", "label")))

    if calibration:
        from synth.lab.calibration import calibration_section
        parts.append(calibration_section(calibration, figs))
    if fit:
        parts.append(fit_section(fit))

    parts.append("<h2>Binned statistics: measured vs simulated</h2>")
    for f, b in result.breakdowns.items():
        name = f"breakdown_{f}.png"
        plot_breakdown(figs / name, f, b)
        parts.append(f"<h3>{html.escape(f)}</h3><img src='figures/{name}' alt='{html.escape(f)} breakdown'>")

    if obs:
        parts.append("<h2>Frames</h2><p>Orange rectangles: worst image blocks (numbered as in the list above).</p>")
        for k, o in enumerate(obs):
            name = f"frame_{k:03d}.png"
            plot_frame(figs / name, o, [r for r in regions if r.kind == "block" and r.frame == k])
            parts.append(f"<h3>frame {o.index}</h3><img src='figures/{name}' alt='frame {o.index}'>")

    parts.append("<h2>Per-frame gaps</h2>" + html_table(
        [(i, fmt_number(g)) for i, g in zip(result.frame_indices, result.frame_gaps)], ("frame", "gap")))
    parts.append("</body></html>\n")
    from data_tools.results import atomic_write_text
    return atomic_write_text(out / REPORT_FILE, "\n".join(parts))


def fit_section(fit: dict) -> str:
    """HTML: the fitted parameters, their intervals (joint and one at a time), correlated pairs
    and bound warnings of a fit record."""
    iv, ab = fit.get("intervals") or {}, fit.get("at_bound") or {}
    single, infl = fit.get("intervals_one_at_a_time") or {}, fit.get("inflation") or {}
    rows = []
    for k, v in (fit.get("params") or {}).items():
        lo_hi, s1 = iv.get(k), single.get(k)
        rows.append([k, f"{v:.5g}", f"[{lo_hi[0]:.5g}, {lo_hi[1]:.5g}]" if lo_hi else "-",
                     f"[{s1[0]:.5g}, {s1[1]:.5g}]" if s1 else "-",
                     f"{infl[k]:.2f}" if k in infl else "-", f"AT BOUND - {ab[k]}" if k in ab else ""])
    note = (f"Gap {fit.get('gap_before', float('nan')):.4f} -> {fit.get('gap', float('nan')):.4f}. One at a time: "
            f"the values whose gap stays within the gap's noise ({fit.get('gap_noise', float('nan')):.4f}) of the "
            f"best, the other parameters at the fit. Joint: that interval widened by the inflation factor "
            f"1/sqrt(1 - R^2) of a local quadratic model of the gap (how far the other parameters can compensate). "
            f"An end on the search bound means the data does not bound the parameter there.")
    corr = fit.get("correlations") or {}
    extra = ""
    if corr:
        extra = "<p>" + html.escape("Correlated estimates (r < 0: a trade-off, one up and the other down fit "
                                    "alike): " + ", ".join(f"{k.replace('|', ' vs ')} r = {r:+.2f}"
                                                           for k, r in corr.items())) + "</p>"
    return (f"<h2>Fitted parameters</h2><p>{html.escape(note)}</p>"
            + html_table(rows, ["parameter", "fitted", "joint interval", "one at a time", "inflation", "note"])
            + extra)


def run_lab(observations: Sequence[FrameObservation], out_dir: str | os.PathLike, *,
            effects: Sequence[str] = (), label: str | None = None, config: CompareConfig | None = None,
            compare_against: str | os.PathLike | None = None, report_frames: int = 4,
            planar: bool = False, fit: dict | None = None) -> CompareResult:
    """One lab step: compare, save metrics.json, append to the history, write the report.

    report_frames: how many frames (evenly spread) get error-map figures. planar: the frames are
    a planar-target capture (the report adds the calibration figures).
    """
    obs = list(observations)
    result = compare(obs, config, effects=effects, label=label)
    entries = append_history(out_dir, list(effects), result.gap, label, compare_against=compare_against)
    k = max(0, min(int(report_frames), len(obs)))
    picks = spread_indices(len(obs), k)
    write_report(result, [obs[i] for i in picks], out_dir, entries, calibration=obs if planar else None, fit=fit)
    return result


def evaluations_text(stages: dict, total: int, max_evaluations: int) -> str:
    """What a fit's evaluation count counts, for the CLI line: ``"42 evaluations (search 22 of a
    budget of 24, raised from max_evaluations 3 by the screen; start 2, screen 8, ...)"``.
    ``stages``: ``FitResult.stages``; ``max_evaluations``: the requested search budget. The
    search alone honours the budget; the other stages come on top of it."""
    search = stages.get("search", {})
    used, budget = int(search.get("evaluations", 0)), int(search.get("budget", max_evaluations))
    raised = f", raised from max_evaluations {max_evaluations} by the screen" if budget > max_evaluations else ""
    rest = ", ".join(f"{name} {int(s.get('evaluations', 0))}" for name, s in stages.items()
                     if name != "search" and int(s.get("evaluations", 0)))
    return f"{total} evaluations (search {used} of a budget of {budget}{raised}" + (f"; {rest})" if rest else ")")
