"""Sparse-feature pose guesses used to re-localise after a tracking failure.

ORB key points of the current colour image are matched to those of a keyframe whose depth is
known; the keyframe points are lifted to 3-D with its depth and the current camera pose is
found by PnP with RANSAC (OpenCV). The result is only an initial guess: the backends verify
it with their dense registration and the same failure checks as ordinary tracking.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data_tools.camera import Intrinsics


@dataclass
class PnPGuess:
    """A pose guess from feature matching."""

    T_cur_to_kf: np.ndarray
    """(4, 4) transform of current-camera points into the keyframe camera."""
    inliers: int
    """RANSAC inlier matches."""
    matches: int
    """Matches that had a valid keyframe depth."""


def orb_features(rgb: np.ndarray, n_features: int):
    """(key points, descriptors) of an (H, W, 3) uint8 RGB image."""
    import cv2
    gray = cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    orb = cv2.ORB_create(nfeatures=int(n_features))
    return orb.detectAndCompute(gray, None)


def pnp_guess(kf_features, kf_depth: np.ndarray, cur_features, intr: Intrinsics,
              min_inliers: int = 25, ratio: float = 0.8, reproj_px: float = 3.0,
              seed: int = 0) -> PnPGuess | None:
    """Pose of the current camera relative to the keyframe, or None when there is no
    trustworthy guess (too few matches or RANSAC inliers). Deterministic for a fixed seed."""
    import cv2
    kp_k, des_k = kf_features
    kp_c, des_c = cur_features
    if des_k is None or des_c is None or len(kp_k) < min_inliers or len(kp_c) < min_inliers:
        return None
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    knn = matcher.knnMatch(des_c, des_k, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if len(good) < min_inliers:
        return None
    h, w = kf_depth.shape
    obj, img = [], []
    for m in good:
        u, v = kp_k[m.trainIdx].pt
        ui, vi = int(round(u)), int(round(v))
        if not (0 <= ui < w and 0 <= vi < h):
            continue
        z = float(kf_depth[vi, ui])
        if not np.isfinite(z) or z <= 0:
            continue
        obj.append([(ui - intr.cx) / intr.fx * z, (vi - intr.cy) / intr.fy * z, z])
        img.append(kp_c[m.queryIdx].pt)
    if len(obj) < min_inliers:
        return None
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        np.asarray(obj, np.float64), np.asarray(img, np.float64), intr.K, None,
        iterationsCount=200, reprojectionError=reproj_px, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    R, _ = cv2.Rodrigues(rvec)
    T_kf_to_cur = np.eye(4)
    T_kf_to_cur[:3, :3] = R
    T_kf_to_cur[:3, 3] = tvec.ravel()
    return PnPGuess(np.linalg.inv(T_kf_to_cur), int(len(inl)), len(obj))
