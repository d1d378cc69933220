"""The diagnosis page of the sensor lab (``diagnosis.html``): the top candidate effects with their
signature figures.

A signature is what an effect does to the measured images that nothing else does; each
figure shows the measurement, the current model (``base``) and the model with the candidate
added (fitted parameters) side by side, so the page answers "is this effect what is missing?"
visually. Each effect declares its signature (``Effect.SIGNATURE``: title, explanation, figure
kind and panels) in its own file; the figure kinds are drawn here (:data:`PLOTS`); effects
without one get the generic distance breakdown.

matplotlib is imported inside the functions (see :mod:`synth.lab.report`).
"""
from __future__ import annotations

import html
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from synth.lab.features import FrameObservation
from synth.lab.report import REPORT_CSS, figure, fmt_number, html_table, save_figure

__all__ = ["write_diagnosis_report", "PLOTS", "signature_of", "plot_signature", "pixel_samples", "binned_statistics",
           "depth_level_steps", "radial_error_map", "plot_binned_signature", "plot_shadow_signature",
           "plot_quantization_signature", "plot_distortion_signature", "DIAGNOSIS_FILE"]

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
    fig = figure(5.2 * len(panels), 4.2)
    axs = np.atleast_1d(fig.subplots(1, len(panels)))
    by_feature: dict[str, tuple[list, list]] = {}  # the pixel features of one feature computed once
    for ax, (feature, stat) in zip(axs, panels):
        axes, stats = by_feature.setdefault(feature, ([], []))
        axes.append(ax)
        stats.append(stat)
    for feature, (axes, stats) in by_feature.items():
        _binned_axes(fig, axes, base, candidate, feature, tuple(stats))
    return save_figure(fig, path)


@_plot_kind("binned")
def _binned_signature(path, base, candidate, sig) -> Path:
    return plot_binned_signature(path, base, candidate, sig.panels)


@_plot_kind("shadow_sides")
def plot_shadow_signature(path, base, candidate, sig=None) -> Path:
    """Invalid fraction vs ``edge_shadow`` (shadow side +, lit side -) and one frame's holes
    next to its depth edges, coloured by side."""
    from synth.lab.features import FeatureConfig, FrameFeatures, make_feature
    fig = figure(14, 4.6)
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
    return save_figure(fig, path)


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
    fig = figure(12, 4.6)
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
    return save_figure(fig, path)


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
    fig = figure(15, 4.4)
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
    return save_figure(fig, path)


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
             f"<style>{REPORT_CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    if measured_name:
        parts.append(f"<p>measured sequence: <code>{html.escape(measured_name)}</code></p>")
    model = diagnosis.get("model")
    parts.append(f"<p class='gap'>gap of the current model = <b>{fmt_number(gap)}</b></p>")
    if model is not None:
        parts.append(f"<p>current model: {html.escape(', '.join(model) or 'ideal (no effect)')}</p>")
    parts.append("<p>Each candidate effect was added to the current model, its parameters fitted to the "
                 "measured sequence, and the gap measured again; gain = (gap − gap after) / gap. Numbers "
                 "in <a href='diagnosis.json'>diagnosis.json</a>.</p>")
    rows = []
    for r, c in enumerate(ranking, 1):
        allp = c.get("params") or {}
        eff = str(c.get("effect"))
        own = [f"{k.split('.', 1)[-1]}={fmt_number(v)}" for k, v in allp.items() if k.startswith(eff + ".") or "." not in k]
        rest = [f"{k}={fmt_number(v)}" for k, v in allp.items() if "." in k and not k.startswith(eff + ".")]
        params = ", ".join(own) + (f" (with the model refitted: {', '.join(rest)})" if rest else "")
        rows.append((r, c.get("effect"), fmt_number(c.get("gap_after")), f"{100 * float(c.get('gain', 0)):.1f} %",
                     params, c.get("evidence", "")))
    parts.append("<h2>Ranking</h2>" + html_table(rows, ("rank", "effect", "gap after", "gain", "fitted parameters",
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
            parts.append(f"<p>gap {fmt_number(gap)} → <b>{fmt_number(c.get('gap_after'))}</b> "
                         f"(gain {100 * float(c.get('gain', 0)):.1f} %)</p>")
        if c.get("evidence"):
            parts.append(f"<p><b>Evidence:</b> {html.escape(str(c['evidence']))}</p>")
        if sig:
            parts.append(f"<p><b>What to look for:</b> {html.escape(sig.explanation)}</p>")
        parts.append(f"<img src='figures/{name}' alt='{html.escape(eff)} signature'>")
    parts.append("</body></html>\n")
    out.mkdir(parents=True, exist_ok=True)
    from data_tools.results import atomic_write_text
    return atomic_write_text(out / DIAGNOSIS_FILE, "\n".join(parts))

