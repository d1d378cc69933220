"""Depth patches: the network's input, cut from a depth image around a detection window.

Following Wohlhart & Lepetit 2015, a patch is object-centred, metric and depth-normalised:

1. The *reference depth* ``z_ref`` is the 10th percentile of the valid depths in the window,
   measured along the virtual camera's axis (step 2), i.e. the near side of the object. Measured on simulated Kinect v1 views of T-LESS obj_01/05/06
   (60 views, physical pipeline vs ideal depth), it moves by 0.6 mm median / 2.5 mm p90 with the
   sensor's holes and noise, against 3.3 / 11 mm for the median of the window's centre, which
   jumps between the levels of an object with holes.
2. A *virtual camera* at the real camera's centre looks along the ray through the window's
   centre (rotation ``R_ray``: the smallest rotation taking the optical axis onto that ray). Its
   image is ``size`` x ``size`` pixels covering ``crop_m`` metres at depth ``z_ref``, so an
   object appears at the same size whatever its distance, and as if it were in the image
   centre whatever its position in the image (the perspective of an off-centre object is
   undone, not just cropped).
3. Each patch pixel takes the depth of the nearest real pixel (no mixing of foreground and
   background), converted to the virtual camera's z, and is normalised to
   ``clip((z - z_ref) / (crop_m / 2), -1, 1)``; pixels without a measurement are +1 (as far as
   the patch goes: holes look like background, as they do to a real recogniser).

Poses are stored relative to that virtual camera (:func:`to_ray_frame` / :func:`from_ray_frame`):
the rotation ``R_local = R_ray^T R`` and the offset ``o = R_ray^T t - (0, 0, z_ref)`` of the
object centre from the reference point, metres. A database pose moved to a new window by
:func:`from_ray_frame` is the *initial estimate* that ICP then refines.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError

__all__ = ["PatchConfig", "Patch", "extract_patch", "depth_patch", "patch_pixels", "resample_nearest", "ray_rotation", "to_ray_frame", "from_ray_frame",
           "bbox_from_mask", "check_bbox"]


@dataclass
class PatchConfig:
    """How patches are cut (saved in the recogniser's configuration)."""

    size: int = 64
    """Patch side, pixels (the network input is size x size)."""
    crop_m: float = 0.15
    """Side of the patch at the reference depth, metres (training sets it to 1.2 x the largest
    object diameter)."""


@dataclass
class Patch:
    """One patch and the geometry needed to turn a database pose into a camera pose."""

    image: np.ndarray
    """(size, size) float32 normalised depth in [-1, 1]."""
    z_ref_m: float
    """Reference depth, metres (along the virtual camera's axis)."""
    R_ray: np.ndarray
    """(3, 3) rotation of the virtual camera in the real camera frame."""
    bbox: tuple[int, int, int, int]
    """The window (x0, y0, x1, y1), pixels, x1/y1 exclusive."""


def check_bbox(bbox, width: int, height: int, where: str = "bbox", min_inside: float = 0.0) -> tuple[int, int, int, int]:
    """The window as ints, clipped to the image; RealgapError (one line) when it is empty, lies
    outside the image, or less than ``min_inside`` of its area is inside the image (a user's
    window mostly off the image would be recognised from a sliver: ``recog predict`` asks 0.5)."""
    try:
        x0, y0, x1, y1 = (int(round(float(v))) for v in bbox)
    except (TypeError, ValueError):
        raise RealgapError(f"{where}: expected [x0, y0, x1, y1] in pixels, got {bbox!r}") from None
    if not (x1 > x0 and y1 > y0):
        raise RealgapError(f"{where}: empty window {[x0, y0, x1, y1]} (needs x1 > x0 and y1 > y0)")
    if x1 <= 0 or y1 <= 0 or x0 >= width or y0 >= height:
        raise RealgapError(f"{where}: window {[x0, y0, x1, y1]} lies outside the {width}x{height} image")
    clipped = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    inside = (clipped[2] - clipped[0]) * (clipped[3] - clipped[1]) / ((x1 - x0) * (y1 - y0))
    if inside < min_inside:
        raise RealgapError(f"{where}: window {[x0, y0, x1, y1]} is only {100 * inside:.0f} % inside the "
                           f"{width}x{height} image (at least {100 * min_inside:.0f} % needed)")
    return clipped


def bbox_from_mask(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) of the True pixels (x1/y1 exclusive), None when there are none."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def ray_rotation(intr: Intrinsics, u: float, v: float) -> np.ndarray:
    """(3, 3) smallest rotation taking the optical axis (0, 0, 1) onto the ray through pixel (u, v)."""
    d = np.array([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0])
    d /= np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    s, c = float(np.linalg.norm(axis)), float(d @ z)
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def extract_patch(depth_m: np.ndarray, intr: Intrinsics, bbox, config: PatchConfig) -> Patch:
    """The patch of the window ``bbox`` in ``depth_m`` ((H, W) float metres, 0/NaN = no
    measurement). RealgapError when the window is outside the image or holds no depth."""
    H, W = depth_m.shape
    x0, y0, x1, y1 = check_bbox(bbox, W, H)
    uc, vc = (x0 + x1 - 1) / 2.0, (y0 + y1 - 1) / 2.0
    R = ray_rotation(intr, uc, vc)
    win = np.nan_to_num(np.asarray(depth_m[y0:y1, x0:x1], dtype=np.float64), nan=0.0)
    vv, uu = np.nonzero(win > 0)
    if vv.size == 0:
        raise RealgapError(f"window {[x0, y0, x1, y1]}: no depth measurement inside it (empty crop)")
    # the window's depths as z in the virtual camera (z * K^-1 [u, v, 1] . R[:, 2])
    axis = R[:, 2]
    zv_win = win[vv, uu] * (((uu + x0) - intr.cx) / intr.fx * axis[0] + ((vv + y0) - intr.cy) / intr.fy * axis[1]
                            + axis[2])
    z_ref = float(np.percentile(zv_win, 10))
    return depth_patch(depth_m, intr, R, z_ref, (x0, y0, x1, y1), config)


def patch_pixels(intr: Intrinsics, R: np.ndarray, z_ref: float, config: PatchConfig) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) (size, size) real-image pixel coordinates of the rays of the virtual camera (rotation ``R``,
    reference depth ``z_ref``; see the module docstring)."""
    n = int(config.size)
    f_v = n * z_ref / float(config.crop_m)
    g = (np.arange(n, dtype=np.float64) - (n - 1) / 2.0) / f_v
    gx, gy = np.meshgrid(g, g)
    dv = np.stack([gx, gy, np.ones_like(gx)], -1)                # virtual-camera ray directions
    dr = dv @ R.T                                                  # the same rays in the real camera
    return intr.fx * dr[..., 0] / dr[..., 2] + intr.cx, intr.fy * dr[..., 1] / dr[..., 2] + intr.cy


def resample_nearest(image: np.ndarray, intr: Intrinsics, R: np.ndarray, z_ref: float,
                     config: PatchConfig) -> np.ndarray:
    """(size, size) nearest-neighbour samples of any (H, W) ``image`` (a mask, instance ids) at the pixels of
    the virtual camera (``R``, ``z_ref``); 0 outside the image. Pixel-aligned with :func:`depth_patch`."""
    import cv2
    u, v = patch_pixels(intr, R, z_ref, config)
    return cv2.remap(np.asarray(image, np.float32), u.astype(np.float32), v.astype(np.float32), cv2.INTER_NEAREST,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def depth_patch(depth_m: np.ndarray, intr: Intrinsics, R: np.ndarray, z_ref: float, bbox,
                config: PatchConfig) -> Patch:
    """The patch of ``depth_m`` seen by the virtual camera ``R`` at reference depth ``z_ref`` (steps 2-3 of the
    module docstring); :func:`extract_patch` chooses R and z_ref from the window, SynDA's training data reuses a
    clean view's R and z_ref for the noisy draws of the same view so that input and target align pixel by pixel."""
    import cv2
    u, v = patch_pixels(intr, R, z_ref, config)
    z = cv2.remap(np.nan_to_num(np.asarray(depth_m, np.float32), nan=0.0), u.astype(np.float32),
                  v.astype(np.float32), cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    # z-depth in the real camera -> z-depth in the virtual camera: the point z * K^-1 [u, v, 1]
    # seen along the virtual axis R[:, 2]
    ray_real = np.stack([(np.round(u) - intr.cx) / intr.fx, (np.round(v) - intr.cy) / intr.fy,
                         np.ones_like(u)], -1)
    zv = z * (ray_real @ R[:, 2])
    half = float(config.crop_m) / 2.0
    img = np.where(z > 0, np.clip((zv - z_ref) / half, -1.0, 1.0), 1.0).astype(np.float32)
    return Patch(img, z_ref, R, tuple(int(b) for b in bbox))


def to_ray_frame(T_obj2cam: np.ndarray, patch: Patch) -> tuple[np.ndarray, np.ndarray]:
    """(R_local (3, 3), offset (3,) metres) of an object-to-camera pose relative to the patch's
    virtual camera and reference point."""
    T = np.asarray(T_obj2cam, dtype=np.float64)
    R_local = patch.R_ray.T @ T[:3, :3]
    off = patch.R_ray.T @ T[:3, 3] - np.array([0.0, 0.0, patch.z_ref_m])
    return R_local, off


def from_ray_frame(R_local: np.ndarray, offset: np.ndarray, patch: Patch) -> np.ndarray:
    """4x4 object-to-camera pose of a database entry (R_local, offset) placed at ``patch``."""
    T = np.eye(4)
    T[:3, :3] = patch.R_ray @ np.asarray(R_local, float)
    T[:3, 3] = patch.R_ray @ (np.asarray(offset, float) + np.array([0.0, 0.0, patch.z_ref_m]))
    return T
