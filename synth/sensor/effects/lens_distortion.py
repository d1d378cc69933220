"""Radial + tangential lens distortion of the IR camera."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_OPTICS, STAGE_WARP, Effect, register_effect


@dataclass
class LensDistortionParams:
    coefficients: tuple = ()
    """OpenCV (k1, k2, p1, p2, k3); empty = the preset's ``distortion``."""


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


@register_effect
class LensDistortion(Effect):
    """The IR lens bends rays: the device's image is distorted (radial k1 k2 k3, tangential p1 p2).

    Physics: real lenses map a ray of normalised direction (x, y) to the distorted position of
    the Brown-Conrady model (OpenCV's). Depth cameras report depth on their distorted pixel
    grid; the reference pattern of a structured-light device was captured through the same
    lens, so the disparity is computed between two distorted images; converting it with one
    constant f b then gives a depth bias growing with the image radius (the physical origin of
    the radial 'depth distortion' that Kinect calibration papers correct). Physical pipeline:
    the radiance image (and the reference) is warped before capture. Direct model: the depth
    image is warped (nearest neighbour, so edges are not blended). Either way the output is in
    distorted pixel coordinates and ``SensorSimulator.camera()`` lists the coefficients.
    """

    name = "lens_distortion"
    IDENTITY_PARAMS = {"coefficients": (0.0, 0.0, 0.0, 0.0, 0.0)}
    Params = LensDistortionParams
    in_reference = True

    def __init__(self, params=None, enabled=True):
        super().__init__(params, enabled)
        self._maps: dict = {}

    def validate(self) -> None:
        if len(self.params.coefficients) not in (0, 4, 5, 8):
            from data_tools.errors import ConfigError
            raise ConfigError(f"effect 'lens_distortion': coefficients need 4, 5 or 8 numbers, "
                              f"got {len(self.params.coefficients)}")

    def coefficients(self, preset) -> tuple:
        return tuple(self.params.coefficients) or tuple(preset.distortion)

    def stage_for(self, physical_model: bool) -> int:
        return STAGE_OPTICS + 5 if physical_model else STAGE_WARP

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
        else:
            z = np.where(state.valid, state.depth, 0).astype(np.float32)
            z = cv2.remap(z, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            state.depth = z
            state.valid = z > 0
        state.log[self.name] = {"active": True, "coefficients": list(coeffs)}
