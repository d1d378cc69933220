"""ToF: light that reaches a pixel via another surface (multipath interference)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_DEPTH, Effect, Signature, param, register_effect

C_LIGHT = 299_792_458.0


@dataclass
class MultipathParams:
    strength: float = param(1.0, "1")
    """Scale of the indirect light (1 = Lambertian one-bounce estimate)."""
    modulation_hz: float = param(80e6, "Hz", 1000000.0, 1000000000.0)
    """Modulation frequency whose phase is measured (Kinect v2: 16/80/120 MHz; 80 MHz dominates)."""
    grid_px: int = param(12, "px", 1, 256)
    """Indirect light is computed on a grid of this spacing (pixels) and interpolated."""
    max_error_m: float = param(0.2, "m")
    """Clip of the multipath error, metres."""


@register_effect
class Multipath(Effect):
    """Depth error from one-bounce indirect illumination, with the phasor sum of a CW-ToF camera.

    Physics: a ToF camera measures the phase of the modulated light returning to each pixel.
    Besides the direct path (source -> surface -> camera, length 2 r) the pixel receives light
    that first lit another surface patch j and bounced to it (length r_j + |X_j - X_i| + r_i).
    The measured phase is that of the sum of the phasors, so in concave corners depth is
    overestimated. Indirect/direct ratio for Lambertian surfaces and a source at the camera:
    a_ij = albedo_j cos_j^src / r_j^2 * cos_j cos_i A_j / (pi d_ij^2) / (cos_i^src / r_i^2).
    Approximations: one bounce, no visibility test between patches (mutual visibility assumed),
    patches on a ``grid_px`` grid of the view itself (surfaces outside the field of view are
    ignored), a single modulation frequency.
    """

    name = "multipath"
    SIGNATURE = Signature(
        "too-far depths in concave corners",
        "Surfaces that face other surfaces (oblique, near corners) read too far.",
        panels=(("incidence", "bias"), ("incidence", "std")))
    IDENTITY_PARAMS = {"strength": 0.0}
    sensor_types = ("tof",)  # phase measurement of continuous-wave time of flight
    Params = MultipathParams
    FITTABLE = {"strength": (0.0, 10.0), "max_error_m": (0.0, 1.0)}
    stage = STAGE_DEPTH - 2

    def error_map(self, state) -> np.ndarray:
        import cv2
        v = state.view
        H, W = state.shape
        g = max(int(self.params.grid_px), 1)
        sl = (slice(g // 2, H, g), slice(g // 2, W, g))
        X = v.points_cam[sl].reshape(-1, 3).astype(np.float32)
        N = v.normals_cam[sl].reshape(-1, 3).astype(np.float32)
        alb = v.albedo[sl].ravel().astype(np.float32)
        hit = v.hit[sl].ravel()
        gh, gw = v.hit[sl].shape
        r = np.linalg.norm(X, axis=1)
        r = np.where(hit, r, 1.0)
        cos_src = np.clip(-(N * X).sum(1) / r, 0.0, 1.0) * hit
        z = X[:, 2]
        f = float(state.intr.fx)
        area = (np.where(hit, z, 0) * g / f) ** 2 / np.maximum(cos_src, 0.05)   # patch area, m^2
        src_j = (alb * cos_src / r ** 2 * area * np.float32(self.params.strength)).astype(np.float32)
        area = area.astype(np.float32)
        k = np.float32(2 * np.pi * self.params.modulation_hz / C_LIGHT)
        err = np.zeros(len(X), np.float32)
        idx = np.nonzero(hit & (cos_src > 0))[0]
        if len(idx) < 2:
            return np.zeros((H, W), np.float32)
        Xs, Ns, rs, src, As = X[idx], N[idx], r[idx], src_j[idx], area[idx]
        xn_s = (Xs * Ns).sum(1)                                   # X_j . n_j
        x2_s = (Xs * Xs).sum(1)
        chunk = max(1, 1_000_000 // len(idx))
        for a in range(0, len(idx), chunk):
            ii = idx[a:a + chunk]
            Xi, Ni = X[ii], N[ii]
            # with D = X_j - X_i: |D|^2, D.n_i and -D.n_j from three matrix products
            d2 = x2_s[None, :] + (Xi * Xi).sum(1)[:, None] - 2.0 * (Xi @ Xs.T)
            d2 = np.maximum(d2, np.float32(1e-12))
            d = np.sqrt(d2)
            ci = (Ni @ Xs.T - (Xi * Ni).sum(1)[:, None]) / d      # cos at the receiver
            cj = (Xi @ Ns.T - xn_s[None, :]) / d                  # cos at the sender
            ok = (ci > 0) & (cj > 0) & (d2 > 4 * As[None, :])
            w = np.where(ok, src[None, :] * ci * cj / (np.float32(np.pi) * d2), np.float32(0.0))
            w /= np.maximum(cos_src[ii] / r[ii] ** 2, 1e-9)[:, None]
            dpath = rs[None, :] + d - r[ii, None]                  # extra length vs direct 2 r_i
            re = 1.0 + (w * np.cos(k * dpath)).sum(1)
            im = (w * np.sin(k * dpath)).sum(1)
            err[a:a + chunk] = np.arctan2(im, re) / (2 * k)       # extra one-way range, metres
        err = np.clip(err, -self.params.max_error_m, self.params.max_error_m)
        small = err.reshape(gh, gw)
        big = cv2.resize(small, (gw * g, gh * g), interpolation=cv2.INTER_LINEAR)
        out = np.zeros((H, W), np.float32)
        out[:min(H, big.shape[0]), :min(W, big.shape[1])] = big[:H, :W]
        return out

    def apply(self, state, draw) -> None:
        err_r = self.error_map(state)
        v = state.view
        rr = np.maximum(np.linalg.norm(v.points_cam, axis=-1), 1e-6)
        dz = err_r * v.points_cam[..., 2] / rr                     # range error -> z error
        state.depth = np.where(state.valid, state.depth + dz, 0).astype(np.float32)
        vz = state.valid
        state.log[self.name] = {"mean_error_m": float(dz[vz].mean()) if vz.any() else 0.0,
                                "max_error_m": float(dz[vz].max()) if vz.any() else 0.0}
