"""Figures of ``realgap synda map`` and ``synda augment``: each modality with its colour scale and
label, and contact sheets (a row per input or sample).

Colour conventions: normalised depth (the recogniser's patch units, -1 near .. +1 far/no
measurement) in viridis with a colour bar; normals (camera frame) as RGB = (n + 1) / 2; the mask
as foreground probability 0..1 in grey; lightness and colour inputs as images ((x + 1) / 2).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["map_figures", "augment_sheet", "draw_modality"]

LABELS = {"input": "input", "measured": "measured (sensor)", "clean": "clean view", "normals": "normals (RGB = n+1 / 2)",
          "depth": "depth (normalised)", "mask": "mask (p foreground)", "lightness": "lightness",
          "output": "output (final)", "target": "target"}


def draw_modality(ax, name: str, a: np.ndarray, fig=None, colorbar: bool = True, title: str | None = None) -> None:
    """Show one (C, S, S) map on ``ax`` with its convention (module docstring) and a colour bar for scalar maps."""
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title or LABELS.get(name, name), fontsize=8)
    if a.shape[0] == 3:
        ax.imshow(np.clip((a.transpose(1, 2, 0) + 1) / 2, 0, 1))
        return
    if name == "mask":
        im = ax.imshow(a[0], cmap="gray", vmin=0, vmax=1)
    elif name == "lightness":
        im = ax.imshow(a[0], cmap="gray", vmin=-1, vmax=1)
    else:
        im = ax.imshow(a[0], cmap="viridis", vmin=-1, vmax=1)
    if colorbar and fig is not None:
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04).ax.tick_params(labelsize=6)


def _save(fig, path: Path) -> None:
    import io

    from data_tools.results import atomic_write_bytes
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    atomic_write_bytes(path, buf.getvalue())


def _sheet(path: Path, rows: list[tuple[str, dict]], columns: list[str], suptitle: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    n, m = len(rows), len(columns)
    fig, axes = plt.subplots(n, m, figsize=(1.9 * m + 0.5, 1.75 * n + 0.6), squeeze=False)
    for i, (label, maps) in enumerate(rows):
        for j, col in enumerate(columns):
            ax = axes[i, j]
            if col in maps:
                draw_modality(ax, col, maps[col], fig, colorbar=(j == m - 1 or maps[col].shape[0] == 1),
                              title=LABELS.get(col, col) if i == 0 else "")
            else:
                ax.axis("off")
        axes[i, 0].set_ylabel(label, fontsize=7)
    fig.suptitle(suptitle, fontsize=9)
    _save(fig, path)
    plt.close(fig)


def map_figures(out: Path, names: list[str], x: np.ndarray, maps: dict[str, np.ndarray], meta: dict) -> int:
    """One folder per input (``input.png`` and a PNG per modality, each with its colour bar) and
    ``contact_sheet.png``; returns the number of single-modality PNGs."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    order = ["input"] + [k for k in ("normals", "depth", "mask", "lightness") if k in maps] + ["output"]
    count = 0
    rows = []
    for i, name in enumerate(names):
        row = {"input": x[i], **{k: v[i] for k, v in maps.items()}}
        rows.append((name, row))
        folder = out / name
        folder.mkdir(exist_ok=True)
        for k in order:
            fig, ax = plt.subplots(figsize=(3.2, 2.8))
            title = f"{LABELS.get(k, k)}" + (f" = {meta['target']}" if k == "output" else "")
            draw_modality(ax, k if k != "output" else meta["target"], row[k], fig, title=title)
            _save(fig, folder / f"{k}.png")
            plt.close(fig)
            count += 1
    _sheet(out / "contact_sheet.png", rows, order,
           f"SynDA {meta['domain']} generator: every intermediate modality, final output = {meta['target']}")
    return count


def augment_sheet(out: Path, samples: dict[str, np.ndarray], domain: str) -> None:
    """``contact_sheet.png`` (a row per sample) and ``samples.npz`` of :func:`recog.synda.inputs.augment_samples`."""
    import io

    from data_tools.results import atomic_write_bytes
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cols = ["clean"] + (["measured"] if domain == "depth" else []) + ["input"] + \
        [k for k in ("depth", "normals", "mask", "lightness") if k in samples]
    n = len(samples["input"])
    rows = [(f"sample {i}", {k: samples[k][i] for k in cols}) for i in range(n)]
    _sheet(out / "contact_sheet.png", rows, cols, f"SynDA augmentation A, {domain} domain: input and its targets")
    buf = io.BytesIO()
    np.savez_compressed(buf, **samples)
    atomic_write_bytes(out / "samples.npz", buf.getvalue())
