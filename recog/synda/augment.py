"""The online augmentation A of SynDA (thesis section 5.3.2): clean synthetic modalities ->
a random real-like input, drawn anew every iteration.

kornia style, the random draw separate from the deterministic apply: :meth:`Augmenter.draw`
(batch, seed or torch.Generator) -> ``params`` (a dict of tensors with the batch first), and
:meth:`Augmenter.apply` (sample, params) is pure: the same params give the same images, and every
sample replays alone (``apply(select(sample, i), select_params(params, i))`` is row i of the
batch's result).

``rgb`` domain (the thesis' setting), from unit normals (B, 3, S, S) and a mask (B, 1, S, S):

1. shading: Blinn-Phong with a random light and coefficients (Algorithm 5.1, :mod:`.shading`);
2. texturing: procedural Perlin / Voronoi / white-noise hue and saturation maps, indexed by the
   normals' (x, y), replace the shading's hue and saturation (its lightness is kept; kornia's
   HLS conversion); ``none`` keeps the shading's colour;
3. background: procedural noise (hue, lightness, saturation from three noise channels) or a
   random crop of an image (kornia ``crop_and_resize``), its lightness shifted so that its mean
   equals the object's (the thesis' homogenisation);
4. occluders: random polygons (Algorithm 5.2, :mod:`.polygons`) painted with colour noise;
5. blur: none / Gaussian / box / median (kornia filters).

It returns the input in [-1, 1] and the *foreground lightness* ground truth (the shading's HLS
lightness on the object, before texturing, 2 L - 1; -1 on the background).

``depth`` domain, from normalised depth (B, 1, S, S) in [-1, 1] and the mask: procedural (or
image-intensity) background depth, occluders as bumpy surfaces nearer than the object, then the
*sensor hook* (:data:`SensorHook`: the project's sensor effects with randomised parameters,
supplied by the caller; without one this step is skipped), then blur.

Deviations from the thesis, on purpose: one colour-noise field per sample fills all of its
occluders; occluder centres are uniform over the image (the thesis' Bernoulli choice between
two ranges per axis is not reproduced); image backgrounds come from a folder (default: the
sample images scikit-image ships) instead of COCO, each image resized to a square bank of
:data:`BANK_SIDE` pixels (aspect not kept), crops of 25-100 % of its side.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import kornia
import numpy as np
import torch

from data_tools.errors import ConfigError, FormatError
from recog.synda.config import BACKGROUNDS, BLURS, TEXTURES, AugmentConfig
from recog.synda.images import IMAGE_SUFFIXES, image_folder
from recog.synda.noise import NOISE_KINDS, draw_noise, eval_noise, pixel_coords
from recog.synda.polygons import polygon_masks, random_polygons
from recog.synda.shading import blinn_phong

__all__ = ["SensorHook", "Augmenter", "load_image_bank", "select_params", "select", "BLUR_FILTERS", "BANK_SIDE",
           "IMAGE_SUFFIXES"]

SensorHook = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""(B, 1, S, S) composited depth in [-1, 1], (B,) int64 per-sample seeds -> (B, 1, S, S) depth
with sensor effects. It must be deterministic for given seeds (A's replayability rests on it)."""

BANK_SIDE = 128
"""Side (pixels) every background image is resized to."""


def load_image_bank(source: str, side: int = BANK_SIDE) -> torch.Tensor:
    """(N, 3, side, side) float RGB in [0, 1] from the images of folder ``source`` (``skimage``:
    the sample images scikit-image ships); grey images are repeated to 3 channels, alpha dropped."""
    import skimage.io
    folder = image_folder(source, "background image")
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    bank = []
    for f in files:
        try:
            im = np.asarray(skimage.io.imread(f))
        except Exception as e:
            raise FormatError(f, f"cannot read the background image ({type(e).__name__})") from None
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, -1)
        if im.ndim != 3 or im.shape[-1] < 3:
            continue
        x = torch.from_numpy(im[..., :3].astype(np.float32) / (255.0 if im.dtype == np.uint8 else 1.0))
        x = x.permute(2, 0, 1)[None].clamp(0, 1)
        bank.append(kornia.geometry.transform.resize(x, (side, side), antialias=True))
    if not bank:
        raise FormatError(folder, f"no background images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    return torch.cat(bank).clamp(0, 1)


def select_params(params: dict[str, torch.Tensor], idx) -> dict[str, torch.Tensor]:
    """The params of the samples ``idx`` (an index, a slice or an index tensor)."""
    if isinstance(idx, int):
        idx = [idx]
    return {k: v[idx] for k, v in params.items()}


def _uniform(gen: torch.Generator, b: int, r, *shape) -> torch.Tensor:
    return float(r[0]) + (float(r[1]) - float(r[0])) * torch.rand(b, *shape, generator=gen)


def _choice(gen: torch.Generator, b: int, allowed, known) -> torch.Tensor:
    ids = torch.tensor([known.index(k) for k in allowed])
    return ids[torch.randint(len(ids), (b,), generator=gen)]


def _prefixed(prefix: str, d: dict) -> dict:
    return {f"{prefix}.{k}": v for k, v in d.items()}


def _unprefixed(prefix: str, params: dict) -> dict:
    n = len(prefix) + 1
    return {k[n:]: v for k, v in params.items() if k.startswith(prefix + ".")}


class Augmenter:
    """A for one domain and image side (see the module docstring). ``images``: a (N, 3, R, R)
    background bank in [0, 1] (default: loaded from ``cfg.background_images`` when ``image``
    backgrounds are enabled)."""

    def __init__(self, cfg: AugmentConfig, domain: str = "rgb", size: int = 64, sensor_hook: SensorHook | None = None,
                 images: torch.Tensor | None = None):
        self.cfg = cfg.validate()
        if domain not in ("rgb", "depth"):
            raise ConfigError(f"synda domain {domain!r}: choose rgb or depth")
        self.domain, self.size, self.sensor_hook = domain, int(size), sensor_hook
        if images is None and "image" in cfg.backgrounds:
            images = load_image_bank(cfg.background_images)
        self.images = images

    # ------------------------------------------------------------------ draw
    def draw(self, batch: int, seed: int | torch.Generator) -> dict[str, torch.Tensor]:
        """All random parameters of ``batch`` samples (CPU tensors, batch first)."""
        gen = seed if isinstance(seed, torch.Generator) else torch.Generator().manual_seed(int(seed))
        c, b, s = self.cfg, int(batch), self.size
        p: dict[str, torch.Tensor] = {}
        theta = torch.deg2rad(_uniform(gen, b, c.light_angle_deg))
        phi = _uniform(gen, b, (0.0, 2 * math.pi))
        p["light"] = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), -theta.cos()], 1)
        p["ambient"] = _uniform(gen, b, c.ambient, 3)
        p["diffuse"] = _uniform(gen, b, c.diffuse, 3)
        p["specular"] = _uniform(gen, b, c.specular, 3)
        p["hardness"] = _uniform(gen, b, c.hardness)
        tex = _choice(gen, b, c.textures, TEXTURES)
        p["tex.on"] = tex != TEXTURES.index("none")
        p["tex.scale"] = _uniform(gen, b, c.texture_scale)
        p.update(_prefixed("tex", draw_noise(torch.where(p["tex.on"], tex, torch.zeros_like(tex)), 2, gen)))
        bg = _choice(gen, b, c.backgrounds, BACKGROUNDS)
        p["bg.image_on"] = bg == BACKGROUNDS.index("image")
        p.update(_prefixed("bg", draw_noise(torch.where(p["bg.image_on"], torch.zeros_like(bg), bg), 3, gen)))
        n_img = 1 if self.images is None else len(self.images)
        p["bg.image"] = torch.randint(n_img, (b,), generator=gen)
        side = _uniform(gen, b, (0.25, 1.0)) * (BANK_SIDE - 1)
        x0 = torch.rand(b, generator=gen) * (BANK_SIDE - 1 - side)
        y0 = torch.rand(b, generator=gen) * (BANK_SIDE - 1 - side)
        p["bg.box"] = torch.stack([torch.stack([x0, y0], 1), torch.stack([x0 + side, y0], 1),
                                   torch.stack([x0 + side, y0 + side], 1), torch.stack([x0, y0 + side], 1)], 1)
        o_max, v_max = int(c.occluders[1]), int(c.vertices[1])
        p["occ.count"] = torch.randint(int(c.occluders[0]), o_max + 1, (b,), generator=gen)
        n_poly = b * max(o_max, 1)
        n = torch.randint(int(c.vertices[0]), v_max + 1, (n_poly,), generator=gen)
        centre = torch.rand(n_poly, 2, generator=gen) * s
        r_mu = _uniform(gen, n_poly, c.occluder_radius) * s
        verts, _, _ = random_polygons(n, centre, r_mu, _uniform(gen, n_poly, c.irregularity),
                                      _uniform(gen, n_poly, c.spikeyness), gen, v_max)
        p["occ.verts"] = verts.view(b, max(o_max, 1), v_max, 2)
        p["occ.offset"] = _uniform(gen, b, c.depth_occluder_offset)
        p.update(_prefixed("occ", draw_noise(torch.randint(len(NOISE_KINDS), (b,), generator=gen), 3, gen)))
        p["blur.kind"] = _choice(gen, b, c.blurs, BLURS)
        ks = torch.arange(int(c.blur_kernel[0]), int(c.blur_kernel[1]) + 1, 2)
        p["blur.kernel"] = ks[torch.randint(len(ks), (b,), generator=gen)]
        p["blur.sigma"] = _uniform(gen, b, c.blur_sigma)
        p["sensor.seed"] = torch.randint(0, 2 ** 62, (b,), generator=gen)
        p["bg.keep"] = torch.rand(b, generator=gen) < float(c.depth_keep_background)
        return p

    # ------------------------------------------------------------------ apply
    def apply(self, sample: dict[str, torch.Tensor], params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Pure: ``sample`` (normals (B, 3, S, S) unit, camera frame; mask (B, 1, S, S) in {0, 1};
        depth (B, 1, S, S) in [-1, 1] for the depth domain, optionally ``measured`` (B, 1, S, S): the same
        views measured by a sensor) -> ``input`` (B, C, S, S) in [-1, 1] and, for rgb, ``lightness``
        (B, 1, S, S) in [-1, 1]; for depth, ``target`` (B, 1, S, S): the clean depth with the same
        background as the input (its own where ``bg.keep``, else the procedural one) and no occluders."""
        self._check(sample)
        mask = sample["mask"].to(torch.float32)
        dev = mask.device
        p = {k: v.to(dev) for k, v in params.items()}
        if self.domain == "rgb":
            x, light = self._rgb(sample["normals"].to(torch.float32), mask, p)
            out = {"input": x * 2 - 1, "lightness": torch.where(mask > 0.5, light * 2 - 1, -torch.ones_like(light))}
        else:
            measured = sample.get("measured")
            x, target = self._depth(sample["depth"].to(torch.float32), mask, p,
                                    None if measured is None else measured.to(torch.float32))
            out = {"input": x, "target": target}
        return out

    def __call__(self, sample: dict[str, torch.Tensor], seed: int | torch.Generator):
        """(apply(sample, params), params) with fresh params."""
        params = self.draw(sample["mask"].shape[0], seed)
        return self.apply(sample, params), params

    def _check(self, sample: dict[str, torch.Tensor]) -> None:
        need = {"mask": 1, "normals": 3} if self.domain == "rgb" else {"mask": 1, "depth": 1}
        for k, ch in need.items():
            x = sample.get(k)
            if x is None or x.dim() != 4 or x.shape[1] != ch or tuple(x.shape[2:]) != (self.size, self.size):
                got = None if x is None else tuple(x.shape)
                raise FormatError(None, f"synda augmentation needs {k} of shape (B, {ch}, {self.size}, "
                                        f"{self.size}), got {got}")

    def _background(self, p: dict, b: int, dev) -> torch.Tensor:
        """(B, 3, S, S) RGB background in [0, 1]."""
        s = self.size
        hls = self._field(_unprefixed("bg", p), b, dev)
        bg = kornia.color.hls_to_rgb(torch.stack([hls[:, 0] * (2 * math.pi), hls[:, 1], hls[:, 2]], 1))
        idx = torch.nonzero(p["bg.image_on"]).flatten()
        if len(idx) and self.images is not None:
            crops = kornia.geometry.transform.crop_and_resize(self.images.to(dev)[p["bg.image"][idx]],
                                                               p["bg.box"][idx].to(torch.float32), (s, s))
            bg = bg.clone()
            bg[idx] = crops.clamp(0, 1)
        return bg

    def _occluders(self, p: dict, b: int, dev) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 1, S, S) occluder mask and (B, 3, S, S) fill noise in [0, 1]."""
        s = self.size
        masks = polygon_masks(p["occ.verts"].to(torch.float32), s, s)             # (B, O, S, S)
        used = torch.arange(masks.shape[1], device=dev)[None, :] < p["occ.count"][:, None]
        occ = (masks * used[..., None, None]).amax(1, keepdim=True)
        fill = self._field({k: v for k, v in _unprefixed("occ", p).items() if k not in ("verts", "count", "offset")},
                           b, dev)
        return occ, fill

    def _field(self, noise: dict, b: int, dev) -> torch.Tensor:
        """A noise field over the image, evaluated at half resolution and upsampled bilinearly
        (backgrounds and occluder fills: 4 x cheaper, and their detail is blurred anyway)."""
        h = max(self.size // 2, 1)
        f = eval_noise(noise, pixel_coords(b, h, h, dev))
        return torch.nn.functional.interpolate(f, size=(self.size, self.size), mode="bilinear", align_corners=False)

    def _rgb(self, normals: torch.Tensor, mask: torch.Tensor, p: dict) -> tuple[torch.Tensor, torch.Tensor]:
        b = normals.shape[0]
        shaded = blinn_phong(normals, p["light"], p["ambient"], p["diffuse"], p["specular"], p["hardness"],
                             self.cfg.focal_px)
        hls = kornia.color.rgb_to_hls(shaded)
        lightness = hls[:, 1:2]
        # texturing: hue/saturation indexed by the normals' (x, y)
        tex_p = {k: v for k, v in _unprefixed("tex", p).items() if k not in ("on", "scale")}
        coords = 0.5 + 0.5 * p["tex.scale"][:, None, None, None] * normals[:, :2].permute(0, 2, 3, 1)
        lo, hi = self.cfg.texture_values
        tex = lo + (hi - lo) * eval_noise(tex_p, coords)
        on = p["tex.on"][:, None, None, None]
        hls = torch.cat([torch.where(on, tex[:, :1] * (2 * math.pi), hls[:, :1]), lightness,
                         torch.where(on, tex[:, 1:2], hls[:, 2:3])], 1)
        obj = kornia.color.hls_to_rgb(hls).clamp(0, 1)
        bg = self._background(p, b, normals.device)
        if self.cfg.homogenise_background:
            bg_hls = kornia.color.rgb_to_hls(bg)
            n_fg = mask.sum((1, 2, 3))
            mean_fg = (lightness * mask).sum((1, 2, 3)) / n_fg.clamp_min(1)
            shift = torch.where(n_fg > 0, mean_fg - bg_hls[:, 1].mean((1, 2)), torch.zeros_like(mean_fg))
            bg_l = (bg_hls[:, 1:2] + shift[:, None, None, None]).clamp(0, 1)
            bg = kornia.color.hls_to_rgb(torch.cat([bg_hls[:, :1], bg_l, bg_hls[:, 2:]], 1)).clamp(0, 1)
        img = mask * obj + (1 - mask) * bg
        occ, fill = self._occluders(p, b, normals.device)
        fill = kornia.color.hls_to_rgb(torch.stack([fill[:, 0] * (2 * math.pi), fill[:, 1], fill[:, 2]], 1))
        img = occ * fill.clamp(0, 1) + (1 - occ) * img
        return self._blur(img, p).clamp(0, 1), lightness

    def _depth(self, depth: torch.Tensor, mask: torch.Tensor, p: dict,
               measured: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        b = depth.shape[0]
        lo, hi = self.cfg.depth_background
        bg = lo + (hi - lo) * kornia.color.rgb_to_grayscale(self._background(p, b, depth.device))
        keep = p.get("bg.keep", torch.zeros(b, dtype=torch.bool, device=depth.device))[:, None, None, None]
        target = torch.where(keep, depth, mask * depth + (1 - mask) * bg)
        src = depth if measured is None else measured
        d = torch.where(keep, src, mask * src + (1 - mask) * bg)
        near = torch.where(mask > 0.5, depth, torch.full_like(depth, 2.0)).amin((1, 2, 3))
        near = torch.where(near > 1.5, torch.zeros_like(near), near)
        occ, fill = self._occluders(p, b, depth.device)
        occ_depth = (near - p["occ.offset"])[:, None, None, None] + 0.1 * (fill[:, :1] - 0.5)
        d = (occ * occ_depth + (1 - occ) * d).clamp(-1, 1)
        if self.sensor_hook is not None:
            d = self.sensor_hook(d, p["sensor.seed"])
        return self._blur(d, p).clamp(-1, 1), target

    def _blur(self, x: torch.Tensor, p: dict) -> torch.Tensor:
        out = x.clone()
        for name, blur in BLUR_FILTERS.items():
            kind = BLURS.index(name)
            for k in torch.unique(p["blur.kernel"][p["blur.kind"] == kind]).tolist():
                idx = torch.nonzero((p["blur.kind"] == kind) & (p["blur.kernel"] == k)).flatten()
                out[idx] = blur(x[idx], int(k), p["blur.sigma"][idx].to(x.dtype))
        return out


BLUR_FILTERS: dict[str, Callable[[torch.Tensor, int, torch.Tensor], torch.Tensor]] = {
    "gaussian": lambda x, k, sigma: kornia.filters.gaussian_blur2d(x, (k, k), torch.stack([sigma, sigma], 1)),
    "box": lambda x, k, sigma: kornia.filters.box_blur(x, (k, k)),
    "median": lambda x, k, sigma: kornia.filters.median_blur(x, (k, k)),
}
"""Blur kind -> (images (B, C, S, S), odd kernel side, (B,) Gaussian sigmas) -> blurred images
(kornia's filters; ``none`` is the absence of an entry)."""


def select(sample: dict[str, torch.Tensor], idx) -> dict[str, torch.Tensor]:
    """The samples ``idx`` of a batch of modalities."""
    if isinstance(idx, int):
        idx = [idx]
    return {k: v[idx] for k, v in sample.items()}

