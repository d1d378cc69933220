"""Radial + tangential lens distortion of the IR camera."""
from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_GEOMETRY, STAGE_OPTICS, Effect, Signature, param, register_effect

TANGENTIAL_LIMIT = 0.01
"""|p1|, |p2| a model may hold (ten times a decentred element's ~1e-3): the parameters' bounds and the
start's clip."""


@dataclass
class LensDistortionParams:
    coefficients: tuple[float, ...] = param((), "1")
    """OpenCV (k1, k2, p1, p2, k3); empty = the preset's ``distortion``."""
    k1: float = param(0.0, "1")
    """Radial distortion added to k1 of ``coefficients`` (else of the preset's distortion): what the
    sensor lab fits (zero for undistorted depth, then it is the lens's k1)."""
    k2: float = param(0.0, "1")
    """Radial distortion added to k2 of the same coefficients."""
    p1: float = param(0.0, "1", -TANGENTIAL_LIMIT, TANGENTIAL_LIMIT)
    """Tangential (decentring) distortion added to p1 of the same coefficients (OpenCV's order k1 k2
    p1 p2 k3, normalised image units; a lens element off the axis by a fraction of a millimetre gives
    |p| ~ 1e-3). Measured by ``sensor fit``'s start when the data show it clearly (``fit_start``) and
    kept fixed by the search (start-only: the search's budget stays on k1, k2; a radial fit without
    these terms biases k1)."""
    p2: float = param(0.0, "1", -TANGENTIAL_LIMIT, TANGENTIAL_LIMIT)
    """Tangential distortion added to p2 of the same coefficients (as ``p1``)."""
    outside: str = param("seen", "", choices=("seen", "hole"))
    """What a distorted pixel whose undistorted position lies outside the pinhole image reports:
    ``seen`` (the lens's ray sees the scene there, as a camera's own lens does) or ``hole`` (depth
    computed on a pinhole grid of the image's size and warped to the distorted one, as a device or
    driver that rectifies, registers or resamples its depth does: no source pixel, no depth - a
    barrel lens then cuts the corners). ``sensor fit`` picks it from the data (``fit_start``)."""


def undistort_pixels(pts: np.ndarray, K: np.ndarray, coeffs) -> np.ndarray:
    """Ideal (pinhole) pixel positions (N, 1, 2) of distorted pixels ``pts`` (N, 1, 2), by
    OpenCV's iterative inversion run to convergence (40 iterations, 1e-9)."""
    import cv2
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9)
    D = np.asarray(coeffs, np.float64)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        return cv2.undistortPointsIter(pts, K, D, None, K, crit)
    return cv2.undistortPoints(pts, K, D, R=None, P=K, criteria=crit)  # OpenCV 5


def distortion_maps(intr, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the distorted image, where it looks in the ideal (pinhole) image."""
    H, W = intr.height, intr.width
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([uu.ravel(), vv.ravel()], -1).reshape(-1, 1, 2)
    und = undistort_pixels(pts, intr.K, coeffs).reshape(H, W, 2).astype(np.float32)
    return np.ascontiguousarray(und[..., 0]), np.ascontiguousarray(und[..., 1])


def warped_ideal_depth(config, intr, depth: np.ndarray) -> np.ndarray:
    """The ideal depth (H, W) as the sensor's distorted pixels see it under the fitted ``k1``/``k2`` of
    ``config``'s enabled lens_distortion (nearest neighbour, as the direct model warps); ``depth``
    unchanged when there is none - for closed-form starts of later effects (:attr:`START_PRIORITY`)."""
    import cv2
    if "lens_distortion" not in config.names(enabled_only=True):
        return depth
    e = config.effect("lens_distortion")
    if not (e.params.k1 or e.params.k2 or e.params.p1 or e.params.p2):
        return depth
    mx, my = distortion_maps(intr, e.coefficients(config.preset))
    return cv2.remap(np.asarray(depth, np.float32), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0)


def _robust_abs_err(m, z, sel):
    v = sel & (m > 0)
    if v.sum() < 30:
        return float("nan")
    return float(np.median(np.abs(m[v] - z[v])))


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else float("nan")


def _parabola_min(grid, costs) -> tuple[float, float]:
    """(argmin refined by a parabola through its two neighbours, at most half a step; the grid's min) of
    ``costs`` sampled on the even ``grid``."""
    costs = np.asarray(costs, dtype=float)
    i = int(np.argmin(costs))
    x = float(grid[i])
    if 0 < i < len(grid) - 1:
        a, b, c = costs[i - 1], costs[i], costs[i + 1]
        den = a - 2 * b + c
        if den > 0:
            x += float(np.clip(0.5 * (a - c) / den, -0.5, 0.5) * (grid[1] - grid[0]))
    return x, float(costs[i])


@register_effect
class LensDistortion(Effect):
    """The IR lens bends rays: the device's image is distorted (radial k1 k2 k3, tangential p1 p2).

    Physics: real lenses map a ray of normalised direction (x, y) to the distorted position of
    the Brown-Conrady model (OpenCV's). Depth cameras report depth on their distorted pixel
    grid; the reference pattern of a structured-light device was captured through the same
    lens, so the disparity is computed between two distorted images; converting it with one
    constant f b then gives a depth bias growing with the image radius (the physical origin of
    the radial 'depth distortion' that Kinect calibration papers correct). Physical pipeline:
    the radiance image (and the reference) is warped before capture. Direct model: every pixel
    casts its own distorted ray (the pinhole direction of its undistorted position, sub-pixel)
    before any other effect, so depth, normals and materials are exact at every distorted pixel
    and the later effects act in the device's pixel grid; without a scene renderer the ideal
    depth is resampled instead (nearest neighbour, so edges are not blended - a staircase of up
    to half a pixel that a noise fit would absorb). Either way the output is in distorted pixel
    coordinates and ``SensorSimulator.camera()`` lists the coefficients.
    """

    name = "lens_distortion"
    SIGNATURE = Signature(
        "residual growing with image radius",
        "The error is small at the image centre and grows towards the corners (a ring or bowl in "
        "the block map), independent of distance.",
        plot="radial_error_map")
    IDENTITY_PARAMS = {"coefficients": (0.0, 0.0, 0.0, 0.0, 0.0)}
    Params = LensDistortionParams
    in_reference = True
    FITTABLE = {"k1": (-0.5, 0.5), "k2": (-0.5, 0.5)}
    START_ONLY_PARAMS = ("outside", "p1", "p2")

    START_PRIORITY = -1     # a pixel re-mapping: started first, the other starts see it
    START_GRID = np.linspace(-0.3, 0.3, 31)
    """k1 values of the closed-form start's scan."""

    def __init__(self, params=None, enabled=True):
        super().__init__(params, enabled)
        self._maps: dict = {}

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """k1 from depth edges: the ideal depth is warped as the sensor would see it for every k1 of
        :attr:`START_GRID` (k2 = 0; pixels undistorted by OpenCV's iteration, nearest neighbour, on a
        grid of ~320 columns) and its depth edges (adjacent depths differing by > 4 %, or by 5 x the
        measured noise of neighbour differences when that is more) are matched with
        the measured ones by the symmetric chamfer distance (mean distance to the nearest edge of the
        other image, capped at 5 px). Edges do not move under depth biases, scale errors or noise
        (which a depth residual would mix in: a 0.3 px disparity offset is a 4 % depth change at
        3 m), only under the lens. The chamfer decides whether there is a lens and where to start;
        (k1, k2) and the tangential p1, p2 are then measured by the sub-pixel depth residual of the
        warped ideal depth (:meth:`_refine_radial`: whole-pixel edges cannot place k1 finely on a small
        image, nor tell k2). When the model has edge_fattening, the fattening
        moves the measured edges into the background by its radius (5-6 px: the chamfer's cap, where
        the cost stops seeing k1 - an independent-generator pair started at k1 0.13 for 0.18), so the
        warped ideal depth is fattened too, by a square window whose radius (0-10 grid px) is scanned
        at the first k1 before k1 is scanned again. Nothing when k1 does not beat k1 = 0 by 5 % of
        the cost (no lens distortion to speak of) or when the frames show fewer than 200 edge
        pixels. ``p1``, ``p2`` only when they lower the residual by
        :attr:`TANGENTIAL_MIN_DROP` (the search keeps them fixed). ``outside`` is "hole" when the
        measured holes present in every frame match the region a barrel k1 leaves without a source
        pixel (:meth:`_border_holes`); that k1 is the start when the edges gave none."""
        import cv2

        from synth.sensor.effects._common import measured_samples
        intr = measured.intrinsics
        H, W = intr.height, intr.width
        step = max(1, int(round(W / 320)))
        vv, uu = np.mgrid[0:H:step, 0:W:step]
        shape = vv.shape
        pts = np.stack([uu.ravel(), vv.ravel()], -1).astype(np.float64).reshape(-1, 1, 2)

        tau = [0.04]

        def edges(d: np.ndarray) -> np.ndarray:
            e = np.zeros(d.shape, bool)
            for ax in (0, 1):
                a = d[:-1, :] if ax == 0 else d[:, :-1]
                b = d[1:, :] if ax == 0 else d[:, 1:]
                jump = (a > 0) & (b > 0) & (np.abs(a - b) > tau[0] * np.minimum(a, b))
                if ax == 0:
                    e[:-1, :] |= jump
                    e[1:, :] |= jump
                else:
                    e[:, :-1] |= jump
                    e[:, 1:] |= jump
            return e

        def dist_to(e: np.ndarray) -> np.ndarray:
            return cv2.distanceTransform((~e).astype(np.uint8), cv2.DIST_L2, 3)

        # the edge threshold stays above the measured noise: 5 x the robust std of the relative
        # difference of horizontal neighbours (most pairs lie on one surface), at least 4 % (a
        # small image of a noisy sensor - 2 % depth noise at 3 m and 160 px - else reads a third of
        # its pixels as edges and the chamfer cost stops seeing k1)
        rel_d = []
        for _, m, r, ok in measured_samples(measured, frames):
            a, b = m[:, :-1], m[:, 1:]
            sel = (a > 0) & (b > 0) & ok[:, :-1] & ok[:, 1:]
            rel_d.append(np.abs(a[sel] - b[sel]) / np.minimum(a[sel], b[sel]))
        rel_d = np.concatenate(rel_d) if rel_d else np.zeros(0)
        if rel_d.size > 100:
            tau[0] = max(0.04, 5.0 * 1.4826 * float(np.median(rel_d)))
        # the warped ideal's edges count only between measured-valid pixels, as the measured ones do:
        # a reference edge next to a measured hole (a box's top against a wall beyond the range) has
        # no measured counterpart, and such edges pulled the cost monotonically towards barrel
        data, data_z = [], []
        for _, m, r, ok in measured_samples(measured, frames):
            mg = np.where(ok[vv, uu], m[vv, uu], 0).astype(np.float64)
            em = edges(mg)
            zr, use = np.where(r.hit, r.depth, 0).astype(np.float64), ok[vv, uu] & (mg > 0)
            data.append((em, dist_to(em), zr, use))
            data_z.append((mg, zr, use))
        if not data or sum(int(d[0].sum()) for d in data) < 200:
            return {}
        e = config.effect("lens_distortion") if "lens_distortion" in config.names() else cls()
        base = [float(x) for x in (tuple(e.params.coefficients) or tuple(config.preset.distortion))]
        base += [0.0] * (5 - len(base))

        fat_r = 0       # radius (grid px) of the edge fattening modelled in the warped ideal depth

        def fatten(zw: np.ndarray, r: int) -> np.ndarray:
            """The foreground dilated by a (2r+1)^2 window where it is nearer by > 4 %."""
            if r <= 0:
                return zw
            far = np.where(zw > 0, zw, 1e6).astype(np.float32)
            near = cv2.erode(far, np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(np.float64)
            return np.where((zw > 0) & (near < zw * 0.96), near, zw)

        def cost(k1: float, k2: float = 0.0, r: int | None = None) -> float:
            r = fat_r if r is None else r
            c = list(base)
            c[0] += k1
            c[1] += k2
            und = undistort_pixels(pts, intr.K, c).reshape(-1, 2) if any(c) else pts.reshape(-1, 2)
            ui, vi = np.rint(und[:, 0]).astype(np.int64), np.rint(und[:, 1]).astype(np.int64)
            inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
            tot, n = 0.0, 0
            for em, dm, z, use in data:
                zw = np.zeros(ui.shape)
                zw[inside] = z[vi[inside], ui[inside]]
                ew = edges(np.where(use, fatten(zw.reshape(shape), r), 0))
                if not ew.any():
                    continue
                dw = dist_to(ew)
                tot += float(np.minimum(dw[em], 5.0).sum() + np.minimum(dm[ew], 5.0).sum())
                n += int(em.sum() + ew.sum())
            return tot / max(n, 1)

        def best_on(grid, f) -> tuple[float, float]:
            return _parabola_min(grid, [f(float(v)) for v in grid])

        border = cls._border_holes(measured, frames, intr, base)
        c0 = cost(0.0)
        k1, c1 = best_on(cls.START_GRID, cost)
        if "edge_fattening" in config.names(enabled_only=True):
            # fattened foregrounds move the measured edges r px into the background, as far as the
            # chamfer cap: model the fattening in the warped ideal depth, radius scanned at that k1
            costs_r = [cost(k1, 0.0, r) for r in range(0, 11)]
            r_best = int(np.argmin(costs_r))
            if r_best > 0 and costs_r[r_best] < 0.98 * costs_r[0]:
                fat_r = r_best
                c0 = cost(0.0)
                k1, c1 = best_on(cls.START_GRID, cost)
        if not c1 < 0.95 * c0:
            if border is None:
                return {}
            k1 = border     # the corners' holes say what the edges did not
        # (k1, k2) finely by the depth residual of the warped ideal depth (sub-pixel: bilinear within
        # a surface), which the chamfer's whole-pixel edges cannot resolve: the gap's valley in (k1, k2)
        # is narrow and diagonal, so a wrong k2 start is one the search does not leave
        k1, k2, p1, p2 = cls._refine_radial(data_z, pts, shape, intr, base, k1, tau[0],
                                            lambda zw: fatten(zw, fat_r), fat_r)
        lo, hi = cls.FITTABLE["k1"]
        out = {f"{cls.name}.k1": float(np.clip(k1, lo, hi))}
        if k2:
            out[f"{cls.name}.k2"] = float(np.clip(k2, *cls.FITTABLE["k2"]))
        if p1 or p2:
            out[f"{cls.name}.p1"] = float(np.clip(p1, -TANGENTIAL_LIMIT, TANGENTIAL_LIMIT))
            out[f"{cls.name}.p2"] = float(np.clip(p2, -TANGENTIAL_LIMIT, TANGENTIAL_LIMIT))
        if border is not None:
            out[f"{cls.name}.outside"] = "hole"
        return out

    REFINE_STEPS_K1 = 0.01 * np.arange(-4, 5)
    """k1 offsets (around the chamfer start) of the residual refinement (:meth:`_refine_radial`)."""
    REFINE_GRID_K2 = np.linspace(-0.15, 0.15, 7)
    """k2 values of the residual refinement."""
    K2_MIN_DROP = 0.01
    """Least relative drop of the residual cost (best k2 against k2 = 0, each at its best k1) that
    keeps a k2 (else 0): along the valley where k1 and k2 trade the residual is nearly flat, and a
    k2 chosen there moves k1 by as much as the bench's tolerance. 1 %: on 36 lens sequences of the three
    independent generators (160x120, 4 frames; true |k2| <= 0.036) the k2 scan lowered the cost by at
    most 0.43 %, and every k2 it kept above 0.1 % (7 of them, 0.04-0.12) moved k1 away from the truth
    (by 0.01-0.04; at k2 = 0 each k1 was within 0.006)."""
    TANGENTIAL_GRID = np.linspace(-0.004, 0.004, 9)
    """p1 (and p2) values of the start's tangential scan (:meth:`_refine_radial`)."""
    TANGENTIAL_MIN_DROP = 0.0025
    """Least relative drop of the start's residual cost that keeps the measured p1, p2 (else none):
    a lens without tangential terms keeps its model unchanged."""

    @classmethod
    def _refine_radial(cls, data_z, pts, shape, intr, base, k1: float, tau: float, fatten,
                       fat_r: int = 0) -> tuple[float, float, float, float]:
        """(k1, k2) minimising the mean clipped relative depth residual over measured-valid pixels with
        reference geometry: r = (m - z_w) / z_w less its mean (clipped at +-``tau``) in 0.25 m bins of
        z_w, then min(|r|, ``tau``), where z_w is the ideal depth warped as the sensor sees it under
        (k1, k2) - bilinear where the four source pixels lie on one surface (within 4 %), nearest
        neighbour across edges, then ``fatten``. k1 first over :attr:`START_GRID` at k2 = 0, then
        jointly: for every k2 of :attr:`REFINE_GRID_K2` the best k1 of that k1 +
        :attr:`REFINE_STEPS_K1`, the best k2 by a parabola through its neighbours (0 unless it lowers
        the cost by :attr:`K2_MIN_DROP`) and k1 again on a 4 x finer grid at that k2. Then p1, p2 over :attr:`TANGENTIAL_GRID` (p1, p2, p1 again; a
        parabola each), kept when they lower the cost by :attr:`TANGENTIAL_MIN_DROP` of it (then k1 once
        more at them), else 0. Returns (k1, k2, p1, p2); ``k1`` (the chamfer's) and zeros when the
        residual cannot tell (no comparable pixels).

        Why: the residual sees the sub-pixel shift of sloped surfaces (a lens moves pixel (x, y) by
        k r^2 (x fx, y fy)) that the chamfer's whole-pixel edges do not (its cost jumps by ~10 %
        between neighbouring k1 on a 160 px image). The noise adds about the same to every (k1, k2);
        the clip keeps edges from dominating and the per-depth mean takes out depth biases (a
        disparity offset, a scale) that a lens does not cause. Joint, not one coordinate after the
        other: k1 and k2 trade along a narrow diagonal valley of the gap, and the fit's coordinate
        search does not leave a wrong k2 start (it moves k1 to the valley at that k2 instead)."""
        H, W = intr.height, intr.width
        any_use = np.zeros(shape, bool)
        for _, _, use in data_z:
            any_use |= use
        idx = np.flatnonzero(any_use)           # only pixels some frame can compare
        pts = pts.reshape(-1, 1, 2)[idx]
        data_z = [(m.ravel()[idx], z, use.ravel()[idx]) for m, z, use in data_z]

        def warp(z: np.ndarray, und: np.ndarray) -> np.ndarray:
            x, y = und[:, 0], und[:, 1]
            x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
            inside = (x0 >= 0) & (x0 < W - 1) & (y0 >= 0) & (y0 < H - 1)
            xc, yc = np.clip(x0, 0, W - 2), np.clip(y0, 0, H - 2)
            fx, fy = x - x0, y - y0
            a, b, c, d = z[yc, xc], z[yc, xc + 1], z[yc + 1, xc], z[yc + 1, xc + 1]
            lin = a * (1 - fx) * (1 - fy) + b * fx * (1 - fy) + c * (1 - fx) * fy + d * fx * fy
            q = np.stack([a, b, c, d])
            lo, hi = q.min(0), q.max(0)
            ui = np.clip(np.rint(x).astype(np.int64), 0, W - 1)
            vi = np.clip(np.rint(y).astype(np.int64), 0, H - 1)
            out = np.where((lo > 0) & (hi < 1.04 * lo), lin, z[vi, ui])
            out[~inside] = 0.0
            return out

        full = np.zeros(int(np.prod(shape)))     # the image the fattening reads; only ``idx`` is ever written

        def cost(a1: float, a2: float, q1: float = 0.0, q2: float = 0.0) -> float:
            c = list(base)
            c[0] += a1
            c[1] += a2
            c[2] += q1
            c[3] += q2
            und = undistort_pixels(pts, intr.K, c).reshape(-1, 2) if any(c) else pts.reshape(-1, 2)
            tot, n = 0.0, 0
            for m, z, use in data_z:
                zw = warp(z, und)
                if fat_r > 0:       # the fattening needs the image's neighbourhoods
                    full[idx] = zw
                    zw = fatten(full.reshape(shape)).ravel()[idx]
                sel = use & (zw > 0)
                if sel.sum() < 30:
                    continue
                r = (m[sel] - zw[sel]) / zw[sel]
                b = np.floor(zw[sel] / 0.25).astype(np.int64)
                cnt = np.bincount(b)
                bias = np.bincount(b, np.clip(r, -tau, tau)) / np.maximum(cnt, 1)
                e = np.minimum(np.abs(r - bias[b]), tau)
                tot += float(e.sum())
                n += int(e.size)
            return tot / n if n else float("nan")

        if not idx.size or not np.isfinite(cost(k1, 0.0)):
            return k1, 0.0, 0.0, 0.0
        k1, _ = _parabola_min(cls.START_GRID, [cost(float(a1), 0.0) for a1 in cls.START_GRID])
        lo1, hi1 = cls.FITTABLE["k1"]
        grid1 = np.clip(k1 + cls.REFINE_STEPS_K1, lo1, hi1)
        best = [_parabola_min(grid1, [cost(float(a1), float(a2)) for a1 in grid1]) for a2 in cls.REFINE_GRID_K2]
        k2, _ = _parabola_min(cls.REFINE_GRID_K2, [c for _, c in best])
        j = int(np.argmin([c for _, c in best]))
        i0 = int(np.argmin(np.abs(cls.REFINE_GRID_K2)))
        if not best[j][1] < (1.0 - cls.K2_MIN_DROP) * best[i0][1]:
            k2, j = 0.0, i0         # k2 only where the data ask for it (it trades with k1 along the valley)
        fine = np.clip(best[j][0] + 0.25 * cls.REFINE_STEPS_K1, lo1, hi1)
        k1, _ = _parabola_min(fine, [cost(float(a1), k2) for a1 in fine])
        c_rad = cost(k1, k2)
        # tangential p1, p2 at that (k1, k2): p1, then p2, then p1 again (they move pixels across each
        # other's directions, and neither moves them radially); kept when the cost drops clearly
        g = cls.TANGENTIAL_GRID
        p1 = p2 = 0.0
        for which in (1, 2, 1):
            if which == 1:
                p1, _ = _parabola_min(g, [cost(k1, k2, float(q), p2) for q in g])
            else:
                p2, _ = _parabola_min(g, [cost(k1, k2, p1, float(q)) for q in g])
        c_tan = cost(k1, k2, p1, p2)
        if not c_tan < (1.0 - cls.TANGENTIAL_MIN_DROP) * c_rad:
            return k1, k2, 0.0, 0.0
        k1, _ = _parabola_min(fine, [cost(float(a1), k2, p1, p2) for a1 in fine])
        return k1, k2, p1, p2

    BORDER_MIN_IOU = 0.7
    """Least intersection-over-union of the measured holes with the region a barrel k1 leaves
    without a source pixel (:meth:`_border_holes`)."""

    @classmethod
    def _border_holes(cls, measured, frames, intr, base) -> float | None:
        """The k1 < 0 of :attr:`START_GRID` whose out-of-image region (distorted pixels whose
        undistorted position falls outside the pinhole image: what ``outside = "hole"`` cuts) best
        matches the measured holes in the band the most barrel grid value cuts, when the
        intersection over union reaches :attr:`BORDER_MIN_IOU` on at least 0.5 % of the image; None
        otherwise (a lens whose rays see the corners, or no barrel lens)."""
        from synth.sensor.effects._common import measured_samples
        H, W = intr.height, intr.width
        holes = None
        for _, m, r, ok in measured_samples(measured, frames):
            h = (m <= 0) & ok
            holes = h.astype(np.int32) if holes is None else holes + h
        if holes is None:
            return None
        n = len(list(frames)) if frames is not None else len(measured)
        always = holes >= max(1, n)         # a hole in every frame: the image frame, not the scene

        def region(k1: float) -> np.ndarray:
            c = list(base)
            c[0] += k1
            mx, my = distortion_maps(intr, tuple(c))
            return (mx < -0.5) | (mx > W - 0.5) | (my < -0.5) | (my > H - 0.5)

        grid = [float(k) for k in cls.START_GRID if k < 0]
        band = region(min(grid))
        if not band.any():
            return None
        best = None
        for k1 in grid:
            o = region(k1)
            if o.sum() < 0.005 * H * W:
                continue
            meas = always & band
            iou = float((o & meas).sum()) / max(float((o | meas).sum()), 1.0)
            if best is None or iou > best[0]:
                best = (iou, k1)
        return best[1] if best is not None and best[0] >= cls.BORDER_MIN_IOU else None

    def validate(self) -> None:
        super().validate()
        if len(self.params.coefficients) not in (0, 4, 5, 8):
            from data_tools.errors import ConfigError
            raise ConfigError(f"effect 'lens_distortion': coefficients need 4, 5 or 8 numbers, "
                              f"got {len(self.params.coefficients)}")

    def coefficients(self, preset) -> tuple:
        """The OpenCV coefficients in use: ``coefficients`` (else the preset's), padded to 5 and
        with ``k1``, ``k2``, ``p1``, ``p2`` added when those are set (the radial terms
        are fitted; the tangential ones, small and weakly constrained by depth, only measured by the
        start when the data show them clearly)."""
        base = tuple(self.params.coefficients) or tuple(preset.distortion)
        p1, p2 = float(self.params.p1), float(self.params.p2)
        if not (self.params.k1 or self.params.k2 or p1 or p2):
            return base
        c = [float(x) for x in base]
        c += [0.0] * (5 - len(c))
        c[0] += float(self.params.k1)
        c[1] += float(self.params.k2)
        c[2] += p1
        c[3] += p2
        return tuple(c)

    def stage_for(self, physical_model: bool) -> int:
        # direct model: before rolling shutter (STAGE_GEOMETRY), which re-casts state.ray_dirs_cam
        return STAGE_OPTICS + 5 if physical_model else STAGE_GEOMETRY - 1

    def distorted_rays(self, intr, coeffs) -> np.ndarray:
        """(H, W, 3) float32 unit camera-frame directions of the distorted pixels: pixel (u, v) of the
        device looks along the pinhole ray of its undistorted position (sub-pixel, OpenCV's
        inversion) - cached per (intrinsics, coefficients)."""
        key = ("rays", intr, coeffs)
        d = self._maps.get(key)
        if d is None:
            mx, my = self.maps(intr, coeffs)
            x = (mx.astype(np.float64) - intr.cx) / intr.fx
            y = (my.astype(np.float64) - intr.cy) / intr.fy
            d = np.stack([x, y, np.ones_like(x)], -1)
            d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)
            d.setflags(write=False)
            if len(self._maps) > 8:
                self._maps.clear()
            self._maps[key] = d
        return d

    def maps(self, intr, coeffs):
        key = (intr, coeffs)
        m = self._maps.get(key)
        if m is None:
            if len(self._maps) > 4:
                self._maps.clear()
            m = self._maps[key] = distortion_maps(intr, coeffs)
        return m

    def apply(self, state, draw) -> None:
        import cv2
        coeffs = self.coefficients(state.preset)
        if not any(coeffs):
            state.log[self.name] = {"active": False}
            return
        mx, my = self.maps(state.intr, coeffs)
        if state.physical and state.radiance is not None:
            warp = lambda a: cv2.remap(a, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            state.radiance = warp(state.radiance)
            if state.radiance_second is not None:
                state.radiance_second = warp(state.radiance_second)
            if state.product("ambient") is not None:
                state.publish("ambient", warp(state.product("ambient")))
        elif state.renderer is not None and not state.is_reference:
            from synth.sensor.state import cast_view
            state.ray_dirs_cam = self.distorted_rays(state.intr, coeffs)
            state.view = cast_view(state.renderer, state.ray_dirs_cam, state.view.row_c2w)
            state.depth = state.view.depth.copy()
            state.valid = state.view.hit.copy()
            if self.params.outside == "hole":
                W, H = state.intr.width, state.intr.height
                out = (mx < -0.5) | (mx > W - 0.5) | (my < -0.5) | (my > H - 0.5)
                state.valid &= ~out
                state.depth = np.where(out, 0.0, state.depth).astype(state.depth.dtype)
        else:
            z = np.where(state.valid, state.depth, 0).astype(np.float32)
            z = cv2.remap(z, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            state.depth = z
            state.valid = z > 0
        state.log[self.name] = {"active": True, "coefficients": list(coeffs)}

    @classmethod
    def evidence(cls, ctx, params: dict, gain: float | None = None) -> str:
        """Median |measured - ideal| and hole rate in the image centre (r < 0.35) vs the outer ring
        (r > 0.7), against the same numbers of the current model.

        Signature present when either (a) the measured outer/centre error ratio is >= 1.25 and
        >= 1.2x the current model's ratio (the model's ratio carries the radial change of depth and
        noise that has nothing to do with the lens), or (b) the outer ring's hole rate exceeds the
        model's there by :data:`ctx.MIN_RATE_EXCESS` more than in the centre."""
        r = ctx.radial()
        z, m, sm = ctx.ideal, ctx.measured, ctx.simulated
        inner, outer = r < 0.35, r > 0.7
        ei, eo = _robust_abs_err(m, z, inner), _robust_abs_err(m, z, outer)
        si, so = _robust_abs_err(sm, z, inner), _robust_abs_err(sm, z, outer)
        hi_, ho = ctx.rate(m <= 0, inner), ctx.rate(m <= 0, outer)
        hsi, hso = ctx.rate(sm <= 0, inner), ctx.rate(sm <= 0, outer)
        rm, rs = _ratio(eo, ei), _ratio(so, si)
        k1 = params.get("lens_distortion.k1")
        tail = f"; fitted k1 = {k1:+.3f}" if k1 is not None else ""
        err_growth = ctx.ge(rm, 1.25) and ctx.ge(rm, 1.2 * rs)
        hole_growth = ctx.ge((ho - hso) - (hi_ - hsi), ctx.MIN_RATE_EXCESS)
        err_txt = (f"median |measured - ideal| {1000 * ei:.1f} mm in the image centre and {1000 * eo:.1f} mm in the "
                   f"outer ring (x{rm:.1f}; current model x{rs:.1f})")
        hole_txt = f"hole rate {ctx.pct(hi_)} vs {ctx.pct(ho)} (current model {ctx.pct(hsi)} vs {ctx.pct(hso)})"
        if err_growth:
            return f"the residual grows with the image radius: {err_txt}, {hole_txt}{tail}."
        if hole_growth:
            return (f"the outer ring loses more pixels than the current model explains: {hole_txt}; "
                    f"{err_txt}{tail}.")
        return ctx.weak("radial signature", gain, f"{err_txt}, {hole_txt}")
