"""Physical stage 1: the virtual projector casts its dot pattern onto the scene."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_PROJECTION, Effect, register_effect


@dataclass
class PatternProjectionParams:
    power: float = 1.0
    """Projector radiant intensity scale: radiance 1 = a white Lambertian surface facing the
    projector at 1 m lit by pattern value 1."""
    dot_sigma_px: float = 0.5
    """Gaussian spread of one projected dot, in pattern pixels (diffraction/defocus of the
    DOE; also the anti-aliasing filter of the point-sampled pattern)."""
    specular_exponent: float = 40.0
    """Phong exponent of the mirror lobe (larger = tighter highlight)."""
    shadow_rays: bool = True
    """Cast a shadow ray from every lit surface point to the projector (projector shadows)."""
    shadow_eps_m: float = 0.002
    """Free gap at both ends of a shadow ray, metres (no self-shadowing)."""
    shadow_method: str = "raycast"
    """``raycast``: one shadow ray per lit pixel through the scene's RaycastingScene (exact);
    ``scanline``: the rectified-rig ordering test on the camera's own depth (a pixel is
    shadowed when a pixel farther towards the projector along its row maps to the same or an
    earlier projector column) - O(pixels), misses occluders the camera cannot see."""


def blurred_pattern(pattern_img: np.ndarray, sigma: float, cache: dict) -> np.ndarray:
    import cv2
    key = (id(pattern_img), round(float(sigma), 6))
    p = cache.get(key)
    if p is None:
        p = cv2.GaussianBlur(pattern_img, (0, 0), sigma) if sigma > 0 else pattern_img
        cache.clear()
        cache[key] = p = np.ascontiguousarray(p, dtype=np.float32)
    return p


_NORM_CACHE: dict = {}


def normalized_coords(ray_dirs_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x/z, y/z) of each pixel's ray, contiguous float32 (cached per ray grid)."""
    key = (id(ray_dirs_cam), ray_dirs_cam.shape)
    hit = _NORM_CACHE.get(key)
    if hit is None or hit[0] is not ray_dirs_cam:
        z = ray_dirs_cam[..., 2]
        hit = (ray_dirs_cam, np.ascontiguousarray(ray_dirs_cam[..., 0] / z, dtype=np.float32),
               np.ascontiguousarray(ray_dirs_cam[..., 1] / z, dtype=np.float32))
        if len(_NORM_CACHE) > 8:
            _NORM_CACHE.clear()
        _NORM_CACHE[key] = hit
    return hit[1], hit[2]


def _nthreads() -> int:
    import os
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return 0


def shadow_test(renderer, view, src_cam: np.ndarray, Lx, Ly, Lz, r, mask: np.ndarray, eps_m: float) -> np.ndarray:
    """(H, W) bool: True where the segment from the light source at ``src_cam`` (camera frame
    of ``view``) to the surface point is blocked. ``L = X - src`` per pixel (camera frame),
    ``r = |L|``; only ``mask`` pixels are tested. Rays start at the source and stop ``eps_m``
    before the surface (no self-shadowing); one Open3D occlusion query per pixel. All
    per-pixel work is element-wise float32 on contiguous arrays (no (N, 3) matmuls)."""
    import open3d as o3d
    out = np.zeros(mask.shape, bool)
    n = int(np.count_nonzero(mask))
    if n == 0:
        return out
    src_cam = np.asarray(src_cam, np.float32)
    scale = np.float32(1.0) - np.float32(eps_m) / np.maximum(r, np.float32(2 * eps_m))
    rays = np.empty((n, 6), np.float32)
    rows = view.row_c2w
    if np.all(rows == rows[0]):
        R = rows[0, :3, :3].astype(np.float32)
        o = R @ src_cam + rows[0, :3, 3].astype(np.float32)
        for i in range(3):
            rays[:, i] = o[i]
            rays[:, 3 + i] = ((Lx * R[i, 0] + Ly * R[i, 1] + Lz * R[i, 2]) * scale)[mask]
    else:  # one pose per row (rolling shutter)
        H, W = mask.shape
        R = rows[:, :3, :3].astype(np.float32)                     # (H, 3, 3)
        o = np.einsum("hij,j->hi", R, src_cam) + rows[:, :3, 3].astype(np.float32)
        for i in range(3):
            rays[:, i] = np.broadcast_to(o[:, i:i + 1], (H, W))[mask]
            d = Lx * R[:, i, 0:1] + Ly * R[:, i, 1:2] + Lz * R[:, i, 2:3]
            rays[:, 3 + i] = (d * scale)[mask]
    occ = renderer.raycasting_scene.test_occlusions(o3d.core.Tensor.from_numpy(rays), tnear=np.float32(eps_m) / 10,
                                                    tfar=1.0, nthreads=_nthreads()).numpy()
    out[mask] = occ.astype(bool)
    return out


def scanline_shadow(up: np.ndarray, valid: np.ndarray, side: float, tol_px: float = 0.05) -> np.ndarray:
    """(H, W) bool projector shadow from the ordering of projector columns along each row.

    For a rectified rig with the projector at +x (``side`` > 0), the projector ray to pixel u
    is blocked iff some surface point seen further right (u' > u, towards the projector's
    epipole) has projector column u_p(u') <= u_p(u): that point lies on the ray between the
    projector and the surface. The running minimum of u_p from the right gives the test for
    all pixels at once. Pixels without a surface (``valid`` False) block nothing.
    """
    P = np.where(valid, up, np.float32(np.inf)).astype(np.float32)
    if side < 0:
        P = -P[:, ::-1]  # mirror: the projector is on the left, columns run the other way
    suffix = np.minimum.accumulate(P[:, ::-1], axis=1)[:, ::-1]
    nxt = np.full_like(P, np.inf)
    nxt[:, :-1] = suffix[:, 1:]
    shadow = P > nxt + np.float32(tol_px)
    if side < 0:
        shadow = shadow[:, ::-1]
    return shadow & valid


def compute_radiance(view, camera_offset_m, preset, pattern_blurred: np.ndarray, params: PatternProjectionParams,
                     renderer=None, ray_dirs_cam: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Radiance (H, W) float32 the camera at ``camera_offset_m`` (rig frame) receives from the
    projected pattern, and statistics.

    For each pixel's surface point X (camera frame): the vector from the projector L = X - p,
    distance r, the projector pixel (u_p, v_p) = f_p (L_x, L_y) / L_z + centre, the pattern
    value there (bilinear on the dot-blurred pattern; 0 outside the projector's field of view),
    the cosine of incidence cos_i = -n.L / r, visibility from the projector (shadow ray), and
    the reflectance towards the camera: a Lambertian part albedo (1 - s) plus a normalised
    Phong mirror lobe s (k + 2) / 2 cos^k(alpha), alpha the angle between the mirror direction
    of the projector ray and the direction to the camera (s = material specular weight). A
    shiny surface therefore sends the pattern away (dark, no match) except where the mirror
    direction hits the camera (saturation). Irradiance = pattern cos_i / r^2 (point source).
    """
    import cv2
    H, W = view.shape
    if ray_dirs_cam is None:
        raise ValueError("compute_radiance needs the camera's ray directions")
    xn, yn = normalized_coords(ray_dirs_cam)
    proj = np.asarray(preset.projector_offset_m, np.float32) - np.asarray(camera_offset_m, np.float32)
    hit = view.hit
    Z = np.where(hit, view.points_cam[..., 2], np.float32(0.0)).astype(np.float32)
    Lx = xn * Z - proj[0]
    Ly = yn * Z - proj[1]
    Lz = Z - proj[2]
    r2 = Lx * Lx + Ly * Ly + Lz * Lz
    r = np.sqrt(r2)
    hp, wp = pattern_blurred.shape
    fp = np.float32(preset.projector_focal_px)
    ok = hit & (Lz > 1e-4)
    invz = np.float32(1.0) / np.where(ok, Lz, np.float32(1.0))
    invz *= fp
    up = Lx * invz + np.float32((wp - 1) / 2.0)
    vp = Ly * invz + np.float32((hp - 1) / 2.0)
    up[~ok] = -10.0
    pat = cv2.remap(pattern_blurred, up, vp, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    n = view.normals_cam
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    mndl = -(nx * Lx + ny * Ly + nz * Lz)                       # = r cos_i
    lit = ok & (mndl > 0) & (pat > 0)
    stats = {"lit_px": int(np.count_nonzero(lit))}
    if params.shadow_rays and params.shadow_method == "scanline" and stats["lit_px"]:
        sh = scanline_shadow(up, ok, 1.0 if proj[0] >= 0 else -1.0) & lit
        lit &= ~sh
        stats["shadowed_px"] = int(np.count_nonzero(sh))
    elif params.shadow_rays and renderer is not None and stats["lit_px"]:
        sh = shadow_test(renderer, view, proj, Lx, Ly, Lz, r, lit, params.shadow_eps_m)
        lit &= ~sh
        stats["shadowed_px"] = int(np.count_nonzero(sh))
    rcube = np.maximum(r2 * r, np.float32(1e-12))
    E = pat * mndl
    E /= rcube
    E[~lit] = 0.0
    if params.power != 1.0:
        E *= np.float32(params.power)
    spec = view.specular
    refl = view.albedo * (np.float32(1.0) - spec)
    if np.any(spec[lit] > 0):
        # Phong lobe: mirror direction of the projector ray m = l - 2 (l.n) n (l = L / r, unit)
        # against the unit direction to the camera v = -X / |X|; cos(alpha) = m.v
        inv_r = np.float32(1.0) / np.maximum(r, np.float32(1e-9))
        lx, ly, lz = Lx * inv_r, Ly * inv_r, Lz * inv_r
        ln2 = np.float32(2.0) * (lx * nx + ly * ny + lz * nz)
        Xx, Xy = xn * Z, yn * Z
        inv_d = np.float32(-1.0) / np.maximum(np.sqrt(Xx * Xx + Xy * Xy + Z * Z), np.float32(1e-9))
        c = ((lx - ln2 * nx) * Xx + (ly - ln2 * ny) * Xy + (lz - ln2 * nz) * Z) * inv_d
        k = np.float32(params.specular_exponent)
        # the lobe matters only near the mirror direction: cos^k < 1e-4 elsewhere is skipped
        near = (c > np.float32(1e-4) ** (np.float32(1.0) / k)) & (spec > 0)
        refl = refl.copy()
        refl[near] += spec[near] * ((k + np.float32(2.0)) / np.float32(2.0)) * np.power(c[near], k)
    E *= refl
    return E.astype(np.float32, copy=False), stats


@register_effect
class PatternProjection(Effect):
    """Projector -> scene: the dot pattern's radiance at every pixel (physical pipeline).

    Physics: the projector (a laser + diffractive element) is a point source at
    ``preset.projector_offset_m`` whose radiant intensity is the pattern image seen through a
    pinhole of focal length ``preset.projector_focal_px``. The irradiance on a surface falls
    with the squared distance to the projector and with the cosine of the incidence angle,
    is zero where a shadow ray to the projector is blocked (projector shadows, on the side of
    foreground objects away from the projector), and is reflected towards the camera by the
    material (Lambertian albedo + a Phong mirror lobe). Writes ``state.radiance`` (and
    ``radiance_second`` for an active-stereo rig, casting the second camera's view).
    Approximations: single bounce, point-sampled pattern with a Gaussian dot spread instead of
    integrating each pixel's footprint, no projector vignetting.
    """

    name = "pattern_projection"
    Params = PatternProjectionParams
    FITTABLE = {"power": (0.05, 20.0), "dot_sigma_px": (0.0, 2.0), "specular_exponent": (1.0, 500.0)}
    stage = STAGE_PROJECTION
    physical = True
    in_reference = True

    def __init__(self, params=None, enabled=True):
        super().__init__(params, enabled)
        self._cache: dict = {}

    def validate(self) -> None:
        super().validate()
        if self.params.shadow_method not in ("raycast", "scanline"):
            from data_tools.errors import ConfigError
            raise ConfigError(f"effect 'pattern_projection': shadow_method must be 'raycast' or 'scanline', "
                              f"got {self.params.shadow_method!r}")

    def apply(self, state, draw) -> None:
        from synth.sensor.state import cast_view
        pattern = state.scratch["pattern"]
        pb = blurred_pattern(pattern, self.params.dot_sigma_px, self._cache)
        rad, stats = compute_radiance(state.view, (0.0, 0.0, 0.0), state.preset, pb, self.params,
                                      state.renderer, state.ray_dirs_cam)
        state.radiance = rad
        if state.preset.type == "active_stereo" and not state.is_reference:
            off = (state.preset.projector_side * state.preset.baseline_m, 0.0, 0.0)
            if state.second_view is None:
                if state.renderer is None:
                    from synth.sensor.state import empty_view
                    state.second_view = empty_view(state.shape)
                else:
                    state.second_view = cast_view(state.renderer, state.ray_dirs_cam, state.view.row_c2w, off)
            state.radiance_second, s2 = compute_radiance(state.second_view, off, state.preset, pb, self.params,
                                                         state.renderer, state.ray_dirs_cam)
            stats["second_lit_px"] = s2["lit_px"]
        state.log[self.name] = stats
