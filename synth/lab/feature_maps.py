"""Per-pixel geometry maps behind the lab's features (plain arrays in, arrays out): incidence
angles, radial distance, depth discontinuities, signed distances to them and the side of an edge
where projector shadows fall.

Depth discontinuities
---------------------
Two 4-neighbour pixels p, q with ideal depths z_p < z_q form a discontinuity when
``z_q - z_p > rel_threshold * z_p`` (default 5 %, above the ~1-4 % per-pixel depth change of a
plane seen at up to ~85 deg at VGA) or when only one of them has geometry (the empty one counts
as infinitely far). p joins the *near-edge* set, q the *far-edge* set. The signed distance of a
pixel is ``0.5 + d`` where d is the exact Euclidean distance transform (pixel centres) to the
nearer of the two sets: it approximates the distance to the crack between the two pixels, so the
two pixels beside a discontinuity get -0.5 (near) and +0.5 (far); values are never integers, so
they never fall on the integer bin edges. Ties (a 1-pixel-thin structure belongs to both sets)
go to the near side. A frame without any discontinuity gives +inf everywhere.

Where projector shadows fall (derivation, checked by ``tests/test_lab_compare.py``)
-------------------------------------------------------------------------------------
Camera at the origin (OpenCV axes: x right, y down, z forward), projector at ``(b, 0, 0)``
with b > 0. A foreground half-plane at depth z_f occupies x > x_e; the background is at
z_b > z_f. A background point (x, z_b) is *seen by the camera* when ``x * z_f / z_b <= x_e``
and is *lit* when the segment to the projector passes the foreground's depth at
``b + (x - b) z_f / z_b <= x_e``. Both fail together (visible but dark = shadow) for
``x_e z_b/z_f - b (z_b/z_f - 1) < x <= x_e z_b/z_f``, i.e. in the image for
``u_e - f b (1/z_f - 1/z_b) < u <= u_e`` with ``u_e`` the foreground's left edge: the shadow lies
on the background **beside the foreground edge on the side opposite to the projector** (image
-x for a projector at camera +x; the foreground, i.e. the occluder, lies *towards* the
projector), and is ``f b (1/z_f - 1/z_b)`` pixels wide (the disparity step). The mirror case (a
foreground occupying x < x_e, background on its +x side) gives an empty interval: no shadow on
the projector side. Kinect v1 (projector at camera +x) indeed shows its shadows left of objects.

``edge_shadow`` therefore classifies each far-edge pixel by the image direction ``o`` towards
its nearer 4-neighbours (its occluder) and the image direction ``d_b ~ (f_x b_x, f_y b_y)`` of the
baseline: ``o . d_b > 0`` -> shadow side (+), ``< 0`` -> lit side (-), ``= 0`` (edges parallel
to the baseline, e.g. horizontal edges for a horizontal baseline, which cast no shadow) -> NaN.
The same geometry holds for active stereo with the second camera in place of the projector.
Approximation: the baseline direction is taken as constant over the image (exact when the
projector offset has no z component, which is the case for all common sensors).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError
from data_tools.geometry import pixel_rays


def _angle_deg(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    n = np.asarray(normals, dtype=np.float64)
    nn = np.linalg.norm(n, axis=-1)
    dd = np.linalg.norm(directions, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.abs(np.sum(n * directions, axis=-1)) / (nn * dd)
    ang = np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))
    ang[~(nn > 0.5) | ~(dd > 0)] = np.nan
    return ang


def incidence_angle_deg(normals: np.ndarray, intr: Intrinsics, depth: np.ndarray | None = None,
                        origin_m: Sequence[float] | None = None,
                        idx: np.ndarray | None = None) -> np.ndarray:
    """Angle (degrees, [0, 90]) between the surface normal and the ray to a viewpoint.

    normals: (H, W, 3) camera-frame normals (orientation ignored; norm < 0.5 -> NaN).
    origin_m: viewpoint in the camera frame (metres); None = the camera centre, in which case
    the depth is not needed. With an origin (e.g. the projector offset) ``depth`` (H, W) metres
    gives the surface points; pixels with depth 0 get NaN.
    idx: optional flat pixel indices; then the result is (N,) for those pixels only.
    """
    h, w = intr.shape
    nrm = np.asarray(normals).reshape(h * w, 3)
    flat = np.arange(h * w) if idx is None else np.asarray(idx, dtype=np.int64)
    n = nrm[flat]
    rays = pixel_rays(intr, flat)
    if origin_m is None:
        ang = _angle_deg(n, rays)
    else:
        if depth is None:
            raise RealgapError("incidence_angle_deg: a depth image is needed with an origin")
        z = np.asarray(depth, dtype=np.float64).reshape(-1)[flat]
        pts = rays / rays[:, 2:3] * z[:, None]
        ang = _angle_deg(n, np.asarray(origin_m, dtype=np.float64)[None, :] - pts)
        ang[~(z > 0)] = np.nan
    return ang if idx is not None else ang.reshape(h, w)


def radial_distance(intr: Intrinsics, idx: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(normalised in [0, 1], pixels) distance of pixel centres from the principal point.

    Normalised by the largest distance from the principal point to the four corner pixel
    centres (the half-diagonal for a central principal point).
    """
    if idx is None:
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    else:
        v, u = np.divmod(np.asarray(idx, dtype=np.int64), intr.width)
    r = np.hypot(u - intr.cx, v - intr.cy)
    return np.minimum(r / radial_max_px(intr), 1.0), r


def radial_max_px(intr: Intrinsics) -> float:
    """Largest distance (pixels) from the principal point to a corner pixel centre (> 0)."""
    corners = [(0, 0), (intr.width - 1, 0), (0, intr.height - 1), (intr.width - 1, intr.height - 1)]
    return max(max(math.hypot(x - intr.cx, y - intr.cy) for x, y in corners), 1e-9)


@dataclass
class DepthEdges:
    """Discontinuities of an ideal depth image (see the module docstring)."""

    near: np.ndarray
    """(H, W) bool: pixels on the near (foreground) side of a discontinuity."""
    far: np.ndarray
    """(H, W) bool: pixels on the far (background or empty) side of a discontinuity."""
    occluder_dx: np.ndarray
    """(H, W) int8: sum over the nearer 4-neighbours of far-edge pixels of their x offset (+1 = occluder at +u)."""
    occluder_dy: np.ndarray
    """(H, W) int8: same along y (+1 = occluder at +v)."""


def depth_edges(ideal: np.ndarray, rel_threshold: float = 0.05) -> DepthEdges:
    """Near/far sides of the ideal-depth discontinuities (4-neighbourhood).

    ideal: (H, W) metres, 0 = no geometry (counts as infinitely far).
    rel_threshold: relative depth jump ``(z_far - z_near) / z_near`` that makes an edge.
    """
    z = np.asarray(ideal, dtype=np.float64)
    g = z > 0
    h, w = z.shape
    near = np.zeros((h, w), bool)
    far = np.zeros((h, w), bool)
    ox = np.zeros((h, w), np.int8)
    oy = np.zeros((h, w), np.int8)
    for axis in (1, 0):
        a = z[:, :-1] if axis == 1 else z[:-1, :]
        b = z[:, 1:] if axis == 1 else z[1:, :]
        ga = g[:, :-1] if axis == 1 else g[:-1, :]
        gb = g[:, 1:] if axis == 1 else g[1:, :]
        with np.errstate(invalid="ignore"):
            jump = ga & gb & (np.abs(a - b) > rel_threshold * np.minimum(a, b))
        disc = jump | (ga ^ gb)
        a_near = disc & ga & (~gb | (a < b))   # a (lower index) is the occluder, b behind it
        b_near = disc & ~a_near
        sl_a = (slice(None), slice(0, -1)) if axis == 1 else (slice(0, -1), slice(None))
        sl_b = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
        o = ox if axis == 1 else oy
        near[sl_a] |= a_near
        far[sl_b] |= a_near
        o[sl_b] -= a_near.astype(np.int8)      # occluder of b lies at -1 along the axis
        near[sl_b] |= b_near
        far[sl_a] |= b_near
        o[sl_a] += b_near.astype(np.int8)      # occluder of a lies at +1
    return DepthEdges(near, far, ox, oy)


def distance_to(mask: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance (pixels, float32) of every pixel centre to the nearest True pixel.

    inf everywhere when the mask is empty. Uses OpenCV's exact (``DIST_MASK_PRECISE``) transform.
    """
    import cv2

    if not mask.any():
        return np.full(mask.shape, np.inf, np.float32)
    return cv2.distanceTransform(np.where(mask, 0, 1).astype(np.uint8), cv2.DIST_L2,
                                 cv2.DIST_MASK_PRECISE)


@dataclass
class EdgeDistanceMaps:
    """Distance transforms (pixels, float32 (H, W)) to the edge-pixel sets of a depth image.

    The far-edge set is split by the side of its occluder relative to the baseline when a
    baseline direction is given (``shadow``/``lit``/``parallel``); otherwise only ``far`` is set.
    """

    near: np.ndarray
    """Distance to the nearest near-side edge pixel."""
    far: np.ndarray | None = None
    """Distance to the nearest far-side edge pixel (no baseline given)."""
    shadow: np.ndarray | None = None
    """Distance to far-side edge pixels whose occluder lies towards the projector."""
    lit: np.ndarray | None = None
    """Distance to far-side edge pixels whose occluder lies away from the projector."""
    parallel: np.ndarray | None = None
    """Distance to far-side edge pixels whose edge is parallel to the baseline."""

    def far_at(self, idx: np.ndarray | None = None) -> np.ndarray:
        pick = (lambda a: a.reshape(-1)[idx]) if idx is not None else (lambda a: a)
        if self.far is not None:
            return pick(self.far)
        return np.minimum(np.minimum(pick(self.shadow), pick(self.lit)), pick(self.parallel))


def edge_distance_maps(ideal: np.ndarray, rel_threshold: float = 0.05,
                       baseline_dir: np.ndarray | None = None,
                       edges: DepthEdges | None = None) -> EdgeDistanceMaps:
    """Exact distance transforms to the near/far edge sets (2 transforms, 4 with a baseline)."""
    e = edges if edges is not None else depth_edges(ideal, rel_threshold)
    dn = distance_to(e.near)
    if baseline_dir is None:
        return EdgeDistanceMaps(dn, far=distance_to(e.far))
    dot = e.occluder_dx * float(baseline_dir[0]) + e.occluder_dy * float(baseline_dir[1])
    return EdgeDistanceMaps(dn, shadow=distance_to(e.far & (dot > 1e-9)),
                            lit=distance_to(e.far & (dot < -1e-9)),
                            parallel=distance_to(e.far & (np.abs(dot) <= 1e-9)))


def signed_edge_values(maps: EdgeDistanceMaps, idx: np.ndarray | None = None) -> np.ndarray:
    """``edge_distance`` from distance maps, at flat indices ``idx`` (or the whole image)."""
    dn = maps.near.reshape(-1)[idx] if idx is not None else maps.near
    df = maps.far_at(idx)
    out = np.where(df < dn, df + 0.5, -(dn + 0.5)).astype(np.float32)
    out[np.isinf(dn) & np.isinf(df)] = np.inf
    return out


def shadow_edge_values(maps: EdgeDistanceMaps, idx: np.ndarray | None = None) -> np.ndarray:
    """``edge_shadow`` from distance maps built with a baseline direction."""
    if maps.shadow is None:
        raise RealgapError("shadow_edge_values needs distance maps built with a baseline direction")
    pick = (lambda a: a.reshape(-1)[idx]) if idx is not None else (lambda a: a)
    dn, dsh, dlit = pick(maps.near), pick(maps.shadow), pick(maps.lit)
    dfar = maps.far_at(idx)
    out = np.full(dn.shape, np.nan, np.float32)
    far_side = dfar < dn
    sh = far_side & (dsh == dfar)
    lit = far_side & ~sh & (dlit == dfar)
    out[sh] = dsh[sh] + 0.5
    out[lit] = -(dlit[lit] + 0.5)
    return out


def signed_edge_distance(ideal: np.ndarray, rel_threshold: float = 0.05,
                         edges: DepthEdges | None = None) -> np.ndarray:
    """Signed distance (pixels) to the nearest depth discontinuity: + far side, - near side.

    |value| = 0.5 + distance to the nearest edge pixel of the side the pixel belongs to; the side
    is the one whose edge-pixel set is nearer (ties -> near side). +inf when there is no edge.
    """
    return signed_edge_values(edge_distance_maps(ideal, rel_threshold, None, edges))


def baseline_image_direction(projector_offset_m: Sequence[float], intr: Intrinsics) -> np.ndarray | None:
    """Unit image direction (du, dv) of the projector baseline, or None when it has no x/y part."""
    bx, by = float(projector_offset_m[0]), float(projector_offset_m[1])
    d = np.array([intr.fx * bx, intr.fy * by])
    n = np.linalg.norm(d)
    if n < 1e-9 * max(intr.fx, intr.fy):
        return None
    return d / n


def shadow_edge_distance(ideal: np.ndarray, intr: Intrinsics, projector_offset_m: Sequence[float],
                         rel_threshold: float = 0.05, edges: DepthEdges | None = None) -> np.ndarray:
    """Signed distance (pixels) of background-side pixels to the nearest discontinuity.

    + where projector shadows fall (the occluder lies towards the projector along the
    baseline), - on the lit side; NaN for near-side pixels, pixels whose nearest edge is
    parallel to the baseline, and everywhere when the baseline has no image-plane component.
    """
    bdir = baseline_image_direction(projector_offset_m, intr)
    if bdir is None:
        return np.full(intr.shape, np.nan, np.float32)
    return shadow_edge_values(edge_distance_maps(ideal, rel_threshold, bdir, edges))
