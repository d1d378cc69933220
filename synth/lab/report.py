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
global backend state).
"""
from __future__ import annotations

import html
import json
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from data_tools.errors import RealgapError
from data_tools.sequence import spread_indices
from synth.lab.compare import (VALIDITY_LABELS, CompareConfig, CompareResult, Region, compare,
                               error_map, validity_map, worst_bins, worst_blocks)
from synth.lab.features import FrameObservation
from synth.lab.history import append_history, load_history, step_labels

REPORT_FILE = "report.html"
VALIDITY_COLOURS = ("#d9d9d9", "#1f77b4", "#d62728", "#252525")
"""Colours of the validity codes: both valid (light grey), measured only (blue), simulated only
(red), both invalid (black)."""


def _figure(width_in: float, height_in: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | os.PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def plot_frame(path: str | os.PathLike, obs: FrameObservation, regions: Sequence[Region] = ()) -> Path:
    """Measured and simulated depth (m), measured - simulated (mm, colour bar) and the
    validity-disagreement map (legend) of one frame; ``regions`` (blocks of this frame) are
    drawn as numbered rectangles on the two lower panels."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Rectangle

    h, w = obs.shape
    aspect = h / w
    fig = _figure(11, 11 * aspect + 1.2)
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
    return _save(fig, path)


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
    fig = _figure(11, 7.5)
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
    return _save(fig, path)


def plot_history(path: str | os.PathLike, entries: Sequence[dict]) -> Path:
    """Gap per lab step, the effects added at each step as tick labels."""
    if not entries:
        raise RealgapError("plot_history: empty history")
    gaps = [float(e["gap"]) for e in entries]
    x = np.arange(len(gaps))
    fig = _figure(max(6.0, 1.1 * len(gaps) + 3), 4.5)
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
    return _save(fig, path)


def _table(rows: Sequence[Sequence], header: Sequence[str]) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _fmt(x) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    return "n/a" if not math.isfinite(x) else f"{x:.4f}"


_CSS = """body{font-family:sans-serif;margin:2em;max-width:1200px}table{border-collapse:collapse;margin:1em 0}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}img{max-width:100%;border:1px solid #eee}
h2{border-bottom:1px solid #ccc}.gap{font-size:1.6em}"""


def write_report(result: CompareResult, observations_subset: Sequence[FrameObservation],
                 out_dir: str | os.PathLike, history: Sequence[dict] | str | os.PathLike | None = None, *,
                 regions: Sequence[Region] | None = None, top_bins: int = 5, top_blocks: int = 5,
                 block_px: int = 32, title: str = "Sensor lab report") -> Path:
    """Write ``out_dir/report.html`` (+ figures, metrics.json, regions.json); returns its path.

    observations_subset: the frames to show (error maps, worst image blocks); usually a few.
    history: entries, or a folder / history.json path to read them from; None = read
    ``out_dir/history.json`` if present. regions: precomputed worst regions (default: the
    ``top_bins`` worst bins of ``result`` and the ``top_blocks`` worst blocks of the subset).
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
    (out / "regions.json").write_text(json.dumps([r.to_json() for r in regions], indent=1) + "\n")

    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    parts.append(f"<p class='gap'>gap = <b>{_fmt(result.gap)}</b></p>")
    summary = [("effects", ", ".join(result.effects) or "(none given)"), ("label", result.label or ""),
               ("frames", len(result.frame_gaps)), ("sampled geometry pixels", result.n_samples),
               ("spatial term S (weighted in the gap)", _fmt(result.spatial_term))]
    summary += [(f"feature term {f}" + ("" if f in result.gap_features else " (not in gap)"), _fmt(t))
                for f, t in result.feature_terms.items()]
    summary += [(f"skipped feature {f}", why) for f, why in result.skipped_features.items()]
    uv = result.diagnostics.get("unmodelled_valid_fraction", {})
    if uv:
        summary.append(("valid where the model has no geometry (measured / simulated)",
                        f"{_fmt(uv.get('measured'))} / {_fmt(uv.get('simulated'))}"))
    parts.append("<h2>Summary</h2>" + _table(summary, ("quantity", "value")))
    parts.append("<p>Definition: see <code>synth/lab/compare.py</code>; numbers in "
                 "<a href='metrics.json'>metrics.json</a>, configuration in "
                 "<a href='compare_config.json'>compare_config.json</a>.</p>")

    parts.append("<h2>Where the model fails worst</h2>"
                 "<p>Feature bins and image blocks whose disagreement exceeds 3x the level that "
                 "sampling noise alone produces when the model is right; score = excess over "
                 "that noise floor.</p><ol>")
    for r in regions:
        parts.append(f"<li>[{html.escape(r.kind)} #{r.rank}, score {_fmt(r.score)}] {html.escape(r.description)}</li>")
    parts.append("</ol>")
    for kind, what in (("bin", "feature bin"), ("block", "image block")):
        if not any(r.kind == kind for r in regions):
            parts.append(f"<p>No {what} differs from the measurement beyond sampling noise.</p>")

    if entries:
        plot_history(figs / "history.png", entries)
        parts.append("<h2>Gap history</h2><img src='figures/history.png' alt='gap history'>")
        parts.append(_table([(e["step"], e["timestamp"], ", ".join(e["effects"]), _fmt(e["gap"]), e.get("label") or "")
                             for e in entries], ("step", "time (UTC)", "effects", "gap", "label")))

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

    parts.append("<h2>Per-frame gaps</h2>" + _table(
        [(i, _fmt(g)) for i, g in zip(result.frame_indices, result.frame_gaps)], ("frame", "gap")))
    parts.append("</body></html>\n")
    path = out / REPORT_FILE
    path.write_text("\n".join(parts))
    return path


def run_lab(observations: Sequence[FrameObservation], out_dir: str | os.PathLike, *,
            effects: Sequence[str] = (), label: str | None = None, config: CompareConfig | None = None,
            compare_against: str | os.PathLike | None = None, report_frames: int = 4) -> CompareResult:
    """One lab step: compare, save metrics.json, append to the history, write the report.

    report_frames: how many frames (evenly spread) get error-map figures.
    """
    obs = list(observations)
    result = compare(obs, config, effects=effects, label=label)
    entries = append_history(out_dir, list(effects), result.gap, label, compare_against=compare_against)
    k = max(0, min(int(report_frames), len(obs)))
    picks = spread_indices(len(obs), k)
    write_report(result, [obs[i] for i in picks], out_dir, entries)
    return result




# ============================================================================================
# Diagnosis page: the top candidate effects with their signature figures
# ============================================================================================
#
# A signature is what an effect does to the measured images that nothing else does; each
# figure shows the measurement, the current model (``base``) and the model with the candidate
# added (fitted parameters) side by side, so the page answers "is this effect what is missing?"
# visually. Each effect declares its signature (``Effect.SIGNATURE``: title, explanation, figure
# kind and panels) in its own file; the figure kinds are drawn here (:data:`PLOTS`); effects
# without one get the generic distance breakdown.

DIAGNOSIS_FILE = "diagnosis.html"
_SERIES = (("measured", "#1f77b4", "o-"), ("current model", "#7f7f7f", "s--"), ("with candidate", "#d62728", "^-"))


PLOTS: dict[str, Callable[..., Path]] = {}
"""Signature figure kinds (:attr:`synth.sensor.registry.Signature.plot`) -> ``plot(path, base,
candidate, signature)``; ``base``/``candidate``: FrameObservation lists (same frames; measured
depth identical, simulated by the current model / with the candidate)."""


def _plot_kind(kind: str):
    def deco(fn):
        PLOTS[kind] = fn
        return fn
    return deco


def signature_of(effect: str):
    """The :class:`~synth.sensor.registry.Signature` an effect declares (None: unknown effect or
    none declared)."""
    from synth.sensor.registry import effect_class, effect_names
    return effect_class(effect).SIGNATURE if effect in effect_names() else None


def plot_signature(path, effect: str, base, candidate) -> Path:
    """The signature figure of ``effect`` (the generic distance breakdown when it declares none)."""
    sig = signature_of(effect)
    if sig is None:
        return _generic_signature(path, base, candidate)
    if sig.plot not in PLOTS:
        raise ValueError(f"effect {effect!r}: unknown signature plot {sig.plot!r}; known: {', '.join(PLOTS)}")
    return PLOTS[sig.plot](path, base, candidate, sig)


def pixel_samples(observations: Sequence[FrameObservation], feature: str,
                  feature_config=None) -> dict[str, np.ndarray]:
    """Every geometry pixel (ideal > 0) of the frames with its ``feature`` value: dict of (N,)
    arrays ``x`` (feature value; categorical features give codes and ``names``), ``ideal``,
    ``measured``, ``simulated`` (metres, 0 invalid), ``frame`` (position in the list)."""
    from synth.lab.features import CategoricalValues, FeatureConfig, FrameFeatures, make_feature

    fc = feature_config or FeatureConfig()
    feat = make_feature(feature, fc)
    xs, zi, zm, zs, fr = [], [], [], [], []
    names: list[str] = []
    for k, o in enumerate(observations):
        ff = FrameFeatures(o, fc)
        if not feat.available(ff):
            continue
        idx = np.flatnonzero(o.ideal.reshape(-1) > 0)
        v = feat.values(ff, idx)
        if isinstance(v, CategoricalValues):
            remap = []
            for nm in v.names:
                if nm not in names:
                    names.append(nm)
                remap.append(names.index(nm))
            remap = np.asarray(remap + [-1], dtype=np.int64)
            v = remap[np.where(v.codes >= 0, v.codes, len(remap) - 1)].astype(np.float64)
        xs.append(np.asarray(v, dtype=np.float64))
        zi.append(o.ideal.reshape(-1)[idx])
        zm.append(o.measured.reshape(-1)[idx])
        zs.append(o.simulated.reshape(-1)[idx])
        fr.append(np.full(idx.size, k))
    cat = lambda a: np.concatenate(a) if a else np.zeros(0)  # noqa: E731
    out = {"x": cat(xs), "ideal": cat(zi), "measured": cat(zm), "simulated": cat(zs), "frame": cat(fr)}
    if names:
        out["names"] = np.asarray(names, dtype=object)
    return out


def binned_statistics(x: np.ndarray, depth: np.ndarray, ideal: np.ndarray, edges: Sequence[float],
                      min_count: int = 20) -> dict[str, np.ndarray]:
    """Per bin [edges[k], edges[k+1]) of ``x``: ``count``, ``invalid_fraction``, ``bias`` (median
    of depth - ideal over valid pixels, m) and ``std`` (IQR / 1.349, m); NaN where a bin has fewer
    than ``min_count`` pixels (or valid pixels for bias/std)."""
    e = np.asarray(edges, dtype=np.float64)
    nb = len(e) - 1
    k = np.searchsorted(e, x, side="right") - 1
    k[(k < 0) | (k >= nb) | ~np.isfinite(x)] = -1
    out = {n: np.full(nb, np.nan) for n in ("invalid_fraction", "bias", "std")}
    out["count"] = np.zeros(nb, np.int64)
    valid = depth > 0
    for b in range(nb):
        sel = k == b
        n = int(sel.sum())
        out["count"][b] = n
        if n < min_count:
            continue
        v = valid & sel
        out["invalid_fraction"][b] = 1.0 - v.sum() / n
        if v.sum() >= min_count:
            err = (depth[v] - ideal[v]).astype(np.float64)
            q1, q2, q3 = np.percentile(err, [25, 50, 75])
            out["bias"][b] = q2
            out["std"][b] = (q3 - q1) / 1.349
    return out


_STAT_LABEL = {"invalid_fraction": ("invalid fraction [–]", 1.0), "bias": ("median error vs ideal [mm]", 1000.0),
               "std": ("robust std (IQR/1.349) [mm]", 1000.0)}


def _edges_for(feature: str, feature_config=None):
    """Bin edges, x positions and tick labels (None for numeric axes) of a feature."""
    from synth.lab.features import FeatureConfig, make_feature
    feat = make_feature(feature, feature_config or FeatureConfig())
    b = feat.binning()
    e = np.asarray(b.edges, dtype=np.float64)
    if np.isinf(e).any():
        return e, np.arange(len(b.labels), dtype=float), list(b.labels), feat
    return e, b.centres, None, feat


def _series(base, candidate, feature: str):
    """(label, colour, style, samples) of measured / current model / with candidate."""
    sb = pixel_samples(base, feature)
    sc = pixel_samples(candidate, feature) if candidate else None
    out = [("measured", sb["measured"], sb), ("current model", sb["simulated"], sb)]
    if sc is not None:
        out.append(("with candidate", sc["simulated"], sc))
    return out


def _binned_axes(fig, axs, base, candidate, feature: str, stats: Sequence[str], title: str = "") -> None:
    from synth.lab.features import FeatureConfig, make_feature
    series = _series(base, candidate, feature)
    feat = make_feature(feature, FeatureConfig())
    if getattr(feat, "categorical", False):
        # categories: codes of the base samples' names; the candidate's samples are remapped
        names = list(series[0][2].get("names", []))
        for i, (label, depth, s) in enumerate(series):
            own = list(s.get("names", []))
            if own != names:
                remap = np.array([names.index(n) if n in names else -1 for n in own] + [-1])
                x = s["x"].astype(np.int64)
                s = dict(s, x=remap[np.where(x >= 0, x, len(own))].astype(np.float64))
                series[i] = (label, depth, s)
        edges = np.arange(len(names) + 1) - 0.5
        xpos = np.arange(len(names), dtype=float)
        ticks = names
    else:
        edges, xpos, ticks, feat = _edges_for(feature)
    unit = f" [{feat.unit}]" if feat.unit else ""
    for ax, stat in zip(axs, stats):
        ylabel, scale = _STAT_LABEL[stat]
        used = np.zeros(len(xpos), bool)
        for (label, depth, s), (_, colour, style) in zip(series, _SERIES):
            st = binned_statistics(s["x"], depth, s["ideal"], edges)
            y = st[stat] * scale
            used |= np.isfinite(y)
            ax.plot(xpos, y, style, color=colour, label=label, markersize=4)
        ax.set_xlabel(f"{feat.title}{unit}")
        ax.set_ylabel(ylabel)
        ax.set_title(title or f"{stat.replace('_', ' ')} per {feature.replace('_', ' ')} bin", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        if ticks is not None:
            ax.set_xticks(xpos)
            ax.set_xticklabels(ticks, rotation=45, ha="right", fontsize=8)
        elif used.any():
            i = np.flatnonzero(used)
            ax.set_xlim(edges[i[0]], edges[i[-1] + 1])


def plot_binned_signature(path, base, candidate, panels: Sequence[tuple[str, str]]) -> Path:
    """Measured / current model / with candidate: one panel per ``(feature, statistic)``
    (statistic: ``bias``, ``std`` or ``invalid_fraction`` per bin of the feature)."""
    fig = _figure(5.2 * len(panels), 4.2)
    axs = np.atleast_1d(fig.subplots(1, len(panels)))
    by_feature: dict[str, tuple[list, list]] = {}  # the pixel features of one feature computed once
    for ax, (feature, stat) in zip(axs, panels):
        axes, stats = by_feature.setdefault(feature, ([], []))
        axes.append(ax)
        stats.append(stat)
    for feature, (axes, stats) in by_feature.items():
        _binned_axes(fig, axes, base, candidate, feature, tuple(stats))
    return _save(fig, path)


@_plot_kind("binned")
def _binned_signature(path, base, candidate, sig) -> Path:
    return plot_binned_signature(path, base, candidate, sig.panels)


@_plot_kind("shadow_sides")
def plot_shadow_signature(path, base, candidate, sig=None) -> Path:
    """Invalid fraction vs ``edge_shadow`` (shadow side +, lit side -) and one frame's holes
    next to its depth edges, coloured by side."""
    from synth.lab.features import FeatureConfig, FrameFeatures, make_feature
    fig = _figure(14, 4.6)
    axs = fig.subplots(1, 3)
    if base and base[0].projector_offset_m is not None:
        _binned_axes(fig, axs[:1], base, candidate, "edge_shadow", ("invalid_fraction",))
    else:
        _binned_axes(fig, axs[:1], base, candidate, "edge_distance", ("invalid_fraction",))
    # frame with most measured holes near edges
    fc = FeatureConfig()
    best, best_n, best_vals = None, -1, None
    for o in base:
        ff = FrameFeatures(o, fc)
        f = make_feature("edge_shadow", fc)
        if not f.available(ff):
            continue
        vals = f.values(ff, np.arange(o.ideal.size)).reshape(o.shape)
        n = int(((np.abs(vals) < 8) & (o.measured <= 0) & (o.ideal > 0)).sum())
        if n > best_n:
            best, best_n, best_vals = o, n, vals
    for ax, which, name in ((axs[1], "measured", "measured"), (axs[2], "simulated", "current model")):
        if best is None:
            ax.axis("off")
            continue
        img = getattr(best, which) if which == "measured" else best.simulated
        if which == "simulated" and candidate:
            img = next((c.simulated for c in candidate if c.index == best.index), img)
            name = "with candidate"
        ax.imshow(np.where(best.ideal > 0, best.ideal, np.nan), cmap="Greys", interpolation="nearest")
        holes = (img <= 0) & (best.ideal > 0)
        shadow = holes & (best_vals > 0) & (best_vals < 16)
        lit = holes & (best_vals < 0) & (best_vals > -16)
        other = holes & ~shadow & ~lit
        rgba = np.zeros(best.shape + (4,))
        rgba[other] = (0.2, 0.2, 0.9, 0.5)
        rgba[lit] = (0.1, 0.7, 0.1, 0.9)
        rgba[shadow] = (0.9, 0.1, 0.1, 0.9)
        ax.imshow(rgba, interpolation="nearest")
        ax.set_title(f"{name} holes, frame {best.index}\nred: shadow side of an edge, green: lit side, "
                     f"blue: elsewhere", fontsize=9)
        ax.set_xlabel("u [px]")
        ax.set_ylabel("v [px]")
    return _save(fig, path)


def depth_level_steps(depth: np.ndarray, max_levels: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """Distinct valid depth values (m) and the step to the next distinct value (m): the
    quantisation staircase of a sensor (steps ~ z² / (f b) x subpixel step for disparity
    quantisation; constant steps for a plain PNG rounding)."""
    v = np.unique(depth[depth > 0].astype(np.float64))
    if v.size < 2:
        return np.zeros(0), np.zeros(0)
    steps = np.diff(v)
    z = v[:-1]
    if z.size > max_levels:
        pick = np.linspace(0, z.size - 1, max_levels).round().astype(int)
        z, steps = z[pick], steps[pick]
    return z, steps


@_plot_kind("disparity_levels")
def plot_quantization_signature(path, base, candidate, sig=None) -> Path:
    """Spacing of consecutive distinct depth values vs depth (log-log, z² reference) and a
    histogram of depths in a 10 cm window (the comb of levels)."""
    fig = _figure(12, 4.6)
    axs = fig.subplots(1, 2)
    sets = [("measured", np.concatenate([o.measured.ravel() for o in base]) if base else np.zeros(0)),
            ("current model", np.concatenate([o.simulated.ravel() for o in base]) if base else np.zeros(0))]
    if candidate:
        sets.append(("with candidate", np.concatenate([o.simulated.ravel() for o in candidate])))
    ax = axs[0]
    for (name, d), (_, colour, _) in zip(sets, _SERIES):
        z, st = depth_level_steps(d)
        ok = (st > 0) & (st < 0.2)
        if ok.any():
            ax.scatter(z[ok], st[ok] * 1000, s=4, color=colour, alpha=0.5, label=name)
    zm, sm = depth_level_steps(sets[0][1])
    ok = (sm > 0) & (sm < 0.2) & (zm > 0)
    if ok.sum() > 10:
        c = float(np.median(sm[ok] / zm[ok] ** 2))
        zz = np.linspace(zm[ok].min(), zm[ok].max(), 50)
        ax.plot(zz, c * zz ** 2 * 1000, "k-", label=f"c·z² (c = {c * 1000:.2f} mm/m²)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("depth z [m]")
    ax.set_ylabel("spacing to the next depth level [mm]")
    ax.set_title("depth levels: spacing vs depth", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax = axs[1]
    dm = sets[0][1]
    dm = dm[dm > 0]
    if dm.size:
        zc = float(np.percentile(dm, 75))
        lo, hi = zc - 0.05, zc + 0.05
        for (name, d), (_, colour, _) in zip(sets, _SERIES):
            sel = d[(d > lo) & (d < hi)]
            if sel.size:
                ax.hist(sel, bins=400, range=(lo, hi), histtype="step", color=colour, label=name)
        ax.set_xlabel("depth z [m]")
        ax.set_ylabel("pixels")
        ax.set_title(f"depth histogram around {zc:.2f} m (0.25 mm bins)", fontsize=10)
        ax.legend(fontsize=8)
    return _save(fig, path)


def radial_error_map(observations: Sequence[FrameObservation], which: str = "measured",
                     block_px: int = 16) -> np.ndarray:
    """(H/b, W/b) median of depth - ideal (m) per image block over all frames (NaN: no data)."""
    if not observations:
        return np.zeros((0, 0))
    h, w = observations[0].shape
    by, bx = (h + block_px - 1) // block_px, (w + block_px - 1) // block_px
    vals: list[list[np.ndarray]] = [[] for _ in range(by * bx)]
    vv, uu = np.mgrid[0:h, 0:w]
    key = (vv // block_px) * bx + (uu // block_px)
    for o in observations:
        d = getattr(o, which)
        ok = (d > 0) & (o.ideal > 0)
        e = (d - o.ideal)[ok]
        kk = key[ok]
        order = np.argsort(kk, kind="stable")
        kk, e = kk[order], e[order]
        cuts = np.flatnonzero(np.diff(kk)) + 1
        for grp_k, grp_e in zip(np.split(kk, cuts), np.split(e, cuts)):
            if grp_k.size:
                vals[int(grp_k[0])].append(grp_e)
    out = np.full(by * bx, np.nan)
    for i, lst in enumerate(vals):
        if lst:
            a = np.concatenate(lst)
            if a.size >= 10:
                out[i] = np.median(a)
    return out.reshape(by, bx)


@_plot_kind("radial_error_map")
def plot_distortion_signature(path, base, candidate, sig=None) -> Path:
    """Median error vs normalised radius, and the block maps of the median error (measured,
    with candidate)."""
    fig = _figure(15, 4.4)
    axs = fig.subplots(1, 3)
    _binned_axes(fig, axs[:1], base, candidate, "radial", ("bias",))
    maps = [("measured", radial_error_map(base, "measured"))]
    maps.append(("with candidate" if candidate else "current model",
                 radial_error_map(candidate or base, "simulated")))
    fin = np.concatenate([m[np.isfinite(m)] for _, m in maps]) if maps else np.zeros(0)
    lim = max(float(np.percentile(np.abs(fin), 95)) * 1000, 1.0) if fin.size else 1.0
    for ax, (name, m) in zip(axs[1:], maps):
        im = ax.imshow(m * 1000, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
        ax.set_title(f"{name}: median error per 16 px block", fontsize=10)
        ax.set_xlabel("block column")
        ax.set_ylabel("block row")
        fig.colorbar(im, ax=ax, label="median depth − ideal [mm]", shrink=0.85)
    return _save(fig, path)


def _generic_signature(path, base, candidate) -> Path:
    return plot_binned_signature(path, base, candidate, [("distance", "bias"), ("distance", "std"),
                                                         ("distance", "invalid_fraction")])


def write_diagnosis_report(diagnosis: dict, base: Sequence[FrameObservation],
                           candidates: dict[str, Sequence[FrameObservation]], out_dir: str | os.PathLike, *,
                           measured_name: str = "", title: str = "Sensor lab diagnosis") -> Path:
    """Write ``out_dir/diagnosis.html`` (+ figures/diag_*.png): the ranking table of
    ``diagnosis`` (the ``Diagnosis.to_json()`` dict) and, for every candidate in
    ``candidates`` (effect -> observations simulated with it, same frames as ``base``), its
    evidence sentence and signature figure. Returns the page path."""
    out = Path(out_dir)
    figs = out / "figures"
    ranking = list(diagnosis.get("ranking", []))
    gap = diagnosis.get("gap")
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    if measured_name:
        parts.append(f"<p>measured sequence: <code>{html.escape(measured_name)}</code></p>")
    model = diagnosis.get("model")
    parts.append(f"<p class='gap'>gap of the current model = <b>{_fmt(gap)}</b></p>")
    if model is not None:
        parts.append(f"<p>current model: {html.escape(', '.join(model) or 'ideal (no effect)')}</p>")
    parts.append("<p>Each candidate effect was added to the current model, its parameters fitted to the "
                 "measured sequence, and the gap measured again; gain = (gap − gap after) / gap. Numbers "
                 "in <a href='diagnosis.json'>diagnosis.json</a>.</p>")
    rows = []
    for r, c in enumerate(ranking, 1):
        allp = c.get("params") or {}
        eff = str(c.get("effect"))
        own = [f"{k.split('.', 1)[-1]}={_fmt(v)}" for k, v in allp.items() if k.startswith(eff + ".") or "." not in k]
        rest = [f"{k}={_fmt(v)}" for k, v in allp.items() if "." in k and not k.startswith(eff + ".")]
        params = ", ".join(own) + (f" (with the model refitted: {', '.join(rest)})" if rest else "")
        rows.append((r, c.get("effect"), _fmt(c.get("gap_after")), f"{100 * float(c.get('gain', 0)):.1f} %",
                     params, c.get("evidence", "")))
    parts.append("<h2>Ranking</h2>" + _table(rows, ("rank", "effect", "gap after", "gain", "fitted parameters",
                                                    "evidence")))
    skipped = diagnosis.get("skipped")
    if skipped:
        items = skipped.items() if isinstance(skipped, dict) else [(str(s), "") for s in skipped]
        parts.append("<p>Not tried: " + "; ".join(html.escape(f"{k} ({v})" if v else k) for k, v in items) + "</p>")
    parts.append("<h2>Top candidates and their signatures</h2>")
    order = [c.get("effect") for c in ranking if c.get("effect") in candidates]
    order += [e for e in candidates if e not in order]
    for k, eff in enumerate(order, 1):
        c = next((x for x in ranking if x.get("effect") == eff), {})
        sig = signature_of(eff)
        name = f"diag_{k:02d}_{eff}.png"
        plot_signature(figs / name, eff, list(base), list(candidates[eff]))
        head = f"{k}. {eff}" + (f": {sig.title}" if sig else "")
        parts.append(f"<h3>{html.escape(head)}</h3>")
        if c:
            parts.append(f"<p>gap {_fmt(gap)} → <b>{_fmt(c.get('gap_after'))}</b> "
                         f"(gain {100 * float(c.get('gain', 0)):.1f} %)</p>")
        if c.get("evidence"):
            parts.append(f"<p><b>Evidence:</b> {html.escape(str(c['evidence']))}</p>")
        if sig:
            parts.append(f"<p><b>What to look for:</b> {html.escape(sig.explanation)}</p>")
        parts.append(f"<img src='figures/{name}' alt='{html.escape(eff)} signature'>")
    parts.append("</body></html>\n")
    out.mkdir(parents=True, exist_ok=True)
    path = out / DIAGNOSIS_FILE
    path.write_text("\n".join(parts))
    return path


__all__ = ["write_report", "run_lab", "plot_frame", "plot_breakdown", "plot_history", "REPORT_FILE",
           "write_diagnosis_report", "PLOTS", "signature_of", "plot_signature", "pixel_samples",
           "binned_statistics", "depth_level_steps", "radial_error_map", "plot_binned_signature",
           "DIAGNOSIS_FILE"]
