"""Physical stage 1: the virtual projector casts its dot pattern onto the scene."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.jit import kernel, n_threads, run_row_bands
from synth.sensor.registry import STAGE_PROJECTION, Effect, param, register_effect


@dataclass
class PatternProjectionParams:
    power: float = param(1.0, "1")
    """Projector radiant intensity scale: radiance 1 = a white Lambertian surface facing the
    projector at 1 m lit by pattern value 1."""
    dot_sigma_px: float = param(0.5, "px")
    """Gaussian spread of one projected dot, in pattern pixels (diffraction/defocus of the
    DOE; also the anti-aliasing filter of the point-sampled pattern)."""
    specular_exponent: float = param(40.0, "1")
    """Phong exponent of the mirror lobe (larger = tighter highlight)."""
    shadow_rays: bool = param(True, "")
    """Cast a shadow ray from every lit surface point to the projector (projector shadows)."""
    shadow_eps_m: float = param(0.002, "m", 0.0, 0.1)
    """Free gap at both ends of a shadow ray, metres (no self-shadowing)."""
    shadow_method: str = param("hybrid", "", choices=("hybrid", "raycast", "scanline"))
    """``raycast``: one shadow ray per lit pixel through the scene's RaycastingScene (exact);
    ``scanline``: the rectified-rig ordering test on the camera's own depth (a pixel is
    shadowed when a pixel farther towards the projector along its row maps to the same or an
    earlier projector column) - O(pixels), misses occluders the camera cannot see;
    ``hybrid`` (default): the scanline test for the part of each shadow ray inside the
    camera's field of view plus real shadow rays for the part outside it, cast only where that
    part is longer than the distance from the projector to the nearest scene surface - the
    same shadows as ``raycast`` up to pixel sampling at shadow boundaries (see
    :func:`hybrid_shadow`), at a fraction of the rays."""


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


def shadow_test(renderer, view, src_cam: np.ndarray, r, mask: np.ndarray, eps_m: float) -> np.ndarray:
    """(H, W) bool: True where the segment from the light source at ``src_cam`` (camera frame
    of ``view``, per row) to the surface point is blocked. ``r`` (H, W): distance from the
    source to the point, metres; only ``mask`` pixels are tested. Rays start at the source and
    stop ``eps_m`` before the surface (no self-shadowing); one Open3D occlusion query per
    pixel."""
    out = np.zeros(mask.shape, bool)
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return out
    rf = r.reshape(-1)[idx]
    frac = np.float32(1.0) - np.float32(eps_m) / np.maximum(rf, np.float32(2 * eps_m))
    out.reshape(-1)[idx] = _segment_occluded(renderer, view, src_cam, frac, idx, eps_m)
    return out


def _segment_occluded(renderer, view, src_cam, frac: np.ndarray, idx: np.ndarray, eps_m: float) -> np.ndarray:
    """(n,) bool: whether geometry lies on the segments from the source ``src_cam`` (camera
    frame, placed in the world by the pose of each pixel's row) towards the surface points of
    the flat pixel indices ``idx``, over the fraction ``frac`` (n,) of the way (ray parameter
    in [eps_m / 10, 1] of that part), by Open3D occlusion queries. Built from the view's world
    points, so a rolling-shutter view (one pose per row) costs the same as a global one."""
    import open3d as o3d
    rays = np.empty((len(idx), 6), np.float32)
    _segment_rays(np.ascontiguousarray(idx, np.int64), view.points_world.reshape(-1, 3),
                  view.cam_point_rows(src_cam).astype(np.float32), np.ascontiguousarray(frac, np.float32),
                  view.hit.shape[1], rays)
    occ = renderer.raycasting_scene.test_occlusions(o3d.core.Tensor.from_numpy(rays), tnear=np.float32(eps_m) / 10,
                                                    tfar=1.0, nthreads=n_threads()).numpy()
    return occ.astype(bool)


@kernel
def _segment_rays(idx, points_world, S, frac, W, rays):
    """Open3D rays (n, 6) of :func:`_segment_occluded`: origin the source ``S[row]`` (its
    pixel's row), direction ``frac`` x (surface point - source)."""
    for k in range(idx.shape[0]):
        i = idx[k]
        r = i // W
        for j in range(3):
            o = S[r, j]
            rays[k, j] = o
            rays[k, 3 + j] = (points_world[i, j] - o) * frac[k]


def hybrid_shadow(renderer, view, src_cam: np.ndarray, up: np.ndarray, ok: np.ndarray, xn: np.ndarray,
                  yn: np.ndarray, Lx, Lz, r, mask: np.ndarray, eps_m: float) -> tuple[np.ndarray, int]:
    """(H, W) bool projector shadow of the ``mask`` pixels and the number of shadow rays cast.

    The same shadows as :func:`shadow_test` (one exact ray per pixel) with far fewer rays, by
    ruling out most pixels with a necessary condition. Rectified rig: the source S at
    ``src_cam`` = (+-b, 0, 0) in the camera frame of each row, camera centre C. The shadow ray
    of pixel p in row v runs from S to its surface point X inside the epipolar plane of row v
    (the plane through the baseline and X; every point of it projects into row v). If a surface
    crosses the segment S-X at Y and the camera ray of Y lies inside the image, the first
    surface Z on the segment C-Y (Y itself or a nearer one) lies inside the triangle C-S-X, so
    the camera sees it in row v on the source's side of p at a projector column <= that of X:
    the :func:`scanline_shadow` ordering test is true. So every pixel for which that test is
    false is lit, as far as occluders inside the field of view go; the test is not sufficient
    (a thin object inside the triangle need not cross S-X), so every pixel it marks gets an
    exact shadow ray. Sampling: the test sees the surfaces only at pixel centres, so an
    occluder's outline can lie up to a pixel beyond its last sample; pixels within two columns
    (away from the source) of a marked pixel or of a nearer surface (inverse depth above the
    linear extrapolation of the pixel's own surface - planes never trigger) get an exact ray
    too. The part of each segment outside the field of view, from S to the plane through the
    outermost pixel column on the source's side (a fraction s* = |S_x| / (|S_x| + g) of it, g =
    the horizontal distance of X from that plane), is tested with a real shadow ray, but only
    where its length s* r exceeds the distance from S to the nearest scene surface
    (``RaycastingScene.compute_distance``: nothing nearer can block it); in a room that leaves
    the pixels within some dozens of columns of the image border on the source's side (whole
    columns farther from it are skipped with a bound on s* r). ``xn``, ``yn``: (H, W) x/z and
    y/z of each pixel's ray.
    Remaining difference to :func:`shadow_test`: an occluder visible over less than one pixel
    spacing of the row (no sample on it) that casts a shadow away from any sampled edge.
    Falls back to :func:`shadow_test` when the source is off the camera's x axis.
    """
    import open3d as o3d
    src_cam = np.asarray(src_cam, np.float32)
    if abs(float(src_cam[1])) > 1e-9 or abs(float(src_cam[2])) > 1e-9 or float(src_cam[0]) == 0.0:
        sh = shadow_test(renderer, view, src_cam, r, mask, eps_m)
        return sh, int(np.count_nonzero(mask))
    side = 1.0 if src_cam[0] > 0 else -1.0
    H, W = mask.shape
    exact = np.empty((H, W), np.bool_)
    run_row_bands(lambda r0, r1: _hybrid_marks_rows(r0, r1, up, ok, Lz, float(src_cam[2]), mask, side, exact),
                  H, n_threads())
    n_exact = int(np.count_nonzero(exact))
    sh = shadow_test(renderer, view, src_cam, r, exact, eps_m) if n_exact else np.zeros(mask.shape, bool)
    rest = mask & ~exact
    if not rest.any():
        return sh, n_exact
    # distance from the source (per row pose; one pose for a global shutter) to the nearest surface
    pw = view.cam_point_rows(src_cam).astype(np.float32)
    if view.global_shutter:
        pw = pw[:1]
    dmin_rows = renderer.raycasting_scene.compute_distance(
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(pw)), nthreads=n_threads()).numpy().astype(np.float64)
    # the out-of-view part of a shadow ray from S: from S to the plane x = x_edge z, a fraction
    # s* = b / (b + g) of it, g = side (x_edge Z - X) >= 0. Columns where even the longest such
    # part is shorter than dmin are skipped: s* r <= b (Z m + b) / (b + Z d) with d = side
    # (x_edge - x/z) and m = |(x/z, y/z, 1)| <= m_max, which is < dmin whenever
    # d >= b m_max / dmin (b < dmin)
    bx = abs(float(src_cam[0]))
    x_edge = float(xn[0, -1] if side > 0 else xn[0, 0])
    dmin_all = float(dmin_rows.min())
    d_col = side * (x_edge - xn[0].astype(np.float64))                 # (W,) >= 0
    if bx < dmin_all - eps_m:
        m_max = float(np.sqrt(1.0 + np.max(xn[0].astype(np.float64) ** 2) + np.max(yn[:, 0].astype(np.float64) ** 2)))
        cols = np.flatnonzero(d_col < bx * m_max / (dmin_all - eps_m) * (1.0 + 1e-6) + 1e-9)
    else:
        cols = np.arange(W)
    n = 0
    if len(cols):
        c0, c1 = int(cols.min()), int(cols.max()) + 1
        sub = rest[:, c0:c1]
        idx2 = np.flatnonzero(sub)
        if len(idx2):
            wsub = c1 - c0
            idx = (idx2 // wsub) * W + c0 + idx2 % wsub                # flat indices in the full image
            Lxf, Lzf, rf = (a.reshape(-1)[idx] for a in (Lx, Lz, r))
            Zf = Lzf + src_cam[2]
            Xf = Lxf + src_cam[0]
            g = (np.float32(x_edge) * Zf - Xf) if side > 0 else (Xf - np.float32(x_edge) * Zf)
            b32 = np.float32(bx)
            s_star = b32 / (b32 + np.maximum(g, np.float32(0.0)))
            dmin = dmin_rows.astype(np.float32)
            dmin = dmin[idx // W] if len(dmin) > 1 else dmin[0]
            sel = s_star * rf >= dmin - np.float32(eps_m)
            n = int(np.count_nonzero(sel))
            if n:
                # the out-of-view part only: scale the segment to s* (and keep the eps gap at X)
                seg = np.minimum(s_star[sel], np.float32(1.0) - np.float32(eps_m)
                                 / np.maximum(rf[sel], np.float32(2 * eps_m)))
                occ = _segment_occluded(renderer, view, src_cam, seg, idx[sel], eps_m)
                sh.reshape(-1)[idx[sel][occ]] = True
    return sh, n + n_exact


def scanline_shadow(up: np.ndarray, valid: np.ndarray, side: float, tol_px: float = 0.05) -> np.ndarray:
    """(H, W) bool projector shadow from the ordering of projector columns along each row.

    For a rectified rig with the projector at +x (``side`` > 0), the projector ray to pixel u
    is blocked iff some surface point seen further right (u' > u, towards the projector's
    epipole) has projector column u_p(u') <= u_p(u): that point lies on the ray between the
    projector and the surface. The running minimum of u_p from the right gives the test for
    all pixels at once. Pixels without a surface (``valid`` False) block nothing.
    """
    # mirrored when the projector is on the left (columns run the other way); pixels without a
    # surface get +inf after the sign flip (before it, they became -inf and shadowed the row)
    P = np.where(valid, up if side > 0 else -up, np.float32(np.inf)).astype(np.float32)
    if side < 0:
        P = P[:, ::-1]
    suffix = np.minimum.accumulate(P[:, ::-1], axis=1)[:, ::-1]
    nxt = np.full_like(P, np.inf)
    nxt[:, :-1] = suffix[:, 1:]
    shadow = P > nxt + np.float32(tol_px)
    if side < 0:
        shadow = shadow[:, ::-1]
    return shadow & valid


def compute_radiance(view, camera_offset_m, preset, pattern_blurred: np.ndarray, params: PatternProjectionParams,
                     renderer=None, ray_dirs_cam: np.ndarray | None = None, shadow_mask: np.ndarray | None = None,
                     out: dict | None = None) -> tuple[np.ndarray, dict]:
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
    ``shadow_mask``: (H, W) bool projector shadows to use instead of testing them (a nearby view's,
    carried over); ``out``: a dict that receives the shadow mask used (``"shadow"``, None when
    shadows are off) and, when it has the key ``"shading"``, the radiance per unit pattern value
    (H, W) float32 (the radiance for a pattern value of 1 wherever the surface faces the projector
    and is not shadowed, 0 elsewhere: fall-off, incidence, material and shadow of each pixel).
    """
    H, W = view.shape
    if ray_dirs_cam is None:
        raise ValueError("compute_radiance needs the camera's ray directions")
    if ray_dirs_cam.shape != (H, W, 3):
        raise ValueError(f"compute_radiance: ray directions {ray_dirs_cam.shape} do not match the view {(H, W)}")
    xn, yn = normalized_coords(ray_dirs_cam)
    proj = np.asarray(preset.projector_offset_m, np.float64) - np.asarray(camera_offset_m, np.float64)
    hit = np.ascontiguousarray(view.hit)
    Z = np.ascontiguousarray(view.points_cam[..., 2])
    nrm = np.ascontiguousarray(view.normals_cam, np.float32)
    hp, wp = pattern_blurred.shape
    fp = float(preset.projector_focal_px)
    Lx, Ly, Lz, r, up = (np.empty((H, W), np.float32) for _ in range(5))
    pat, mndl = np.empty((H, W), np.float32), np.empty((H, W), np.float32)
    ok, lit = np.empty((H, W), np.bool_), np.empty((H, W), np.bool_)
    nthreads = n_threads()
    run_row_bands(lambda r0, r1: _projection_rows(
        r0, r1, Z, hit, xn, yn, nrm, pattern_blurred, proj[0], proj[1], proj[2], fp, (wp - 1) / 2.0,
        (hp - 1) / 2.0, Lx, Ly, Lz, r, up, ok, pat, mndl, lit), H, nthreads)
    stats = {"lit_px": int(np.count_nonzero(lit))}
    sh = None
    if params.shadow_rays and shadow_mask is not None:
        sh = np.asarray(shadow_mask, bool) & lit
        lit &= ~sh
        stats["shadowed_px"] = int(np.count_nonzero(sh))
    elif params.shadow_rays and stats["lit_px"]:
        if params.shadow_method == "scanline":
            sh = scanline_shadow(up, ok, 1.0 if proj[0] >= 0 else -1.0) & lit
        elif params.shadow_method == "hybrid" and renderer is not None:
            sh, stats["shadow_rays"] = hybrid_shadow(renderer, view, proj.astype(np.float32), up, ok, xn, yn, Lx,
                                                     Lz, r, lit, params.shadow_eps_m)
        elif renderer is not None:
            sh = shadow_test(renderer, view, proj, r, lit, params.shadow_eps_m)
        if sh is not None:
            lit &= ~sh
            stats["shadowed_px"] = int(np.count_nonzero(sh))
    if out is not None:
        out["shadow"] = sh
    E = np.empty((H, W), np.float32)
    k = float(params.specular_exponent)
    # the shading (radiance for a pattern value of 1) wherever the surface faces the projector
    # unshadowed, between the dots too: the dots of a moving frame's sub-exposures move there
    want_g = out is not None and "shading" in out
    G = np.empty((H, W) if want_g else (1, 1), np.float32)
    shm = sh if sh is not None else np.zeros((1, 1), np.bool_)
    run_row_bands(lambda r0, r1: _radiance_rows(
        r0, r1, lit, pat, mndl, Lx, Ly, Lz, r, xn, yn, Z, nrm, np.ascontiguousarray(view.albedo, np.float32),
        np.ascontiguousarray(view.specular, np.float32), float(params.power), k, 1e-4 ** (1.0 / k), E,
        want_g, ok, shm, sh is not None, G), H, nthreads)
    if want_g:
        out["shading"] = G
    return E, stats


@kernel
def _projection_rows(r0, r1, Z, hit, xn, yn, nrm, pattern, px, py, pz, fp, cxp, cyp,
                     Lx, Ly, Lz, r, up, ok, pat, mndl, lit):
    """Rows [r0, r1) of the projector geometry of every pixel (see :func:`compute_radiance`):
    L = X - p and |L| (camera frame, metres), the projector column u_p (-10 where the point is
    not in front of the projector), the bilinearly sampled pattern (0 outside it), n.L sign
    flipped (= r cos_i) and the lit mask before shadows."""
    hp, wp = pattern.shape
    W = Z.shape[1]
    for v in range(r0, r1):
        for u in range(W):
            z = Z[v, u] if hit[v, u] else 0.0
            lx = xn[v, u] * z - px
            ly = yn[v, u] * z - py
            lz = z - pz
            rr = np.sqrt(lx * lx + ly * ly + lz * lz)
            Lx[v, u] = lx
            Ly[v, u] = ly
            Lz[v, u] = lz
            r[v, u] = rr
            o = hit[v, u] and lz > 1e-4
            ok[v, u] = o
            p = 0.0
            if o:
                uu = lx * (fp / lz) + cxp
                vv = ly * (fp / lz) + cyp
                up[v, u] = uu
                x0 = np.floor(uu)
                y0 = np.floor(vv)
                i = int(x0)
                j = int(y0)
                fx = uu - x0
                fy = vv - y0
                if -1 <= i < wp and -1 <= j < hp:  # bilinear, zero outside the pattern
                    p00 = pattern[j, i] if (i >= 0 and j >= 0) else 0.0
                    p01 = pattern[j, i + 1] if (i + 1 < wp and j >= 0) else 0.0
                    p10 = pattern[j + 1, i] if (i >= 0 and j + 1 < hp) else 0.0
                    p11 = pattern[j + 1, i + 1] if (i + 1 < wp and j + 1 < hp) else 0.0
                    p = (p00 * (1.0 - fx) + p01 * fx) * (1.0 - fy) + (p10 * (1.0 - fx) + p11 * fx) * fy
            else:
                up[v, u] = -10.0
            pat[v, u] = p
            m = -(nrm[v, u, 0] * lx + nrm[v, u, 1] * ly + nrm[v, u, 2] * lz)
            mndl[v, u] = m
            lit[v, u] = o and m > 0.0 and p > 0.0


@kernel
def _radiance_rows(r0, r1, lit, pat, mndl, Lx, Ly, Lz, r, xn, yn, Z, nrm, albedo, spec, power, k, thr, E,
                   want_g, ok, shadow, use_shadow, G):
    """Rows [r0, r1) of the reflected radiance (see :func:`compute_radiance`): irradiance
    pattern cos_i / r^2 times (Lambertian albedo (1 - s) + Phong lobe s (k + 2) / 2 cos^k alpha,
    the lobe only where cos^k alpha >= 1e-4, i.e. cos alpha > ``thr``). ``want_g``: also the
    same for a pattern value of 1 into ``G`` wherever ``ok``, -n.L > 0 and not ``shadow`` (when
    ``use_shadow``), 0 elsewhere."""
    W = lit.shape[1]
    for v in range(r0, r1):
        for u in range(W):
            g_on = want_g and ok[v, u] and mndl[v, u] > 0.0 and not (use_shadow and shadow[v, u])
            if want_g and not g_on:
                G[v, u] = 0.0
            if not (lit[v, u] or g_on):
                E[v, u] = 0.0
                continue
            rr = r[v, u]
            s = spec[v, u]
            refl = albedo[v, u] * (1.0 - s)
            if s > 0.0:
                # mirror direction of the unit projector ray l: m = l - 2 (l.n) n, against the
                # unit direction from the point to the camera -X / |X|
                inv_r = 1.0 / max(rr, 1e-9)
                lx = Lx[v, u] * inv_r
                ly = Ly[v, u] * inv_r
                lz = Lz[v, u] * inv_r
                nx = nrm[v, u, 0]
                ny = nrm[v, u, 1]
                nz = nrm[v, u, 2]
                ln2 = 2.0 * (lx * nx + ly * ny + lz * nz)
                z = Z[v, u]
                X = xn[v, u] * z
                Y = yn[v, u] * z
                inv_d = -1.0 / max(np.sqrt(X * X + Y * Y + z * z), 1e-9)
                c = ((lx - ln2 * nx) * X + (ly - ln2 * ny) * Y + (lz - ln2 * nz) * z) * inv_d
                if c > thr:
                    refl += s * (k + 2.0) / 2.0 * c ** k
            E[v, u] = pat[v, u] * mndl[v, u] / max(rr * rr * rr, 1e-12) * power * refl if lit[v, u] else 0.0
            if g_on:
                G[v, u] = mndl[v, u] / max(rr * rr * rr, 1e-12) * power * refl


@kernel
def _hybrid_marks_rows(r0, r1, up, ok, Lz, src_z, mask, side, exact):
    """Rows [r0, r1) of the pixels :func:`hybrid_shadow` must settle with an exact ray: the
    ``mask`` pixels that the ordering test (:func:`scanline_shadow`, tolerance 0.05 px) marks,
    or that lie within two columns (away from the source) of a marked pixel or of a nearer
    surface (inverse depth above the linear extrapolation of the pixel's own surface, with a
    0.2 % margin). Columns are walked in the mirrored order when the source is at -x."""
    W = up.shape[1]
    inf = np.inf
    mk = np.empty(W, np.bool_)
    iz = np.empty(W)
    okm = np.empty(W, np.bool_)
    for v in range(r0, r1):
        # j: column index with the source at +x (mirrored when it is at -x)
        run = inf
        for j in range(W - 1, -1, -1):
            u = j if side > 0 else W - 1 - j
            P = (up[v, u] if side > 0 else -up[v, u]) if ok[v, u] else inf
            mk[j] = ok[v, u] and mask[v, u] and P > run + 0.05
            run = min(run, P)
            okm[j] = ok[v, u]
            iz[j] = 1.0 / (Lz[v, u] + src_z) if ok[v, u] else 0.0
        for j in range(W):
            u = j if side > 0 else W - 1 - j
            if not mask[v, u]:
                exact[v, u] = False
                continue
            near = mk[j]
            slope = iz[j] - iz[j - 1] if (j > 0 and okm[j - 1]) else 0.0
            tol = iz[j] * 1.002
            for kk in range(1, 3):
                if near or j + kk >= W:
                    break
                near = mk[j + kk] or (okm[j + kk] and iz[j + kk] > tol + kk * slope)
            exact[v, u] = near


@register_effect
class PatternProjection(Effect):
    """Projector -> scene: the dot pattern's radiance at every pixel (physical pipeline).

    Physics: the projector (a laser + diffractive element) is a point source at
    ``preset.projector_offset_m`` whose radiant intensity is the pattern image seen through a
    pinhole of focal length ``preset.projector_focal_px``. The irradiance on a surface falls
    with the squared distance to the projector and with the cosine of the incidence angle,
    is zero where a shadow ray to the projector is blocked (projector shadows, on the side of
    foreground objects away from the projector; ``shadow_method`` ``hybrid`` gives the shadows
    of one exact ray per pixel while casting only the rays an ordering test cannot settle,
    see :func:`hybrid_shadow`), and is reflected towards the camera by the
    material (Lambertian albedo + a Phong mirror lobe). Writes ``state.radiance`` (and
    ``radiance_second`` for an active-stereo rig, casting the second camera's view).
    Approximations: single bounce, point-sampled pattern with a Gaussian dot spread instead of
    integrating each pixel's footprint, no projector vignetting.
    """

    name = "pattern_projection"
    REQUIRED_IN_PIPELINE = True
    Params = PatternProjectionParams
    FITTABLE = {"power": (0.05, 20.0), "dot_sigma_px": (0.0, 2.0), "specular_exponent": (1.0, 500.0)}
    stage = STAGE_PROJECTION
    physical = True
    in_reference = True

    def __init__(self, params=None, enabled=True):
        super().__init__(params, enabled)
        self._cache: dict = {}

    def apply(self, state, draw) -> None:
        from synth.sensor.state import cast_view
        pb = blurred_pattern(state.pattern, self.params.dot_sigma_px, self._cache)
        from synth.sensor.state import ProjectorProduct
        state.publish("projector", ProjectorProduct(pb, self.params))
        # a moving frame's sub-exposures (motion_blur) reuse the shading of this view
        sh: dict = {"shading": None} if state.frame.moving and not state.is_reference else {}
        rad, stats = compute_radiance(state.view, (0.0, 0.0, 0.0), state.preset, pb, self.params,
                                      state.renderer, state.ray_dirs_cam, out=sh)
        state.radiance = rad
        if sh.get("shadow") is not None:
            state.publish("projector_shadow", sh["shadow"])
        if sh.get("shading") is not None:
            state.publish("projector_shading", sh["shading"])
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
