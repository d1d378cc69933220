"""Block matching for structured light (image vs stored reference) and active stereo.

Geometry (rectified rig, projector or second camera on the camera's x axis at ``side * b``):

* structured light: the IR image I and the reference image R (the pattern on a plane at
  depth z0, captured once) satisfy I(u) = R(u - d) (projector at +x) with
  ``d = f b (1/z - 1/z0)``, so ``1/z = 1/z0 + d / (f b)``;
* active stereo: left image L (depth camera) and right image R (second camera at +x):
  L(u) = R(u - d) with ``d = f b / z``.

A projector (or second camera) at -x mirrors the images, which is handled by flipping both
images horizontally. The matcher is OpenCV's StereoBM (SAD on pre-filtered images) or
StereoSGBM (semi-global); both return 1/16 px disparities, which are then quantised to the
device's sub-pixel step. The reference image is rendered wider than the camera image
(``pad_before``/``pad_after`` columns) so every camera pixel can be matched over the whole
search range; the real device has the projector's wider field of view for that.

:func:`sad_block_match` is a plain numpy/OpenCV-box-filter SAD (or census) matcher with
parabolic sub-pixel refinement and a uniqueness check: slower, fully transparent, used to
cross-check the OpenCV path in the tests.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import ConfigError
from synth.jit import kernel


@dataclass(frozen=True)
class MatchSetup:
    """Disparity search range and image padding of one device (all in pixels)."""

    fb: float
    """Focal length x baseline, pixel-metres."""
    z0: float | None
    """Reference plane depth, metres (None: stereo, absolute disparity)."""
    side: float
    """+1 projector/second camera at +x, -1 at -x."""
    min_disp: int
    """Smallest disparity searched (OpenCV minDisparity)."""
    num_disp: int
    """Number of disparities searched (multiple of 16)."""
    pad_before: int
    """Extra reference columns left of the image (in unflipped image coordinates)."""
    pad_after: int
    """Extra reference columns right of the image."""
    block: int
    """Matching window side."""
    step: float
    """Device sub-pixel step."""

    @classmethod
    def for_preset(cls, preset, block_size: int | None = None, min_depth_m: float | None = None,
                   max_depth_m: float | None = None) -> "MatchSetup":
        """Search range bounded by the depth range (a one-pixel margin each side)."""
        block = int(block_size or preset.block_size)
        if block < 3 or block % 2 == 0:
            raise ConfigError(f"matching block size must be odd and >= 3, got {block}")
        zmin = float(min_depth_m or preset.min_depth_m)
        zmax = float(max_depth_m or preset.max_depth_m)
        fb = preset.fb
        if fb <= 0:
            raise ConfigError(f"sensor {preset.name!r}: block matching needs a positive baseline")
        stereo = preset.type == "active_stereo"
        z0 = None if stereo else float(preset.reference_depth_m)
        inv0 = 0.0 if stereo else 1.0 / z0
        lo = fb * (1.0 / zmax - inv0)
        hi = fb * (1.0 / zmin - inv0)
        min_disp = int(math.floor(lo)) - 1
        num_disp = int(math.ceil((hi + 1 - min_disp) / 16.0)) * 16
        if stereo:
            pad_l = pad_r = 0
        else:
            half = block // 2 + 1
            pad_l = max(min_disp + num_disp - 1, 0) + half
            pad_r = max(-min_disp, 0) + half
        if preset.projector_side < 0:
            pad_l, pad_r = pad_r, pad_l
        return cls(fb, z0, preset.projector_side, min_disp, num_disp, pad_l, pad_r, block,
                   float(preset.subpixel_step_px))

    def reference_intrinsics(self, intr: Intrinsics) -> Intrinsics:
        """Intrinsics of the padded reference image."""
        return Intrinsics(intr.width + self.pad_before + self.pad_after, intr.height, intr.fx, intr.fy,
                          intr.cx + self.pad_before, intr.cy)

    def disparity_to_depth(self, d: np.ndarray) -> np.ndarray:
        """Depth (metres, 0 where invalid/NaN or behind the camera) from disparity (pixels)."""
        d = np.asarray(d, dtype=np.float32)
        inv0 = 0.0 if self.z0 is None else 1.0 / self.z0
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(inv0) + d / np.float32(self.fb)
            z = np.where(np.isfinite(inv) & (inv > 0), 1.0 / inv, 0.0)
        return z.astype(np.float32)

    def depth_to_disparity(self, z: np.ndarray) -> np.ndarray:
        """Disparity (pixels) of depth z (metres); NaN where z <= 0."""
        z = np.asarray(z, dtype=np.float32)
        inv0 = 0.0 if self.z0 is None else 1.0 / self.z0
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.float32(self.fb) * (1.0 / z - np.float32(inv0))
        return np.where(z > 0, d, np.nan).astype(np.float32)

    def quantize(self, d: np.ndarray) -> np.ndarray:
        """Round disparities to the device's sub-pixel step (NaN stays NaN)."""
        s = np.float32(self.step)
        return (np.round(np.asarray(d, np.float32) / s) * s).astype(np.float32)


@dataclass(frozen=True)
class MatcherParams:
    """Settings of the OpenCV matcher (see the block_matching effect for their meaning)."""

    prefilter: str = "normalized"
    prefilter_size: int = 9
    prefilter_cap: int = 31
    uniqueness_ratio: int = 10
    texture_threshold: int = 0
    speckle_window_px: int = 200
    speckle_range_16: int = 2
    lr_max_diff_px: int = -1
    sgbm_p1: int = 0
    sgbm_p2: int = 0
    subpixel_iterations: int = 2
    """Gauss-Newton sub-pixel refinement steps after the matcher (0 = keep its 1/16 px)."""
    max_refine_px: float = 1.0
    """Where the refinement moves the disparity farther than this, the matcher's value is kept."""


def _make_matcher(setup: MatchSetup, method: str, p: MatcherParams):
    import cv2
    if method == "bm":
        m = cv2.StereoBM_create(setup.num_disp, setup.block)
        m.setMinDisparity(setup.min_disp)
        m.setPreFilterType(cv2.StereoBM_PREFILTER_NORMALIZED_RESPONSE if p.prefilter == "normalized"
                           else cv2.StereoBM_PREFILTER_XSOBEL)
        m.setPreFilterSize(max(5, p.prefilter_size | 1))
        m.setPreFilterCap(int(np.clip(p.prefilter_cap, 1, 63)))
        m.setUniquenessRatio(int(p.uniqueness_ratio))
        m.setTextureThreshold(int(p.texture_threshold))
        m.setSpeckleWindowSize(int(p.speckle_window_px))
        m.setSpeckleRange(int(p.speckle_range_16))
        m.setDisp12MaxDiff(int(p.lr_max_diff_px))
        return m
    if method == "sgbm":
        bs = setup.block
        return cv2.StereoSGBM_create(
            minDisparity=setup.min_disp, numDisparities=setup.num_disp, blockSize=bs,
            P1=p.sgbm_p1 or 8 * bs * bs, P2=p.sgbm_p2 or 32 * bs * bs,
            disp12MaxDiff=int(p.lr_max_diff_px), preFilterCap=int(np.clip(p.prefilter_cap, 1, 63)),
            uniquenessRatio=int(p.uniqueness_ratio), speckleWindowSize=int(p.speckle_window_px),
            speckleRange=int(p.speckle_range_16), mode=cv2.StereoSGBM_MODE_SGBM_3WAY)
    raise ConfigError(f"unknown matcher {method!r} (use 'bm' or 'sgbm')")


_MATCHER_CACHE: dict = {}


def match(left8: np.ndarray, right8: np.ndarray, setup: MatchSetup, method: str = "bm",
          params: MatcherParams = MatcherParams()) -> np.ndarray:
    """Disparity (H, W) float32 pixels of ``left8`` (H, W) uint8 against ``right8``.

    Structured light: ``right8`` is the padded reference (H, W + pad_before + pad_after);
    stereo: the second camera's image (H, W). Returns the raw matcher output (1/16 px steps,
    not yet quantised to the device step) with NaN where the matcher found no valid match.
    """
    H, W = left8.shape
    Wt = W + setup.pad_before + setup.pad_after
    if right8.shape != (H, Wt):
        raise ConfigError(f"matching: right/reference image is {right8.shape}, expected {(H, Wt)}")
    if setup.pad_before or setup.pad_after:
        L = np.zeros((H, Wt), np.uint8)
        L[:, setup.pad_before:setup.pad_before + W] = left8
    else:
        L = left8
    R = right8
    if setup.side < 0:
        L = np.ascontiguousarray(L[:, ::-1])
        R = _flipped(right8)
    key = (setup, method, params)
    m = _MATCHER_CACHE.get(key)
    if m is None:
        m = _MATCHER_CACHE[key] = _make_matcher(setup, method, params)
    D16 = m.compute(np.ascontiguousarray(L), np.ascontiguousarray(R))
    d = D16.astype(np.float32) * np.float32(1.0 / 16.0)
    d[D16 < setup.min_disp * 16] = np.nan
    # the image's columns in the (possibly mirrored) working frame
    c0 = setup.pad_before if setup.side > 0 else Wt - setup.pad_before - W
    c1 = c0 + W
    if params.subpixel_iterations > 0:
        # refine only the image's columns plus the margin its windows reach: each of the
        # iterations and the normalisation widen the dependency by half a window, so the
        # result there is the same as refining the whole padded width. The same holds for
        # rows, so row bands (with that margin) refine concurrently on several cores.
        M = (int(params.subpixel_iterations) + 1) * (setup.block // 2) + 2
        a, b = max(c0 - M, 0), min(c1 + M, Wt)
        d = _refine_in_bands(L[:, a:b], R, d[:, a:b], setup.block, params, a, M)[:, c0 - a:c1 - a]
    else:
        d = d[:, c0:c1]
    if setup.side < 0:
        d = d[:, ::-1]
    return np.ascontiguousarray(d)


def _refine_in_bands(left, right, d, block, params, col_offset, margin):
    """:func:`refine_subpixel` of (H, w) ``left``/``d`` (a column band of ``right`` starting at
    ``col_offset``), split into row bands refined concurrently (one per usable CPU, threads:
    OpenCV and numpy release the GIL), each with ``margin`` extra rows that are refined and
    dropped, so the result equals refining the whole image."""
    from synth.jit import n_threads
    H = left.shape[0]
    n = min(n_threads(), max(1, H // (4 * margin)))
    if n <= 1:
        return refine_subpixel(left, right, d, block, params.subpixel_iterations, params.max_refine_px, col_offset)
    from synth.jit import thread_pool
    Rn, Rx = _normalized_with_gradient(right, block)
    edges = [round(i * H / n) for i in range(n + 1)]
    out = np.empty(d.shape, np.float32)

    def band(i: int) -> None:
        r0, r1 = edges[i], edges[i + 1]
        a, b = max(r0 - margin, 0), min(r1 + margin, H)
        sub = _refine(_normalized(left[a:b], block), Rn[a:b], Rx[a:b], d[a:b], block,
                      params.subpixel_iterations, params.max_refine_px, col_offset)
        out[r0:r1] = sub[r0 - a:r1 - a]

    list(thread_pool(n).map(band, range(n)))
    return out


_FLIP_CACHE: list = []


def _flipped(img: np.ndarray) -> np.ndarray:
    """Horizontally mirrored contiguous copy, cached for the last image (the stored reference
    is the same array every frame, so its normalisation cache keeps working)."""
    for src, out in _FLIP_CACHE:
        if src is img:
            return out
    out = np.ascontiguousarray(img[:, ::-1])
    _FLIP_CACHE[:] = [(img, out)]
    return out


_REF_CACHE: list = []


def _normalized(img: np.ndarray, block: int) -> np.ndarray:
    """Zero-mean, unit-contrast image over ``block`` windows (gain/offset invariant), float32."""
    import cv2
    img = np.ascontiguousarray(img)
    f = np.empty(img.shape, np.float32)
    f2 = np.empty(img.shape, np.float32)
    _square(img, f, f2)
    k = (block, block)
    m = cv2.blur(f, k)
    v = cv2.blur(f2, k)
    out = np.empty(img.shape, np.float32)
    _contrast(f, m, v, out)
    return out


@kernel
def _square(img, f, f2):
    """``img`` as float32 into ``f``, and its square into ``f2`` (the inputs of the box means)."""
    H, W = img.shape
    for y in range(H):
        for x in range(W):
            a = np.float32(img[y, x])
            f[y, x] = a
            f2[y, x] = a * a


@kernel
def _contrast(f, m, v2, out):
    """(f - mean) / sqrt(max(mean of f^2 - mean^2, 1)), float32 (the window normalisation)."""
    H, W = f.shape
    for y in range(H):
        for x in range(W):
            var = v2[y, x] - m[y, x] * m[y, x]
            out[y, x] = (f[y, x] - m[y, x]) / np.sqrt(max(var, np.float32(1.0)))


def _normalized_with_gradient(img: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """(normalised image, its central-difference x gradient), cached for the last two images
    (the stored reference is the same array every frame)."""
    import cv2
    for ref, b, out in _REF_CACHE:
        if ref is img and b == block:
            return out
    n = _normalized(img, block)
    gx = cv2.Sobel(n, cv2.CV_32F, 1, 0, ksize=1) * np.float32(0.5)
    _REF_CACHE[:] = [(img, block, (n, gx))] + _REF_CACHE[:1]
    return n, gx


def refine_subpixel(left: np.ndarray, right: np.ndarray, d: np.ndarray, block: int, iterations: int = 2,
                    max_shift_px: float = 1.0, col_offset: int = 0) -> np.ndarray:
    """Gauss-Newton sub-pixel refinement of a disparity map (L(u) = R(u - d)).

    Both images are normalised per window (zero mean, unit contrast: the captured pattern is
    dimmer than the reference). For each window W(p), with g = dR/du sampled at q - d(q) and
    the residual e(q) = L(q) - R(q - d(q)), one step is
    ``d(p) <- sum_W g^2 d / sum_W g^2 - sum_W e g / sum_W g^2``: the window's weighted mean
    disparity plus the least-squares shift, i.e. a window-constant (plus linear) disparity is
    recovered without the integer pixel-locking of cost-curve interpolation. Everything is
    box filters and remaps (no per-pixel Python; element-wise steps in place, float32). Where
    the refinement moves more than ``max_shift_px`` from the matcher's value (a window
    straddling a depth edge, where a single shift cannot explain it) the matcher's own value
    is kept. ``left``/``d`` may be a column band of the full images starting at column
    ``col_offset`` of ``right`` (results within (iterations + 1) half-windows of the band's
    ends are affected by its borders).
    """
    Rn, Rx = _normalized_with_gradient(right, block)
    return _refine(_normalized(left, block), Rn, Rx, d, block, iterations, max_shift_px, col_offset)


def _refine(Ln, Rn, Rx, d, block, iterations, max_shift_px, col_offset):
    """:func:`refine_subpixel` given the normalised left image ``Ln`` and the normalised
    right image ``Rn`` with its x gradient ``Rx`` (the same rows as ``Ln``). The element-wise
    steps between the remaps and box filters are compiled kernels (one pass each instead of
    ten numpy passes; float32 throughout, the same operations in the same order)."""
    import cv2
    H, W = Ln.shape
    u = np.arange(col_offset, col_offset + W, dtype=np.float32)
    v = _row_map(H, W)
    d = np.ascontiguousarray(d, np.float32)
    d0 = np.empty((H, W), np.float32)
    okf = np.empty((H, W), np.float32)
    mx = np.empty((H, W), np.float32)
    _refine_start(d, u, d0, okf, mx)
    cur = d0
    k = (block, block)
    terms = np.empty((H, W, 3), np.float32)   # g^2, g^2 d, e g: one 3-channel box filter
    for it in range(int(iterations)):          # (per channel the same sums as three filters)
        Rw = cv2.remap(Rn, mx, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        g = cv2.remap(Rx, mx, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        _refine_terms(g, okf, cur, Ln, Rw, terms)
        sums = cv2.boxFilter(terms, -1, k, normalize=False)
        cur = np.empty((H, W), np.float32)
        _refine_step(sums, u, cur, mx)
    _refine_finish(cur, d0, d, np.float32(max_shift_px))
    return cur


@kernel
def _refine_start(d, u, d0, okf, mx):
    """Set-up of :func:`_refine`: the matcher's disparity with 0 where it has none (``d0``),
    the valid mask as 0/1 (``okf``) and the first sampling column u - d0 (``mx``)."""
    H, W = d.shape
    for y in range(H):
        for x in range(W):
            ok = np.isfinite(d[y, x])
            d0[y, x] = d[y, x] if ok else np.float32(0.0)
            okf[y, x] = np.float32(1.0) if ok else np.float32(0.0)
            mx[y, x] = u[x] - d0[y, x]


@kernel
def _refine_terms(g, okf, cur, Ln, Rw, terms):
    """The window sums' terms of one Gauss-Newton step into ``terms`` (H, W, 3): g^2 (valid
    pixels), g^2 d and e g with the residual e = L - R(u - d) (float32, the products in the
    order of the numpy original)."""
    H, W = g.shape
    for y in range(H):
        for x in range(W):
            a = g[y, x] * g[y, x] * okf[y, x]
            terms[y, x, 0] = a
            terms[y, x, 1] = a * cur[y, x]
            terms[y, x, 2] = (Ln[y, x] - Rw[y, x]) * g[y, x] * okf[y, x]


@kernel
def _refine_step(sums, u, cur, mx):
    """The new disparity (sum g^2 d - sum e g) / max(sum g^2, 1e-6) from the window sums
    ``sums`` (H, W, 3) of :func:`_refine_terms`, and the next sampling column u - d."""
    H, W = cur.shape
    for y in range(H):
        for x in range(W):
            c = (sums[y, x, 1] - sums[y, x, 2]) / max(sums[y, x, 0], np.float32(1e-6))
            cur[y, x] = c
            mx[y, x] = u[x] - c


@kernel
def _refine_finish(cur, d0, d, max_shift):
    """Keep the matcher's value where the refinement diverged (not finite, or moved more than
    ``max_shift`` pixels); NaN where the matcher had no match."""
    H, W = cur.shape
    for y in range(H):
        for x in range(W):
            c = cur[y, x]
            if not np.isfinite(d[y, x]):
                cur[y, x] = np.nan
            elif not np.isfinite(c) or abs(c - d0[y, x]) > max_shift:
                cur[y, x] = d0[y, x]


_ROW_MAPS: dict = {}


def _row_map(H: int, W: int) -> np.ndarray:
    """(H, W) float32 row coordinate of every pixel (cached, read-only)."""
    m = _ROW_MAPS.get((H, W))
    if m is None:
        m = np.ascontiguousarray(np.broadcast_to(np.arange(H, dtype=np.float32)[:, None], (H, W)))
        m.setflags(write=False)
        if len(_ROW_MAPS) >= 64:  # a few shapes (row bands, presets), not one per call
            _ROW_MAPS.clear()
        _ROW_MAPS[(H, W)] = m
    return m


def sad_block_match(left: np.ndarray, right: np.ndarray, min_disp: int, num_disp: int, block: int,
                    uniqueness_ratio: float = 10.0, census: bool = False) -> np.ndarray:
    """Reference SAD (or census/Hamming) block matcher, L(u) = R(u - d).

    For every disparity the absolute differences (or census Hamming distances) are summed over
    the block with a box filter; the winner gets parabolic sub-pixel refinement and must beat
    every disparity outside +-1 by ``uniqueness_ratio`` percent. Returns (H, W) float32
    disparities, NaN where invalid (borders, non-unique). O(num_disp) full-image passes.
    """
    import cv2
    L = np.asarray(left, np.float32)
    R = np.asarray(right, np.float32)
    H, W = L.shape
    if census:
        L, R = _census(L), _census(R)
    costs = np.full((num_disp, H, W), np.inf, np.float32)
    for k in range(num_disp):
        d = min_disp + k
        diff = np.full((H, W), np.nan, np.float32)
        if d >= 0:
            if d < W:
                a, b = L[:, d:], R[:, :W - d]
                diff[:, d:] = _hamming(a, b) if census else np.abs(a - b)
        else:
            a, b = L[:, :W + d], R[:, -d:]
            diff[:, :W + d] = _hamming(a, b) if census else np.abs(a - b)
        bad = np.isnan(diff)
        c = cv2.boxFilter(np.where(bad, 0, diff).astype(np.float32), -1, (block, block), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
        nb = cv2.boxFilter(bad.astype(np.float32), -1, (block, block), normalize=False,
                           borderType=cv2.BORDER_CONSTANT)
        c[nb > 0] = np.inf
        costs[k] = c
    best = np.argmin(costs, axis=0)
    cmin = np.take_along_axis(costs, best[None], 0)[0]
    ii = np.arange(num_disp)[:, None, None]
    far = np.abs(ii - best[None]) > 1
    second = np.where(far, costs, np.inf).min(axis=0)
    cm = np.take_along_axis(costs, np.clip(best - 1, 0, num_disp - 1)[None], 0)[0]
    cp = np.take_along_axis(costs, np.clip(best + 1, 0, num_disp - 1)[None], 0)[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        den = cm + cp - 2 * cmin
        off = np.where((den > 0) & np.isfinite(den), (cm - cp) / (2 * den), 0.0)
    disp = (min_disp + best + np.clip(off, -0.5, 0.5)).astype(np.float32)
    ok = np.isfinite(cmin) & (best > 0) & (best < num_disp - 1)
    ok &= second * 100 > cmin * (100 + uniqueness_ratio)
    disp[~ok] = np.nan
    return disp


def _census(img: np.ndarray, radius: int = 2) -> np.ndarray:
    """5x5 census transform as (H, W, 24) bool bit planes (border pixels compare with edge copies)."""
    H, W = img.shape
    p = np.pad(img, radius, mode="edge")
    bits = []
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy == 0 and dx == 0:
                continue
            bits.append(p[radius + dy:radius + dy + H, radius + dx:radius + dx + W] < img)
    return np.stack(bits, axis=-1)


def _hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.count_nonzero(a != b, axis=-1).astype(np.float32)
