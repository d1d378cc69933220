"""Inputs of ``realgap synda map`` (files -> (N, C, S, S) arrays in [-1, 1]) and the samples of
``realgap synda augment`` (a few simulated views through A).

Accepted inputs, each checked against the generator's domain (C = 3 for rgb, 1 for depth) and side S
with a one-line :class:`~data_tools.errors.FormatError` naming the file:

* ``.npy``: (S, S), (N, S, S), (C, S, S) or (N, C, S, S) float values in [-1, 1] (the normalised
  patches of :mod:`recog.patches` for depth);
* ``.png`` of S x S pixels: 8-bit grey (depth) or RGB (rgb), 0..255 -> -1..1;
* a 16-bit depth scan ``.png`` with ``bbox`` (depth generators): the patch is cut as the recogniser
  cuts it (:func:`recog.patches.extract_patch`) with the patch configuration the generator was
  trained with; the camera is ``camera`` or the camera.json beside the scan or in its parent folder.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError

__all__ = ["read_inputs", "augment_samples"]

RANGE_TOLERANCE = 1e-3
"""How far past [-1, 1] an input value may lie (float rounding of a normalised patch) before it is an error;
what lies within it is clipped."""


def _check(a: np.ndarray, c: int, s: int, path) -> np.ndarray:
    if a.ndim == 2:
        a = a[None, None]
    elif a.ndim == 3:
        a = a[None] if (a.shape[0] == c and c == 3) else a[:, None]
    if a.ndim != 4 or a.shape[1] != c or a.shape[2] != s or a.shape[3] != s:
        raise FormatError(path, f"the generator takes {c}-channel {s} x {s} images, got an array of shape "
                                f"{tuple(a.shape)}")
    if not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)):
        raise FormatError(path, f"expected finite float values in [-1, 1], got {a.dtype}")
    lo, hi = float(a.min()), float(a.max())
    if lo < -1.0 - RANGE_TOLERANCE or hi > 1.0 + RANGE_TOLERANCE:
        raise FormatError(path, f"values must lie in [-1, 1] (normalised patches), got {lo:.4g} to {hi:.4g}")
    return np.clip(a.astype(np.float32), -1.0, 1.0)


def _scan_patch(png: Path, bbox: str, camera, patch: dict) -> np.ndarray:
    from data_tools.camera import read_camera_json
    from data_tools.sequence import read_depth_png
    from recog.patches import PatchConfig, check_bbox, extract_patch
    if camera is None:
        for cand in (png.parent / "camera.json", png.parent.parent / "camera.json"):
            if cand.is_file():
                camera = cand
                break
        else:
            raise FormatError(png, "no camera.json next to the scan or in its parent folder (give --camera)")
    cam = read_camera_json(camera)
    try:
        box = [float(v) for v in str(bbox).split(",")]
        assert len(box) == 4
    except (ValueError, AssertionError):
        raise ConfigError(f"--bbox: expected x0,y0,x1,y1 in pixels, got {bbox!r}") from None
    depth = read_depth_png(png, cam.depth_scale)
    box = check_bbox(box, depth.shape[1], depth.shape[0], "--bbox", min_inside=0.5)
    return extract_patch(depth, cam.intrinsics, box, PatchConfig(**patch)).image


def read_inputs(paths: list[str], cfg, info: dict, bbox: str | None = None, camera=None,
                gen_path=None) -> tuple[list[str], np.ndarray]:
    """(names, (N, C, S, S) float32) of the input files for a generator of config ``cfg`` (a
    :class:`SyndaConfig`) and ``info`` (its patch configuration, for scans)."""
    import cv2
    c, s = cfg.in_channels, cfg.generator.size
    names, arrays = [], []
    for p in paths:
        path = Path(p)
        if not path.is_file():
            raise FormatError(path, "input not found")
        if path.suffix.lower() == ".npy":
            try:
                a = np.load(path, allow_pickle=False)
            except Exception as e:
                raise FormatError(path, f"unreadable .npy ({type(e).__name__})") from None
            a = _check(np.asarray(a), c, s, path)
        elif path.suffix.lower() == ".png":
            im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if im is None:
                raise FormatError(path, "unreadable PNG")
            if im.dtype == np.uint16 and im.ndim == 2 and c == 1 and bbox is not None:
                if not info.get("patch"):
                    raise FormatError(gen_path, "the generator does not say how its patches are cut (no patch info)")
                a = _scan_patch(path, bbox, camera, info["patch"])[None, None]
            elif im.dtype == np.uint16:
                raise FormatError(path, "a 16-bit image: a depth scan needs --bbox (and a depth generator)")
            else:
                if im.ndim == 3:
                    im = cv2.cvtColor(im[..., :3], cv2.COLOR_BGR2RGB).transpose(2, 0, 1)
                    if c == 1:
                        raise FormatError(path, f"a colour image, the depth generator takes 1-channel {s} x {s} "
                                                f"images")
                a = _check(im.astype(np.float32) / 127.5 - 1.0, c, s, path)
        else:
            raise FormatError(path, "unknown input type (give .npy or .png)")
        for i in range(len(a)):
            names.append(path.stem if len(a) == 1 else f"{path.stem}_{i:03d}")
        arrays.append(a)
    return names, np.concatenate(arrays)


def augment_samples(objects_spec, domain: str, n: int, seed: int, sensor: str = "kinect_v1",
                    scale: float | None = None, preset: str = "cpu") -> dict[str, np.ndarray]:
    """``n`` samples of A on views of the objects simulated as ``synda train`` makes them (``preset``'s
    augmentation): {'clean', 'measured' (depth), 'input', target modalities} as numpy arrays (N, C, S, S)."""
    import torch

    from recog.data import DataConfig, view_grid
    from recog.objects import load_objects
    from recog.patches import PatchConfig
    from recog.synda.augment import Augmenter
    from recog.synda.config import synda_preset
    from recog.synda.data import SyndaData, simulate_views
    from recog.synda.train import make_batch
    cfg = synda_preset(preset, domain)
    objs = load_objects(objects_spec, scale)
    views = DataConfig(variant="physical", preset=sensor, seed=seed, subdivisions=1).validate()
    patch = PatchConfig(size=cfg.generator.size, crop_m=round(1.2 * max(o.diameter_m for o in objs), 4))
    rng = np.random.default_rng(seed)
    n_grid = len(view_grid(views)[0])
    parts = []
    for i, obj in enumerate(objs):
        k = n // len(objs) + (1 if i < n % len(objs) else 0)
        if k:
            v = sorted(rng.choice(n_grid, size=min(k * 2, n_grid), replace=False).tolist())
            d = simulate_views(obj, views, patch, 0, v, domain == "depth")
            ok = np.nonzero(d["ok"])[0][:k]
            parts.append((d["clean"][ok], d["mask"][ok], d["noisy"][ok]))
    data = SyndaData(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                     np.concatenate([p[2] for p in parts]), np.zeros(sum(len(p[0]) for p in parts), np.int32))
    if len(data) == 0:
        raise ConfigError("no view shows the objects (are they too small for the sensor?)")
    aug = Augmenter(cfg.augment, domain, cfg.generator.size)
    idx = np.arange(len(data))
    draw = rng.integers(0, max(data.noisy.shape[1], 1), len(data))
    with torch.no_grad():
        x, tgt = make_batch(data, idx, draw, aug, aug.draw(len(data), seed))
    out = {"clean": data.clean.astype(np.float32)[:, None], "input": x.numpy()}
    if domain == "depth":
        out["measured"] = data.noisy[idx, draw].astype(np.float32)[:, None]
    out.update({k: v.numpy() for k, v in tgt.items()})
    return out
