"""Direct model: the matching window spreads foreground depth over the background."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_DROPOUT, Effect, Signature, param, register_effect


@dataclass
class EdgeFatteningParams:
    radius_px: int = param(0, "px")
    """How far foreground depth spreads, pixels; 0 = half the preset's matching window."""
    min_jump_rel: float = param(0.03, "1")
    """A neighbour counts as foreground when it is nearer by more than this fraction of depth."""
    window: str = param("square", "", choices=("square", "disk"))
    """Shape of the neighbourhood the foreground spreads over: ``square`` ((2r+1)^2, a block
    matcher's window: Kinect v1, StereoBM) or ``disk`` (Euclidean radius r: matchers with
    circular or weighted windows, and filtering that spreads isotropically). ``sensor fit``
    picks the shape from the data (see ``fit_start``)."""
    min_jump_px: float = param(0.0, "px")
    """A neighbour counts as foreground only when its disparity f b / z exceeds the pixel's by more
    than this, pixels (0 = no disparity test): a matcher locks onto a nearer surface when the
    disparity jump is one it can see - a disparity threshold is a depth threshold that grows with
    depth (rel ~ jump z / f b). Both tests apply; ``min_jump_rel`` 0 leaves this one alone."""
    gate: str = param("edges", "", choices=("edges", "none"))
    """Where fattening may happen: ``edges`` only within the window of a discontinuity of the ideal
    view (a neighbour off the pixel's tangent plane by ``min_jump_rel``: steep but continuous
    surfaces are left alone), ``none`` wherever the window holds a nearer surface by the thresholds
    (a matcher or a post-filter, e.g. a disparity max filter, that does not tell a depth edge from a
    steep slope). ``sensor fit`` picks it from the data (see ``fit_start``)."""


def window_kernel(radius: int, shape: str) -> np.ndarray:
    """uint8 (2r+1)^2 structuring element: all ones (``square``) or the pixels with
    dx^2 + dy^2 <= r^2 (``disk``)."""
    r = int(radius)
    if shape == "disk":
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
        return ((xx * xx + yy * yy) <= r * r).astype(np.uint8)
    return np.ones((2 * r + 1, 2 * r + 1), np.uint8)


def gate_rel(min_jump_rel: float, min_jump_px: float, depth: np.ndarray, fb: float):
    """The relative threshold of the ``edges`` gate's tangent-plane test: ``min_jump_rel`` when it is
    set, else the disparity threshold as a relative one per pixel, ``min_jump_px`` z / (f b) (a
    disparity jump dd is a depth jump dz = dd z^2 / (f b)), (H, W); 0 when neither is set. With a
    disparity threshold alone the gate used to test at 0 and took every pixel of a curved or tilted
    surface for an edge, so a steep floor was fattened too and the fit shrank the radius to undo it
    (blind sensor seeds 5, 9: radius 1 and 2 for 2 and 4)."""
    if min_jump_rel > 0 or not (min_jump_px > 0 and fb > 0):
        return float(min_jump_rel)
    return (np.float32(min_jump_px / fb) * depth).astype(np.float32)


def depth_discontinuities(view, ray_dirs_cam: np.ndarray, rel) -> np.ndarray:
    """(H, W) bool: pixels next to a depth discontinuity of the ideal view.

    For each 4-neighbour q of pixel p, the depth predicted by p's tangent plane is
    z_p (n . r_p) / (n . r_q) (r = (x/z, y/z, 1) of each pixel's ray, n = p's normal); q is
    across an edge when its depth differs from that by more than ``rel`` z_p (or one of them is
    not a surface). ``rel``: a number or (H, W) per pixel p (:func:`gate_rel`). Exact for planes,
    so grazing walls are not edges."""
    from synth.sensor.effects.pattern_projection import normalized_coords
    xn, yn = normalized_coords(ray_dirs_cam)
    z = view.depth
    hit = view.hit
    n = view.normals_cam
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    dot_p = nx * xn + ny * yn + nz
    out = np.zeros(z.shape, bool)
    for dy, dx in ((0, 1), (1, 0)):
        H, W = z.shape
        a = (slice(0, H - dy), slice(0, W - dx))      # p
        b = (slice(dy, H), slice(dx, W))              # q = p + (dy, dx)
        for (sp, sq) in ((a, b), (b, a)):
            dot_q = nx[sp] * xn[sq] + ny[sp] * yn[sq] + nz[sp]
            with np.errstate(divide="ignore", invalid="ignore"):
                pred = z[sp] * dot_p[sp] / dot_q
            rp = rel[sp] if isinstance(rel, np.ndarray) else rel
            bad = ~(np.abs(z[sq] - pred) <= rp * z[sp]) | (hit[sp] != hit[sq])
            bad &= hit[sp] | hit[sq]
            out[sp] |= bad
            out[sq] |= bad
    return out


def _threshold_in(jump: np.ndarray, fattened: np.ndarray, lo: float, hi: float,
                  min_pixels: int) -> float | None:
    """The smallest jump (bins of 0.05 decades from ``lo`` to ``hi``) from which at least half the
    pixels of every bin of ``min_pixels`` or more are ``fattened``; None when the first bin already
    is (a threshold no larger than ``lo``) or no bin is."""
    edges = 10.0 ** np.arange(np.log10(lo), np.log10(hi) + 0.05, 0.05)
    b = np.digitize(jump, edges) - 1
    shares = [(edges[k], float(fattened[b == k].mean())) for k in range(len(edges) - 1)
              if np.count_nonzero(b == k) >= min_pixels]
    if not shares or shares[0][1] >= 0.5:
        return None
    for j, (e, _) in enumerate(shares):
        if all(sh >= 0.5 for _, sh in shares[j:]):
            return float(e)
    return None


def _split(jump: np.ndarray, fattened: np.ndarray, min_pixels: int, max_error: float = 0.1) -> float | None:
    """The decision stump (:func:`_stump`) when it is a clean split: at least ``min_pixels`` pixels
    below it and at most ``max_error`` of all pixels on the wrong side (interleaved jumps, which no
    threshold of this form separates, give none). For scenes
    with few weak edges, whose 0.05-decade bins below the threshold each hold fewer than
    ``min_pixels`` (:func:`_threshold_in` then sees the first populated bin fattened and gives
    nothing: the mystery generator's seed 31 at 160 px, 50 unfattened ring-1 pixels at 0.2-0.8 px
    of disparity jump and 210 fattened ones at 1-3 px)."""
    t = _stump(jump, fattened)
    if t is None:
        return None
    below = jump <= t
    if np.count_nonzero(below) < min_pixels or float(np.mean(fattened == below)) > max_error:
        return None
    return t


def _stump(jump: np.ndarray, fattened: np.ndarray) -> float | None:
    """The threshold t that best splits ``fattened`` pixels (jump > t) from the others: fewest
    misclassified, in the middle (geometric mean) of the jumps bounding the best split; None
    without both kinds of pixels."""
    o = np.argsort(jump)
    j, f = np.asarray(jump, np.float64)[o], np.asarray(fattened, bool)[o]
    if f.all() or not f.any():
        return None
    # split i: the first i pixels (smallest jumps) below the threshold
    err = np.concatenate([[0], np.cumsum(f)]) + np.concatenate([np.cumsum((~f)[::-1])[::-1], [0]])
    i = np.flatnonzero(err == err.min())
    lo, hi = j[max(i[0] - 1, 0)], j[min(i[-1], j.size - 1)]
    return float(np.sqrt(max(lo, 1e-6) * max(hi, 1e-6)))


def _jump_threshold(samples, rel: float, min_pixels: int = 30, fb: float = 0.0) -> tuple[str, float] | None:
    """The smallest depth jump across which the measured depth of the pixels right behind an edge
    (ring 1: a nearer surface among the 8 neighbours, nearer by more than ``rel``) carries the
    foreground's depth in at least half of them, in every 0.05-decade bin of jumps from there up
    (bins of ``min_pixels`` pixels or more), measured two ways: as the relative jump 1 - z_near / z
    (``("rel", q)``) and, when ``fb`` > 0 (f b, px m), as the disparity jump f b / z_near - f b / z
    in pixels (``("px", d)``). The form whose threshold classifies the ring-1 pixels (fattened iff
    the jump exceeds it) with fewer errors wins, the disparity one on a tie: a matcher sees
    disparities, so an edge it can see at 1 m (a large disparity jump) may be one it cannot at 3 m
    for the same relative jump, and a scene whose edges all lie in a few depth bands separates
    both ways. None when ring 1 is
    fattened from the smallest jump on in both forms, or never. ``samples``: (measured depth, ideal
    depth with 1e6 where nothing is hit, usable mask) per frame, (H, W) each."""
    import cv2
    qs, ds, fs = [], [], []
    for m, z, ok in samples:
        z = np.asarray(z, np.float32)
        near = cv2.erode(z, np.ones((3, 3), np.uint8))
        q = 1.0 - near / z
        sel = ok & (m > 0) & (q > rel) & (q < 0.95)
        if sel.any():
            qs.append(q[sel])
            ds.append(fb / near[sel] - fb / z[sel] if fb > 0 else np.zeros(int(sel.sum())))
            fs.append(np.abs(m[sel] - near[sel]) < np.abs(m[sel] - z[sel]))
    if not qs:
        return None
    q, d, f = np.concatenate(qs), np.concatenate(ds), np.concatenate(fs)
    found = []
    t = _threshold_in(q, f, rel, 0.95, min_pixels)
    if t is None:
        t = _split(q, f, min_pixels)
    if t is not None:
        found.append(("rel", t, int(np.count_nonzero(f != (q > t)))))
    if fb > 0 and d.size:
        t = _threshold_in(d, f, max(float(d.min()), 0.05), max(float(d.max()), 0.1), min_pixels)
        if t is None:
            t = _split(d, f, min_pixels)
        if t is not None:
            found.append(("px", t, int(np.count_nonzero(f != (d > t)))))
    if not found:
        return None
    if len(found) == 2 and found[1][2] <= found[0][2]:
        return found[1][:2]
    return found[0][:2]


def _fattens(near: np.ndarray, z: np.ndarray, fb: float, px: float, rel_step: float) -> np.ndarray:
    """(H, W) bool: a surface at ``near`` (m) in the window fattens a pixel of ideal depth ``z`` (m): its
    disparity f b / near leads by more than ``px`` (pixels) when ``px`` > 0, else it is nearer by more
    than ``rel_step`` of z."""
    if px > 0:
        with np.errstate(divide="ignore"):
            return fb / near - fb / z > px
    return near < z * (1 - rel_step)


def _measured_band(samples, min_pixels: int = 100) -> tuple[float, float] | None:
    """(low, high) metres: the 0.5th and 99.5th percentiles of the measured valid depths over
    ``samples`` (``measured_samples``' tuples, every frame) - where the sensor measures (a fattened pixel
    carries its nearer surface's depth, so a hole whose nearer surface lies in this band was not
    fattened); None with fewer than ``min_pixels``."""
    valid = np.concatenate([m[m > 0] for _, m, _, _ in samples]) if samples else np.zeros(0)
    if valid.size < min_pixels:
        return None
    lo, hi = np.percentile(valid, [0.5, 99.5])
    return float(lo), float(hi)


@register_effect
class EdgeFattening(Effect):
    """Background pixels within ``radius_px`` of a nearer surface take its depth.

    Physics/device: block matching assigns one disparity to a whole window; a window that
    straddles a depth edge is dominated by the textured, unoccluded foreground part, so the
    foreground "fattens" by about half the window (4 px for Kinect v1's 9x9), including into
    the projector-shadow band next to it. The physical pipeline produces this by itself
    (``block_matching``); this is the analytic stand-in: within ``radius_px`` of a depth
    discontinuity (adjacent pixels differing by more than ``min_jump_rel``), a grey erosion
    (minimum depth) over a (2r+1)^2 window replaces pixels whose minimum is nearer by
    ``min_jump_rel`` (holes next to the foreground that the scene surface covers are filled
    too; steep but continuous surfaces are left alone, unless ``gate`` is "none"); with
    ``min_jump_px`` the nearer surface must also lead by that much disparity.
    """

    name = "edge_fattening"
    SIGNATURE = Signature(
        "foreground bleeding over depth edges",
        "Just beyond depth edges (background side, + distances) the measured depth is too close: "
        "the median error turns negative over a few pixels.",
        panels=(("edge_distance", "bias"), ("edge_distance", "invalid_fraction")))
    IDENTITY_PARAMS = {"radius_px": 0}
    sensor_types = ("structured_light", "active_stereo")  # triangulation
    Params = EdgeFatteningParams
    FITTABLE = {"radius_px": (0, 20), "min_jump_rel": (0.0, 1.0), "min_jump_px": (0.0, 4.0)}
    START_ONLY_PARAMS = ("window", "gate")
    stage = STAGE_DROPOUT + 5

    def apply(self, state, draw) -> None:
        import cv2
        r = self.params.radius_px or state.preset.block_size // 2
        if r <= 0:
            return
        big = np.float32(1e6)
        z = np.where(state.valid, state.depth, big).astype(np.float32)
        k = window_kernel(r, self.params.window)
        near = cv2.erode(z, k)
        # compare with the pixel's own depth (its ideal depth where it is a hole): only a truly
        # nearer surface fattens, holes on flat surfaces stay holes
        own = np.where(state.valid, state.depth, state.view.depth)
        # only across real discontinuities, not along steep but continuous surfaces: a
        # neighbour is across an edge when its depth differs from the depth the pixel's own
        # tangent plane predicts for it by more than min_jump_rel
        fat = (near < big) & state.view.hit & (near < own * np.float32(1.0 - self.params.min_jump_rel))
        fb = float(getattr(state.preset, "fb", 0.0) or 0.0)
        if self.params.gate == "edges":
            rel = gate_rel(self.params.min_jump_rel, self.params.min_jump_px, state.view.depth, fb)
            jump = depth_discontinuities(state.view, state.ray_dirs_cam, rel)
            fat &= cv2.dilate(jump.astype(np.uint8), k) > 0
        if self.params.min_jump_px > 0 and fb > 0:
            with np.errstate(divide="ignore", invalid="ignore"):
                fat &= fb / near - fb / own > np.float32(self.params.min_jump_px)
        state.depth = np.where(fat, near, state.depth).astype(np.float32)
        state.valid = state.valid | fat
        state.log[self.name] = {"fattened_px": int(fat.sum()), "radius_px": r}

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict:
        """The radius and the window shape from the measured depth beside depth edges: for each
        shape and each ring k = 1..15 (pixels whose nearest nearer surface, by min_jump_rel, first
        appears in the radius-k window of that shape), the share of measured depths nearer to that
        foreground depth than to their own ideal depth (edges of at least twice min_jump_rel, >= 6 %:
        on weaker edges noise blurs the test). Per shape the radius is the largest k
        before the first ring whose share is < 0.5 (or < half the share of ring 1); the shape whose profile drops
        most sharply after its radius (share(r) - share(r + 1)) wins. Nothing (the preset's
        default) when ring 1 is not fattened.

        The jump threshold first (:func:`_jump_threshold`): a matcher fattens only across edges
        whose disparity jump it can see, so when ring-1 pixels behind weak edges are not fattened
        the smallest relative jump from which they are becomes ``min_jump_rel``'s start and the
        radius is read on edges above it (an independent generator fattening only across jumps of
        1.6 px of disparity, 20-40 % of depth at 160 px width, gave no start at all: ring 1 over
        every 6 % edge was fattened in 30 % of the pixels). When the disparity jump separates the
        fattened ring-1 pixels at least as well as the relative one (:func:`_jump_threshold`), the
        start is ``min_jump_px`` (refined against the nearest surface of the whole window,
        :meth:`_window_splits`) with ``min_jump_rel`` 0; the radius and shape are then read again at that
        threshold with the holes a fattening would have filled counted (:meth:`_read_radius`), and that
        reading is kept when its window's disparity split errs on fewer pixels. ``gate`` is "none" when pixels whose window
        holds a nearer surface but no discontinuity of the ideal view are fattened too
        (:meth:`_fattens_slopes`)."""
        from synth.sensor.effects._common import measured_samples
        rel0 = float(config.effect(cls.name).params.min_jump_rel) if cls.name in config.names() else 0.03
        rel = clear = max(2.0 * rel0, 0.06)      # clear edges only: the radius does not depend on which edges
        fb = float(config.preset.fb) if getattr(config.preset, "type", "") != "tof" else 0.0
        thr = _jump_threshold(((m, np.where(r.hit, r.depth, 1e6), ok) for _, m, r, ok in measured_samples(measured)),
                              rel, fb=fb)
        out, px = {}, 0.0
        if thr is not None and thr[0] == "rel" and thr[1] > rel:
            rel = min(thr[1], 0.9)
            out[f"{cls.name}.min_jump_rel"] = rel0 = float(np.clip(thr[1], *cls.FITTABLE["min_jump_rel"]))
        elif thr is not None and thr[0] == "px":        # a disparity threshold: no relative one
            px = float(np.clip(thr[1], *cls.FITTABLE["min_jump_px"]))
            rel0 = 0.0
            out[f"{cls.name}.min_jump_rel"], out[f"{cls.name}.min_jump_px"] = 0.0, px

        # ring k must have nothing within k - 1 px that would have fattened the pixel by itself: at the
        # threshold read from the data, else any 1 % step (with a fixed 1 % a 160 px floor, 1-2 % a row,
        # left no pixel past ring 1 and the radius read 1: mystery seeds 28 and 37, 4 and 3)
        weak_rel = rel0 if f"{cls.name}.min_jump_rel" in out and rel0 > 0 else 0.01
        samples = list(measured_samples(measured))
        band = _measured_band(samples)
        best = cls._read_radius(samples, fb, px, rel, weak_rel)
        if best is None:
            return {}
        out.update({f"{cls.name}.radius_px": float(best[1]), f"{cls.name}.window": best[2]})
        sp = None
        if px == 0 and fb > 0 and f"{cls.name}.min_jump_rel" in out:
            # a relative threshold read on ring 1: the disparity one instead when it splits the window's
            # pixels, holes beside measured surfaces included, with fewer errors (:meth:`_window_splits`)
            sp = cls._window_splits(samples, band, fb, best[1], best[2], clear)
            if sp is not None and sp["px"][1] < sp["rel"][1]:
                px, rel0 = float(np.clip(sp["px"][0], *cls.FITTABLE["min_jump_px"])), 0.0
                out[f"{cls.name}.min_jump_rel"], out[f"{cls.name}.min_jump_px"] = 0.0, px
            else:
                sp = None
        elif px > 0:      # the disparity threshold again, against the nearest surface of the whole window
            sp = cls._window_splits(samples, band, fb, best[1], best[2], clear)      # clear == rel here
            if sp is not None:
                px = out[f"{cls.name}.min_jump_px"] = float(np.clip(sp["px"][0], *cls.FITTABLE["min_jump_px"]))
        if sp is not None:      # (a split needs the band)
            # the radius again at that threshold, the holes counted (:meth:`_read_radius`); kept when its
            # window's disparity stump errs on fewer pixels than the first reading's
            again = cls._read_radius(samples, fb, px, rel, 0.0, band)
            if again is not None and again[1:] != best[1:]:
                sp2 = cls._window_splits(samples, band, fb, again[1], again[2], clear)
                if sp2 is not None and sp2["px"][1] < sp["px"][1]:
                    best, px = again, float(np.clip(sp2["px"][0], *cls.FITTABLE["min_jump_px"]))
                    out.update({f"{cls.name}.radius_px": float(best[1]), f"{cls.name}.window": best[2],
                                f"{cls.name}.min_jump_px": px})
        if (rel0 > 0 or px > 0) and cls._fattens_slopes(measured, best[1], best[2], rel0, px, fb,
                                                        lambda near, z: _fattens(near, z, fb, px, rel)):
            out[f"{cls.name}.gate"] = "none"
        return out

    @staticmethod
    def _read_radius(samples, fb: float, px: float, rel: float, weak_rel: float, band=None, K: int = 15):
        """(drop, radius, shape) read from the rings of :meth:`fit_start` (None when ring 1 is not
        fattened or no shape has a radius). Ring k of a shape: the usable pixels whose radius-k window
        holds a surface that fattens them (:func:`_fattens` at ``px`` / ``rel``) and whose radius-(k - 1)
        window holds none (at ``px`` / ``weak_rel``); its share: the measured depths nearer to that
        surface's depth than to their own, of >= 30 pixels. ``band`` (low, high metres, the measured
        depths, :func:`_measured_band`): the ring's holes whose nearer surface lies in it count as not
        fattened - a fattened pixel would carry that depth, which the sensor measures. Without them, a
        ring past the radius beside a background beyond the range holds only the pixels that some
        surface did fatten (the rest are holes) and reads as fattened, or as too few to tell (the mystery
        generator's seed 48, a 9 x 9 square: its ring 5 held 26 valid pixels and 415 such holes, the
        square's drop was unknown and a disk of radius 5 won). Counted only once the disparity form is
        read: with a relative threshold where the matcher follows disparities, every ring holds the holes
        behind a far background's weak disparity jumps.

        Per shape the radius is the largest k before the first ring whose share is < 0.5 (or < half
        ring 1's); the shape whose share drops most after its radius wins."""
        import cv2
        lo, hi = band if band is not None else (np.inf, -np.inf)
        shapes = ("square", "disk")
        fat = {sh: np.zeros(K + 2) for sh in shapes}
        cnt = {sh: np.zeros(K + 2) for sh in shapes}
        for _, m, r, ok in samples:
            z = np.where(r.hit, r.depth, np.float32(1e6)).astype(np.float32)
            for sh in shapes:
                prev = z
                for k in range(1, K + 2):
                    near = cv2.erode(z, window_kernel(k, sh))
                    # a clear edge first within k px, and nothing within k - 1 px that would have
                    # fattened the pixel by itself (the threshold read from the data, else 1 %)
                    ring = ok & _fattens(near, z, fb, px, rel) & ~_fattens(prev, z, fb, px, weak_rel)
                    prev = near
                    sel = ring & (m > 0)
                    if sel.any():
                        mm, zz, nn = m[sel], z[sel], near[sel]
                        fat[sh][k] += np.count_nonzero(np.abs(mm - nn) < np.abs(mm - zz))
                        cnt[sh][k] += sel.sum()
                    cnt[sh][k] += np.count_nonzero(ring & (m <= 0) & (near >= lo) & (near <= hi))
        best = None
        for sh in shapes:
            share = np.where(cnt[sh] >= 30, fat[sh] / np.maximum(cnt[sh], 1), np.nan)
            if not np.isfinite(share[1]) or share[1] < 0.5:
                return None
            r = 0
            for k in range(1, K + 1):          # the rings up to the first one that is not fattened
                if not (np.isfinite(share[k]) and share[k] >= max(0.5, 0.5 * share[1])):
                    break
                r = k
            if r == 0:
                continue
            # a ring past the radius with too few pixels tells nothing about the drop: such a shape
            # ranks below any measured drop (both unknown: the first, square, the block matcher's window;
            # a 0 there made a disk of radius 3 beat the true square of radius 2 whose ring 3 was empty)
            drop = share[r] - share[r + 1] if np.isfinite(share[r + 1]) else -1.0
            if best is None or drop > best[0]:
                best = (drop, r, sh)
        return best

    @staticmethod
    def _window_splits(samples, band, fb: float, radius: int, shape: str, rel: float) -> dict | None:
        """The disparity threshold (px) that best splits the measured pixels carrying a nearer
        surface's depth from the others (:func:`_stump`), the jump taken to the nearest surface of
        the (radius, shape) window - what the model compares (ring 1 alone underestimates it: a
        pixel beside a small jump may take the depth of a bigger one farther in the window). Pixels
        whose window holds a surface nearer by more than ``rel`` (clear edges), the measured holes
        among them too where that surface's depth lies within the measured ones (0.5-99.5th
        percentile, ``band``: :func:`_measured_band` of ``samples``, ``measured_samples``' tuples): a hole
        behind a foreground the sensor measures was not fattened.

        Returns {"px": (threshold px, errors), "rel": (threshold, errors)}: the stump of each form of
        the jump (disparity f b / near - f b / z, relative 1 - near / z) and how many of those pixels
        it misclassifies; None without a split. Which form the matcher follows shows here, not on
        ring 1 (:func:`_jump_threshold`): the valid ring-1 pixels of a scene whose edges lie in a few
        depth bands split either way, and the relative start then fattens holes that the sensor left
        (the mystery generator's seed 42, disparity threshold 1.66 px, radius 2: its valid ring-1
        pixels split without error at a relative jump of 0.30, a start that filled the holes beside a
        far background and scored worse than no fattening; over the radius-2 window with those holes,
        the disparity stump 1.658 px errs on no pixel, the relative one on 48)."""
        import cv2
        k = window_kernel(radius, shape)
        if band is None:
            return None
        lo, hi = band
        js, qs, fs = [], [], []
        for _, m, r, ok in samples:
            z = np.where(r.hit, r.depth, np.float32(1e6)).astype(np.float32)
            near = cv2.erode(z, k)
            # a hole whose nearer surface the sensor would have measured (within the measured depths)
            # was not fattened: a fattened pixel carries that depth (e.g. a background beyond the range)
            sel = ok & (near < z * (1 - rel)) & ((m > 0) | ((near >= lo) & (near <= hi)))
            if sel.any():
                js.append(fb / near[sel] - fb / z[sel])
                qs.append(1.0 - near[sel] / z[sel])
                fs.append((m[sel] > 0) & (np.abs(m[sel] - near[sel]) < np.abs(m[sel] - z[sel])))
        if not js:
            return None
        f = np.concatenate(fs)
        out = {}
        for form, jump in (("px", np.concatenate(js)), ("rel", np.concatenate(qs))):
            t = _stump(jump, f)
            if t is None:
                return None
            out[form] = (t, int(np.count_nonzero(f != (jump > t))))
        return out

    @staticmethod
    def _fattens_slopes(measured, radius: int, shape: str, rel_gate: float, px_gate: float, fb: float, nearer,
                        min_pixels: int = 30) -> bool:
        """True when the measured depth is fattened away from depth edges too: of the pixels whose
        (radius, shape) window holds a surface ``nearer`` (the start's thresholds) but no
        discontinuity of the ideal view (tangent-plane test at :func:`gate_rel` of ``rel_gate``,
        ``px_gate``, ``fb``: the model's ``edges`` gate), at least half carry the nearer depth (>= ``min_pixels`` such pixels; a steep floor
        or side wall seen by a matcher whose window's nearest depth wins)."""
        import cv2
        from synth.sensor.effects._common import measured_samples
        k = window_kernel(radius, shape)
        fat = cnt = 0
        for _, m, r, ok in measured_samples(measured):
            z = np.where(r.hit, r.depth, np.float32(1e6)).astype(np.float32)
            near = cv2.erode(z, k)
            gated = cv2.dilate(depth_discontinuities(r, r.ray_dirs_cam, gate_rel(rel_gate, px_gate, r.depth, fb))
                               .astype(np.uint8), k) > 0
            sel = ok & (m > 0) & nearer(near, z) & ~gated
            if sel.any():
                fat += int(np.count_nonzero(np.abs(m[sel] - near[sel]) < np.abs(m[sel] - z[sel])))
                cnt += int(sel.sum())
        return cnt >= min_pixels and fat >= 0.5 * cnt

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """Share of measured depths within 6 px on the background side of depth edges that are > 5 %
        nearer than the background (``ctx.foreground_spill``: each share over that side's valid depths).

        Signature present: that share exceeds the current model's by :data:`ctx.MIN_RATE_EXCESS` and is
        at least twice the share that is > 5 % farther (plain noise makes both alike)."""
        sp = ctx.foreground_spill(6.0)     # the lab's one definition (decisive.foreground_spill uses it too)
        if sp.pixels < 50:
            return ctx.weak("edge-fattening signature", gain,
                         f"only {sp.pixels} measured pixels lie within 6 px on the background side of depth edges")
        r_n, r_f, r_s = sp.near, sp.far, sp.model_near
        numbers = (f"within 6 px on the background side of depth edges {ctx.pct(r_n)} of the measured depths are more "
                   f"than 5 % nearer than the background and {ctx.pct(r_f)} more than 5 % farther (current model: "
                   f"{ctx.pct(r_s)} nearer)")
        if not (ctx.ge(r_n, r_s + ctx.MIN_RATE_EXCESS) and ctx.ge(r_n, 2 * r_f)):
            return ctx.weak("edge-fattening signature", gain, numbers)
        return (f"within 6 px on the background side of depth edges {ctx.pct(r_n)} of the measured depths are more "
                f"than 5 % nearer than the background (they carry the foreground's depth; {ctx.pct(r_f)} are farther), "
                f"against {ctx.pct(r_s)} in the current model.")
