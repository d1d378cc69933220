"""``colmap``: an offline, colour-only baseline with COLMAP (pycolmap), independent of the depth
based trackers.

1. Keyframes (every ``keyframe_step``-th frame) are written as images; SIFT features are
   extracted with the camera fixed to the known pinhole intrinsics (colour is assumed
   registered to depth, as everywhere in realgap).
2. Sequential matching (each keyframe against the next ``overlap``) with geometric
   verification, then COLMAP's incremental mapping with the intrinsics held fixed. The
   largest model is kept.
3. Metric scale: COLMAP's reconstruction has an arbitrary scale. For every registered keyframe
   and every triangulated feature, the ratio between the measured depth at the feature and the
   point's z in that camera is collected; the scale is their median (robust to depth holes and
   mismatches). ``inlier_rmse`` of a keyframe is the RMS of (scaled z - measured depth) over
   its points within ``depth_check_m`` (metres), ``fitness`` the fraction of such points.
4. Poses of all frames: between two registered keyframes, interpolated (linear translation,
   spherical-linear rotation in time); frames outside the registered range, or between
   keyframes more than ``max_gap_keyframes`` apart, are reported as failed. The trajectory is
   expressed in the frame of the first registered keyframe.

Requires the optional package ``pycolmap`` (CPU wheel); it is imported only when the backend
runs. Slow (SIFT + bundle adjustment): meant as an independent third trajectory.
"""
from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, RealgapError
from slam.registration import RegistrationBackend, TrackResult, check_positive, register_backend


@dataclass
class ColmapConfig:
    """COLMAP baseline options."""

    keyframe_step: int = 10
    """Use every n-th processed frame as a COLMAP keyframe."""
    max_num_features: int = 4096
    """SIFT features per keyframe."""
    overlap: int = 10
    """Sequential matching: each keyframe is matched to the next ``overlap`` keyframes."""
    loop_detection: bool = False
    """Also match by vocabulary-tree retrieval (needs a vocabulary tree file; off by default)."""
    min_num_matches: int = 15
    """Fewest verified matches for an image pair to be used by the mapper."""
    min_model_size: int = 3
    """Fewest registered keyframes for a COLMAP model to be kept (COLMAP's default is 10)."""
    init_min_tri_angle_deg: float = 4.0
    """Smallest triangulation angle of the initial image pair, degrees (COLMAP's default 16 is
    too large for a hand-held camera a metre or two from the scene)."""
    max_gap_keyframes: int = 3
    """Interpolate only between registered keyframes at most this many keyframes apart."""
    depth_check_m: float = 0.05
    """Residual bound for the depth agreement (fitness / inlier_rmse) of a keyframe, metres."""
    min_scale_samples: int = 50
    """Fewest depth/point pairs needed to trust the metric scale."""
    num_threads: int = -1
    """COLMAP worker threads (-1 = all cores)."""
    seed: int = 0
    """Random seed of the mapper (RANSAC and initial pair choice)."""
    work_dir: str = ""
    """Where COLMAP's database and images go ('' = a temporary folder, deleted afterwards)."""

    def validate(self) -> "ColmapConfig":
        check_positive(self, "keyframe_step", "max_num_features", "overlap", "min_num_matches",
                       "max_gap_keyframes", "depth_check_m", "min_scale_samples", "min_model_size",
                       "init_min_tri_angle_deg")
        if self.num_threads == 0 or self.num_threads < -1:
            raise ConfigError(f"ColmapConfig.num_threads must be -1 or >= 1, got {self.num_threads}")
        return self


def _import_pycolmap():
    try:
        import pycolmap
    except ImportError:
        raise RealgapError("the colmap backend needs the optional package pycolmap "
                           "(pip install 'pycolmap==4.2.1')") from None
    try:  # COLMAP logs every step at INFO level; keep warnings and errors
        pycolmap.logging.minloglevel = 1
        pycolmap.logging.stderrthreshold = 1
    except AttributeError:
        pass
    return pycolmap


def _slerp(R0: np.ndarray, R1: np.ndarray, a: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation, Slerp
    s = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([R0, R1])))
    return s([a]).as_matrix()[0]


@register_backend
class ColmapBackend(RegistrationBackend):
    """Offline SfM on keyframes (pycolmap), metric scale from depth, interpolation."""

    name = "colmap"
    Config = ColmapConfig
    online = False
    uses_color = True

    def __init__(self, config: ColmapConfig, intrinsics, tsdf_config, sensor=None):
        super().__init__(config.validate(), intrinsics, tsdf_config, sensor)
        self.scale: float | None = None
        self.model_info: dict = {}

    def run_offline(self, reader, indices, progress: bool = True) -> list[TrackResult]:
        pycolmap = _import_pycolmap()
        import cv2
        c = self.config
        keys = indices[:: c.keyframe_step]
        if indices and keys[-1] != indices[-1]:
            keys.append(indices[-1])
        tmp = None
        work = Path(c.work_dir) if c.work_dir else Path(tmp := tempfile.mkdtemp(prefix="realgap_colmap_"))
        try:
            img_dir = work / "images"
            img_dir.mkdir(parents=True, exist_ok=True)
            db = work / "database.db"
            if db.exists():
                db.unlink()
            names, depths = {}, {}
            bar = _progress(progress, len(keys), "colmap: keyframes")
            for i in keys:
                f = reader[i]
                if f.rgb is None:
                    raise RealgapError(f"{reader.path}: the colmap backend needs colour images (frame {i} has none)")
                name = f"{i:06d}.png"
                cv2.imwrite(str(img_dir / name), np.ascontiguousarray(f.rgb[:, :, ::-1]))
                names[name] = i
                depths[i] = f.depth
                bar.update(1)
            bar.close()
            intr = self.intrinsics
            reader_opts = pycolmap.ImageReaderOptions()
            reader_opts.camera_model = "PINHOLE"
            reader_opts.camera_params = f"{intr.fx},{intr.fy},{intr.cx},{intr.cy}"
            ext = pycolmap.FeatureExtractionOptions()
            ext.sift.max_num_features = c.max_num_features
            ext.num_threads = c.num_threads
            ext.use_gpu = False
            pycolmap.extract_features(db, img_dir, image_names=sorted(names), camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader_opts, extraction_options=ext, device=pycolmap.Device.cpu)
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = c.overlap
            pairing.loop_detection = c.loop_detection
            match = pycolmap.FeatureMatchingOptions()
            match.use_gpu = False
            match.num_threads = c.num_threads
            pycolmap.match_sequential(db, matching_options=match, pairing_options=pairing, device=pycolmap.Device.cpu)
            opts = pycolmap.IncrementalPipelineOptions()
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
            opts.min_num_matches = c.min_num_matches
            opts.min_model_size = c.min_model_size
            opts.mapper.init_min_tri_angle = c.init_min_tri_angle_deg
            opts.num_threads = c.num_threads
            opts.random_seed = c.seed
            out = work / "sparse"
            out.mkdir(exist_ok=True)
            models = pycolmap.incremental_mapping(db, img_dir, out, options=opts)
            if not models:
                return [TrackResult(None, None, None, True, "COLMAP could not reconstruct the keyframes")
                        for _ in indices]
            rec = max(models.values(), key=lambda r: r.num_reg_images())
            return self._poses(rec, names, depths, indices, reader)
        finally:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)

    def _poses(self, rec, names, depths, indices, reader) -> list[TrackResult]:
        c = self.config
        cam_from_world: dict[int, np.ndarray] = {}
        obs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for img in rec.images.values():
            if not img.has_pose or img.name not in names:
                continue
            i = names[img.name]
            T = np.eye(4)
            T[:3, :4] = img.cam_from_world().matrix()
            cam_from_world[i] = T
            zs, ds = [], []
            h, w = depths[i].shape
            for p2d in img.points2D:
                if not p2d.has_point3D():
                    continue
                X = rec.points3D[p2d.point3D_id].xyz
                z = (T[:3, :3] @ X + T[:3, 3])[2]
                u, v = int(round(p2d.xy[0])), int(round(p2d.xy[1]))
                if 0 <= u < w and 0 <= v < h and z > 0:
                    d = float(depths[i][v, u])
                    if d > 0:
                        zs.append(z)
                        ds.append(d)
            obs[i] = (np.asarray(zs), np.asarray(ds))
        ratios = np.concatenate([d / z for z, d in obs.values() if len(z)]) if obs else np.zeros(0)
        if len(ratios) < c.min_scale_samples:
            raise RealgapError(f"{reader.path}: COLMAP registered {len(cam_from_world)} keyframes but only "
                               f"{len(ratios)} points have a depth: cannot recover the metric scale")
        s = float(np.median(ratios))
        self.scale = s
        self.model_info = {"registered_keyframes": len(cam_from_world), "points3D": int(rec.num_points3D()),
                           "scale": s, "scale_samples": int(len(ratios))}
        # camera-to-world, metric, in the frame of the first registered keyframe
        c2w = {}
        for i, T in cam_from_world.items():
            Ts = T.copy()
            Ts[:3, 3] *= s
            c2w[i] = np.linalg.inv(Ts)
        first = min(c2w)
        W = np.linalg.inv(c2w[first])
        c2w = {i: W @ P for i, P in c2w.items()}
        stats = {}
        for i, (z, d) in obs.items():
            r = z * s - d
            ok = np.abs(r) <= c.depth_check_m
            stats[i] = (float(ok.mean()) if len(r) else 0.0,
                        float(np.sqrt(np.mean(r[ok] ** 2))) if ok.any() else None)
        key_sorted = sorted(c2w)
        key_all = sorted(names.values())
        results = []
        for i in indices:
            if i in c2w:
                fit, rmse = stats[i]
                results.append(TrackResult(c2w[i], fit, rmse, False, "keyframe"))
                continue
            k = np.searchsorted(key_sorted, i)
            if k == 0 or k == len(key_sorted):
                results.append(TrackResult(None, None, None, True, "outside the registered keyframes"))
                continue
            a, b = key_sorted[k - 1], key_sorted[k]
            gap = key_all.index(b) - key_all.index(a)
            if gap > c.max_gap_keyframes:
                results.append(TrackResult(None, None, None, True,
                                           f"between keyframes {a} and {b}, {gap - 1} of them unregistered"))
                continue
            ta, tb, ti = reader.timestamps[a], reader.timestamps[b], reader.timestamps[i]
            al = float((ti - ta) / (tb - ta)) if tb > ta else 0.0
            P = np.eye(4)
            P[:3, :3] = _slerp(c2w[a][:3, :3], c2w[b][:3, :3], al)
            P[:3, 3] = (1 - al) * c2w[a][:3, 3] + al * c2w[b][:3, 3]
            results.append(TrackResult(P, None, None, False, "interpolated"))
        return results


class _NoBar:
    def update(self, n=1):
        pass

    def close(self):
        pass


def _progress(enabled: bool, total: int, desc: str):
    if not enabled:
        return _NoBar()
    from data_tools.progress import progress_bar
    return progress_bar(total=total, desc=desc, unit="frame")



