"""Planar-target references: captures of a flat target without poses -> a sequence the sensor lab
can compare against (``realgap data make-reference SEQ --plane --out REF``).

This is how Khoshelham & Elberink 2012, Nguyen et al. 2012, Smisek et al. 2011 and Herrera et al.
2012 measured the Kinect: the sensor in front of a flat target at many distances. Per frame:

1. the dominant plane of the window ``roi`` (default the whole image) is found by RANSAC
   (Open3D ``segment_plane`` on every second pixel's point, threshold ``ransac_threshold_m``,
   seeded) and refined by least squares (SVD) on its inliers;
2. the frame's *mask* is where the target is: the pixels within ``max(mask_threshold_m, 3 sigma(z))``
   of the plane (sigma = Nguyen et al.'s axial noise), inside the ROI, reduced to the largest
   connected component and closed (3x3) - the target, without the room behind it - plus everything
   inside that component's outline that is a hole (depth 0) or within ``OUTLIER_FACTOR`` x the band.
   The lab compares hole rates and error distributions on the mask: a mask of only the pixels the
   sensor measured inside the band reads a hole rate of 0 and cuts the noise tails of a sensor
   noisier than Nguyen's (at 2 x his sigma the band is 1.5 sigma, the robust std reads 0.85 x);
3. a *flatness check* keeps only the clean part of that plane (:func:`flat_support`): the mask is
   cut into tiles of ``tile_px`` (scaled to a 640 px wide image); the plane is refitted by least
   squares on the mask, and a tile is rejected when the median of its residuals is off the plane
   by more than ``tile_offset_sigma`` x the noise at its depth (the larger of sigma(z) and the tile's
   own robust spread, over sqrt of the tile's valid pixels, floored at ``tile_offset_floor_m`` and ``tile_offset_floor_sigma`` sigma(z): an object lying in the +-3 sigma band, a bent or
   second surface) or when more than ``tail_fraction`` of its residuals lie beyond 3 x its own robust
   spread (a small object or a step inside the tile). The plane is refitted on the kept tiles
   (twice); a frame keeping fewer than ``min_flat_share`` of its tiles is not a clean plane and
   gets no pose. plane_reference.json records per frame the tiles kept and the plane's own
   flatness: the RMS of the kept tiles' median residuals (``flatness_mm``), which holds the
   sensor's low-frequency depth distortion and whatever curvature the target has;
4. the frame's *pose* puts that plane on the world plane z = 0 (the camera on the +z side at its
   distance from the plane; the rotation is the smallest that takes the plane normal to +z, so
   the in-plane position and yaw, which a plane cannot determine, are fixed by convention).

REF gets a copy of the sequence (images hard-linked), ``groundtruth.txt`` with those poses (frames
whose plane has fewer than ``min_inliers`` inliers get none and are skipped by the lab),
``mask.txt`` + ``mask/*.png`` (../shared/FORMATS.md section 4), ``scene.json`` with one large
square of the world plane (material ``target``) and ``plane_reference.json`` (the fitted planes).
"""
from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError

__all__ = ["PlaneReferenceConfig", "fit_plane", "plane_pose", "plane_mask", "make_plane_reference",
           "PlaneReferenceResult", "flat_support", "FlatSupport"]


@dataclass
class PlaneReferenceConfig:
    """How the planar reference is made (saved in plane_reference.json)."""

    roi: tuple[int, int, int, int] | None = None
    """Window x0, y0, x1, y1 (pixels, x1/y1 exclusive) holding the target; None = the whole image."""
    ransac_threshold_m: float = 0.01
    """RANSAC inlier distance, metres."""
    mask_threshold_m: float = 0.01
    """Smallest distance from the plane that still counts as target, metres (grown to 3 sigma(z))."""
    min_inliers: int = 500
    """Frames whose plane has fewer inliers get no pose."""
    material: str = "target"
    """Material name of the plane in scene.json."""
    albedo: float = 0.5
    """Its albedo."""
    seed: int = 0
    """RANSAC seed."""
    flatness_check: bool = True
    """Keep only the tiles of the mask that lie flat on the plane (module docstring, step 3)."""
    tile_px: int = 32
    """Tile size of the flatness check, pixels at a 640 px wide image (scaled with the width)."""
    tile_offset_sigma: float = 4.0
    """A tile whose median residual exceeds this many standard errors of the sensor noise
    (sigma(z) / sqrt(pixels)) is off the plane."""
    tile_offset_floor_m: float = 0.002
    """...but never for less than this offset, metres, ..."""
    tile_offset_floor_sigma: float = 0.5
    """...nor for less than this many sigma(z) (a real Kinect's low-frequency depth distortion is a
    few mm and grows with z^2 like the noise: it is the sensor's, not the target's)."""
    tail_fraction: float = 0.05
    """A tile with more than this share of residuals beyond 3 x its robust std holds a step or an object."""
    min_flat_share: float = 0.25
    """A frame keeping fewer than this share of its tiles is not a clean plane (no pose); a cluttered
    desk (TUM fr1/xyz) keeps 30-45 % of its tiles, a clean wall or floor > 90 %."""

    def validate(self) -> "PlaneReferenceConfig":
        if self.roi is not None:
            x0, y0, x1, y1 = self.roi
            if not (x1 > x0 >= 0 and y1 > y0 >= 0):
                raise ConfigError(f"--roi must be x0,y0,x1,y1 with x1 > x0 >= 0 and y1 > y0 >= 0, got {self.roi}")
        for k in ("ransac_threshold_m", "mask_threshold_m"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"{k} must be > 0, got {getattr(self, k)}")
        if not 0 <= self.albedo <= 1:
            raise ConfigError(f"--albedo must be in [0, 1], got {self.albedo}")
        return self


OUTLIER_FACTOR = 3.0
"""Inside the target's outline, residuals up to this many times the mask band count as target."""


def _nguyen_sigma(z: np.ndarray) -> np.ndarray:
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def fit_plane(points: np.ndarray, threshold_m: float, seed: int = 0, iterations: int = 300):
    """(n (3,), d, inlier count) of the dominant plane n.X + d = 0 of (N, 3) camera-frame points,
    n pointing to the camera (d > 0): Open3D RANSAC, then least squares on the inliers."""
    import open3d as o3d
    if len(points) < 3:
        return None
    o3d.utility.random.seed(int(seed))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    model, inl = pc.segment_plane(float(threshold_m), 3, int(iterations))
    P = np.asarray(points, np.float64)[np.asarray(inl, int)]
    if len(P) < 3:
        return None
    n, d = _refit(P)
    res = np.abs(np.asarray(points) @ n + d)
    return n, d, int((res < threshold_m).sum())


def plane_pose(n: np.ndarray, d: float) -> np.ndarray:
    """4x4 camera-to-world pose putting the camera-frame plane n.X + d = 0 (n towards the camera)
    on the world plane z = 0, the camera at height d."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(n, z), float(n @ z)
    if np.linalg.norm(v) < 1e-12:
        R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        R = np.eye(3) + K + K @ K * (1.0 / (1.0 + c))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.0, 0.0, d]
    return T


def plane_mask(depth: np.ndarray, intr, n: np.ndarray, d: float, roi, threshold_m: float) -> np.ndarray:
    """(H, W) bool: pixels on the plane (see the module docstring, step 2)."""
    import cv2
    from data_tools.geometry import unproject
    H, W = depth.shape
    pts = unproject(depth, intr)
    z = depth
    tol = np.maximum(threshold_m, 3.0 * _nguyen_sigma(z))
    res = pts @ n + d
    on = (z > 0) & (np.abs(res) < tol)
    if roi is not None:
        x0, y0, x1, y1 = roi
        box = np.zeros_like(on)
        box[y0:min(y1, H), x0:min(x1, W)] = True
        on &= box
    if not on.any():
        return on
    k, lab, stats, _ = cv2.connectedComponentsWithStats(on.astype(np.uint8), connectivity=8)
    if k > 2:
        big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        on = lab == big
    from scipy.ndimage import binary_fill_holes
    closed = cv2.morphologyEx(on.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    inside = binary_fill_holes(closed)
    return inside & ((z <= 0) | (np.abs(res) < OUTLIER_FACTOR * tol)) | on


@dataclass
class FlatSupport:
    """Result of :func:`flat_support` on one frame."""

    mask: np.ndarray
    """(H, W) bool: the kept (flat) part of the mask."""
    n: np.ndarray
    """Unit normal of the plane refitted on it (towards the camera)."""
    d: float
    """Its offset (n.X + d = 0), metres."""
    tiles: int
    """Tiles of the mask with enough pixels to judge."""
    kept: int
    """Of those, the tiles kept."""
    flatness_mm: float
    """RMS of the kept tiles' median residuals, mm (the reference's own non-flatness)."""
    residual_mm: float
    """Robust std (1.4826 MAD) of all kept residuals, mm."""


def _refit(P: np.ndarray):
    """(n, d) of the least-squares plane n.X + d = 0 through (N, 3) points, n towards the camera (d > 0)."""
    c = P.mean(0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    n = vt[2]
    d = -float(n @ c)
    return (-n, -d) if d < 0 else (n, d)


def flat_support(depth: np.ndarray, intr, mask: np.ndarray, n: np.ndarray, d: float,
                 cfg: "PlaneReferenceConfig") -> FlatSupport:
    """The flat part of ``mask`` and the plane refitted on it (module docstring, step 3)."""
    from data_tools.geometry import unproject
    H, W = depth.shape
    pts = unproject(depth, intr)
    t = max(4, int(round(cfg.tile_px * W / 640)))
    ty, tx = np.divmod(np.arange(H * W).reshape(H, W), W)
    tile_id = (ty // t) * ((W + t - 1) // t) + tx // t
    on = mask & (depth > 0)
    flat = on.ravel()
    P = pts.reshape(-1, 3)
    tid = tile_id.ravel()
    z = depth.ravel().astype(np.float64)
    min_px = max(20, t * t // 4)
    kept_tiles, judged = set(), []
    meds = {}
    sel = np.flatnonzero(flat)
    for _ in range(3):                                    # judge every tile, refit on the kept ones; twice
        if sel.size < 3:
            break
        res = P[sel] @ n + d
        order = np.argsort(tid[sel], kind="stable")
        ids, starts = np.unique(tid[sel][order], return_index=True)
        judged, kept_tiles, meds = [], set(), {}
        for k, (tile, a) in enumerate(zip(ids, starts)):
            b = starts[k + 1] if k + 1 < len(starts) else order.size
            if b - a < min_px:
                continue
            judged.append(tile)
            r = res[order[a:b]]
            med = float(np.median(r))
            spread = 1.4826 * float(np.median(np.abs(r - med)))
            sig = float(_nguyen_sigma(np.median(z[sel][order[a:b]])))
            tol = max(cfg.tile_offset_floor_m, cfg.tile_offset_floor_sigma * sig,   # the median's standard
                      cfg.tile_offset_sigma * max(sig, spread) / math.sqrt(b - a))  # error: the tile's own noise
            tails = float(np.mean(np.abs(r - med) > 3.0 * max(spread, 1e-6)))
            if abs(med) <= tol and tails <= cfg.tail_fraction:
                kept_tiles.add(tile)
                meds[tile] = med
        flat = on.ravel() & np.isin(tid, list(kept_tiles))
        if flat.sum() >= 3:
            n, d = _refit(P[flat])
    region = mask.ravel() & np.isin(tid, list(kept_tiles))    # with the sensor's holes in kept tiles
    sel = np.flatnonzero(flat)
    res = P[sel] @ n + d if sel.size else np.zeros(0)
    mad = 1.4826 * float(np.median(np.abs(res - np.median(res)))) if res.size else float("nan")
    fl = float(np.sqrt(np.mean(np.square(list(meds.values()))))) if meds else float("nan")
    return FlatSupport(region.reshape(H, W), np.asarray(n, float), float(d), len(judged), len(kept_tiles),
                       1000 * fl, 1000 * mad)


@dataclass
class PlaneReferenceResult:
    out_dir: Path
    frames: int
    frames_posed: int
    distances_m: list = field(default_factory=list)
    """Camera-to-plane distance of each posed frame, metres."""
    mask_fraction: list = field(default_factory=list)
    seconds: float = 0.0


def make_plane_reference(seq_dir, out_dir, config: PlaneReferenceConfig | None = None, *, camera=None,
                         max_frames: int | None = None, spread_frames: int | None = None, overwrite: bool = False,
                         progress: bool = True) -> PlaneReferenceResult:
    """Write the planar reference of ``seq_dir`` into ``out_dir`` (see the module docstring)."""
    from data_tools.geometry import pose_to_tum, unproject
    from data_tools.mesh import TriMesh
    from data_tools.outputs import check_input_dir, check_output_dir, clear_incomplete, mark_incomplete
    from data_tools.results import atomic_write_image, atomic_write_json, atomic_write_text
    from data_tools.scene_spec import Material, SceneSpec, write_scene_json
    from data_tools.sequence import SequenceReader
    from slam.reference import _copy_sequence
    cfg = (config or PlaneReferenceConfig()).validate()
    src = check_input_dir(seq_dir, "sequence folder")
    out = check_output_dir(out_dir, what="output sequence folder", finished="plane_reference.json",
                           overwrite=overwrite)
    if out.resolve() == src.resolve():
        raise ConfigError("--out must not be the input sequence (the reference is written beside a copy)")
    t0 = time.perf_counter()
    reader = SequenceReader(src, camera=camera)
    cam = camera or reader.camera
    intr = cam.intrinsics
    if cfg.roi is not None and (cfg.roi[0] >= intr.width or cfg.roi[1] >= intr.height):
        raise ConfigError(f"--roi {cfg.roi} lies outside the {intr.width}x{intr.height} image")
    idx = list(range(len(reader)))[:max_frames]       # the first max_frames, then spread_frames of them
    if spread_frames is not None and spread_frames < len(idx):
        idx = sorted(set(np.linspace(0, len(idx) - 1, spread_frames).round().astype(int).tolist()))
    _copy_sequence(reader, out, cam)
    for name in ("groundtruth.txt", "mask.txt"):
        (out / name).unlink(missing_ok=True)
    mark_incomplete(out, "realgap data make-reference --plane", 0, len(idx), resumable=False)
    (out / "mask").mkdir(exist_ok=True)
    gt = ["# camera-to-world poses putting the fitted target plane on z = 0 (realgap make-reference --plane)",
          "# timestamp tx ty tz qx qy qz qw"]
    masks = ["# masks of the target's pixels (255 = compare)", "# timestamp filename"]
    planes, dists, fracs = [], [], []
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=len(idx), desc="fitting planes", unit="frame")
    for done, i in enumerate(idx, 1):
        depth = reader.read_depth(i)
        ts = f"{reader.timestamps[i]:.6f}"
        sub = depth[::2, ::2]
        pts = unproject(depth, intr)[::2, ::2]
        ok = sub > 0
        if cfg.roi is not None:
            x0, y0, x1, y1 = cfg.roi
            vv, uu = np.mgrid[0:depth.shape[0]:2, 0:depth.shape[1]:2]
            ok &= (uu >= x0) & (uu < x1) & (vv >= y0) & (vv < y1)
        fit = fit_plane(pts[ok], cfg.ransac_threshold_m, cfg.seed + i)
        rel = f"mask/{ts}.png"
        if fit is None or fit[2] * 4 < cfg.min_inliers:
            mask = np.zeros(depth.shape, bool)
            planes.append({"timestamp": float(ts), "posed": False})
        else:
            n, d, _ = fit
            mask = plane_mask(depth, intr, n, d, cfg.roi, cfg.mask_threshold_m)
            extra, why = {}, "too few pixels on the plane"
            if cfg.flatness_check and mask.sum() >= cfg.min_inliers:
                fs = flat_support(depth, intr, mask, n, d, cfg)
                extra = {"tiles": fs.tiles, "tiles_kept": fs.kept, "flatness_mm": fs.flatness_mm,
                         "residual_mm": fs.residual_mm}
                if fs.kept < cfg.min_flat_share * max(fs.tiles, 1):
                    why = f"not flat: {fs.kept} of {fs.tiles} tiles lie flat on the plane"
                    mask = np.zeros(depth.shape, bool)
                else:
                    mask, n, d = fs.mask, fs.n, fs.d
            if mask.sum() < cfg.min_inliers:
                planes.append({"timestamp": float(ts), "posed": False, "reason": why, **extra})
                mask = np.zeros(depth.shape, bool)
            else:
                T = plane_pose(n, d)
                gt.append(f"{ts} " + " ".join(f"{x:.9g}" for x in pose_to_tum(T)))
                planes.append({"timestamp": float(ts), "posed": True, "normal": [float(x) for x in n],
                               "distance_m": float(d), "mask_pixels": int(mask.sum()), **extra})
                dists.append(float(d))
                fracs.append(float(mask.mean()))
        atomic_write_image(out / rel, mask.astype(np.uint8) * 255)
        masks.append(f"{ts} {rel}")
        if done % 25 == 0 or done == len(idx):
            mark_incomplete(out, "realgap data make-reference --plane", done, len(idx), resumable=False)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    if not dists:
        raise FormatError(src, "no frame has a dominant plane with enough inliers (is the target in view? try --roi)")
    atomic_write_text(out / "groundtruth.txt", "\n".join(gt) + "\n")
    atomic_write_text(out / "mask.txt", "\n".join(masks) + "\n")
    size = max(20.0, 20 * max(dists))
    plane = TriMesh(np.array([[-size, -size, 0], [size, -size, 0], [size, size, 0], [-size, size, 0]], float),
                    np.array([[0, 1, 2], [0, 2, 3]]), "target_plane", cfg.material)
    write_scene_json(out, SceneSpec([plane], {cfg.material: Material(float(cfg.albedo), 0.0)}))
    res = PlaneReferenceResult(out, len(idx), len(dists), dists, fracs, time.perf_counter() - t0)
    atomic_write_json(out / "plane_reference.json", {
        "source": str(src.resolve()), "config": asdict(cfg), "frames": len(idx), "frames_posed": len(dists),
        "planes": planes, "seconds": res.seconds})
    clear_incomplete(out)
    return res
