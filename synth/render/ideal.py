"""Ideal (noise-free) RGB-D rendering of a :class:`SceneSpec` by ray casting.

:class:`IdealRenderer` wraps one ``open3d.t.geometry.RaycastingScene`` (Embree BVH) built
from the scene's meshes and renders, for a camera-to-world pose (OpenCV axes: x right,
y down, z forward) and pinhole :class:`Intrinsics`:

* exact z-depth, hit mask, world points, ray lengths and unit ray directions,
* per-pixel camera-frame normals (flat triangle normals, flipped to face the camera),
* instance ids (``k + 1`` for ``scene.meshes[k]``, 0 = no hit),
* a simple shaded RGB (:func:`shade_rgb`).

Two interchangeable back-ends compute the per-pixel first hits of :meth:`IdealRenderer.render`:
``"raster"`` (default; :mod:`synth.raster`, an exact numba rasteriser: the same hits as a
ray cast, ~6x less CPU for a furnished room) and ``"raycast"`` (Open3D's Embree ray cast, the
reference the tests compare the rasteriser with). Both give the same depth to float32
rounding and the same triangles except at edges passing within ~1e-7 px of a pixel centre.

It is also the geometry service of the sensor simulators built on top of it (synth/sensor):
:meth:`IdealRenderer.cast_rays` for arbitrary rays, :meth:`IdealRenderer.occluded` for
shadow rays (projector visibility), :meth:`IdealRenderer.albedo_specular` for material
look-ups, and the public ``raycasting_scene`` for anything else.

Conventions, fixed for every caller:

* pixel centres are at integer coordinates; the ray of pixel (u, v) goes through
  ((u - cx) / fx, (v - cy) / fy, 1) in the camera frame (normalised to unit length);
* lens distortion in ``Intrinsics.distortion`` is ignored: images are rendered undistorted,
  which is how realgap stores depth (see :func:`data_tools.geometry.unproject`);
* no near/far clipping: every intersection at t > 0 counts (a sensor model applies its own
  range limits);
* float32 ray casting: points are exact to ~1e-7 relative (well below 0.1 mm in a room).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.jit import kernel, n_threads

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError
from data_tools.geometry import pixel_rays
from data_tools.scene_spec import SceneSpec

AMBIENT = 0.3
"""Ambient share of the shaded RGB (the rest is Lambert from a light at the camera centre)."""

OCCLUSION_EPS_M = 1e-3
"""Default gap (metres) left free at both ends of a shadow ray so the surfaces the ray starts
or ends on do not count as occluders."""


def build_raycasting_scene(scene: SceneSpec):
    """An ``open3d.t.geometry.RaycastingScene`` holding every mesh of ``scene``.

    Returns (raycasting_scene, geometry_to_mesh) where ``geometry_to_mesh[g]`` is the index k
    in ``scene.meshes`` of Open3D geometry id g.
    """
    import open3d as o3d
    if not scene.meshes:
        raise RealgapError("cannot render a scene without meshes")
    rs = o3d.t.geometry.RaycastingScene()
    gid_to_mesh = []
    for k, m in enumerate(scene.meshes):
        if len(m.triangles) == 0:
            raise RealgapError(f"mesh {m.name!r} has no triangles")
        g = rs.add_triangles(o3d.core.Tensor(np.ascontiguousarray(m.vertices, dtype=np.float32)),
                             o3d.core.Tensor(np.ascontiguousarray(m.triangles, dtype=np.uint32)))
        if g != len(gid_to_mesh):  # Open3D numbers geometries 0, 1, 2, ... in insertion order
            raise RealgapError(f"unexpected Open3D geometry id {g} for mesh {k}")
        gid_to_mesh.append(k)
    return rs, np.asarray(gid_to_mesh, dtype=np.int64)


def pinhole_ray_dirs(intr: Intrinsics) -> np.ndarray:
    """(H, W, 3) float32 unit ray directions in the camera frame (pixel centres at integers;
    :func:`data_tools.geometry.pixel_rays`)."""
    return pixel_rays(intr).astype(np.float32)


@dataclass
class RenderResult:
    """One ideal RGB-D view. Arrays are (H, W, ...) in image layout (row v, column u)."""

    depth: np.ndarray
    """(H, W) float32 z-depth along the optical axis, metres; 0 where no hit."""
    hit: np.ndarray
    """(H, W) bool, True where the pixel's ray hits geometry."""
    points_world: np.ndarray
    """(H, W, 3) float32 hit points in the world frame, metres; 0 where no hit."""
    normals_cam: np.ndarray
    """(H, W, 3) float32 unit surface normals in the camera frame, facing the camera
    (dot(normal, ray_dir) <= 0); 0 where no hit. Flat per-triangle normals."""
    instance_ids: np.ndarray
    """(H, W) int32: k + 1 for ``scene.meshes[k]``, 0 = no hit."""
    ray_dirs_cam: np.ndarray
    """(H, W, 3) float32 unit ray directions in the camera frame (same for every pose; a
    read-only array shared between renders - copy it before modifying)."""
    t_hit: np.ndarray
    """(H, W) float32 ray length from the camera centre to the hit, metres; inf where no hit.
    ``depth == t_hit * ray_dirs_cam[..., 2]`` on hits."""
    rgb: np.ndarray | None
    """(H, W, 3) uint8 shaded colour (:func:`shade_rgb`); black where no hit; None when
    rendered with ``with_rgb=False``."""
    points_cam_data: np.ndarray | None = None
    """(H, W, 3) float32 camera-frame hit points when the back-end computed them (raster);
    None: :attr:`points_cam` derives them from the rays."""

    @property
    def points_cam(self) -> np.ndarray:
        """(H, W, 3) float32 hit points in the camera frame, metres; 0 where no hit."""
        if self.points_cam_data is not None:
            return self.points_cam_data
        t = np.where(self.hit, self.t_hit, 0.0).astype(np.float32)
        return self.ray_dirs_cam * t[..., None]


def shade_rgb(base_color: np.ndarray, normals_cam: np.ndarray, ray_dirs_cam: np.ndarray,
              hit: np.ndarray, ambient: float = AMBIENT) -> np.ndarray:
    """Head-light Lambert shading: ``color * (ambient + (1 - ambient) * cos)``.

    ``cos`` is the cosine between the camera-facing normal and the reversed ray (the light is
    at the camera centre, no distance fall-off, no shadows, no specular highlight). Inputs are
    (..., 3) float colours in [0, 1], normals and unit rays; returns uint8, black where
    ``hit`` is False. A deliberately simple model: good enough for RGB odometry features and
    for looking at the scene, not a photometric simulation.
    """
    cos = -np.einsum("...k,...k->...", normals_cam, ray_dirs_cam)
    return _shade(np.asarray(base_color, np.float32), cos.astype(np.float32), hit, ambient)


def _shade(base_color: np.ndarray, cos: np.ndarray, hit: np.ndarray, ambient: float = AMBIENT) -> np.ndarray:
    """:func:`shade_rgb` given the cosines (..., ) directly."""
    f = np.clip(cos, 0.0, 1.0)
    f *= np.float32(255.0 * (1.0 - ambient))
    f += np.float32(255.0 * ambient)
    f[~hit] = 0.0
    rgb = base_color * f[..., None]
    rgb += 0.5
    np.clip(rgb, 0, 255, out=rgb)
    return rgb.astype(np.uint8)


class IdealRenderer:
    """Noise-free ray-cast renderer of one :class:`SceneSpec` (see the module docstring).

    Build it once per scene and call :meth:`render` per pose (the BVH is built on the first
    query). Ray directions are cached per :class:`Intrinsics`; the cached array is shared,
    read-only, by every :class:`RenderResult` of those intrinsics (``ray_dirs_cam``).
    """

    def __init__(self, scene: SceneSpec, backend: str = "auto"):
        self.scene = scene
        """The scene being rendered (meshes must not be modified afterwards)."""
        if backend not in ("auto", "raster", "raycast"):
            raise RealgapError(f"renderer backend must be 'auto', 'raster' or 'raycast', got {backend!r}")
        from synth.render import raster
        if backend == "auto":
            backend = "raster" if raster.available() else "raycast"
        elif backend == "raster" and not raster.available():
            raise RealgapError("renderer backend 'raster' needs numba, which is not installed (use 'raycast')")
        self.backend = backend
        """How :meth:`render` finds the first hits: ``"raster"`` (synth.raster) or
        ``"raycast"`` (Open3D); every other query uses the Open3D scene."""
        rs, gid_to_mesh = build_raycasting_scene(scene)
        self._raster = raster.Rasterizer([(m.vertices, m.triangles) for m in scene.meshes]) \
            if backend == "raster" else None
        self.raycasting_scene = rs
        """The ``open3d.t.geometry.RaycastingScene`` of all meshes (geometry id g ->
        ``scene.meshes[geometry_to_mesh[g]]``)."""
        self.geometry_to_mesh = gid_to_mesh
        """(G,) int64 mesh index of each Open3D geometry id."""
        # geometry id -> instance id, with one extra slot (value 0) for INVALID_ID hits
        self._gid_to_instance = np.zeros(len(gid_to_mesh) + 1, dtype=np.int32)
        self._gid_to_instance[:-1] = gid_to_mesh + 1
        mats = [scene.material_of(m) for m in scene.meshes]
        self._albedo = np.array([0.0] + [m.albedo for m in mats], dtype=np.float32)
        self._specular = np.array([0.0] + [m.specular for m in mats], dtype=np.float32)
        # per-triangle vertex colours of all meshes, concatenated: (F_total, 3 corners, 3) float32
        offs, cols = [0], []
        for m, mat in zip(scene.meshes, mats):
            if m.vertex_colors is not None and len(m.vertex_colors) == len(m.vertices):
                vc = np.clip(np.asarray(m.vertex_colors, dtype=np.float32), 0.0, 1.0)
            else:  # no colours: a grey of the material's albedo
                vc = np.full((len(m.vertices), 3), mat.albedo, dtype=np.float32)
            cols.append(vc[m.triangles])
            offs.append(offs[-1] + len(m.triangles))
        self._tri_colors = np.concatenate(cols)
        # the same as contiguous per-channel columns: corner-0 colour and corner differences
        tc = self._tri_colors
        self._col_stack = None
        self._col_c0 = [np.ascontiguousarray(tc[:, 0, ch]) for ch in range(3)]
        self._col_d1 = [np.ascontiguousarray(tc[:, 1, ch] - tc[:, 0, ch]) for ch in range(3)]
        self._col_d2 = [np.ascontiguousarray(tc[:, 2, ch] - tc[:, 0, ch]) for ch in range(3)]
        self._tri_offset = np.asarray(offs[:-1] + [0], dtype=np.int64)  # last slot for INVALID_ID
        self._ray_cache: dict[Intrinsics, tuple[np.ndarray, list[np.ndarray]]] = {}

    # ------------------------------------------------------------------ helpers
    @property
    def n_meshes(self) -> int:
        return len(self.scene.meshes)

    def ray_dirs_cam(self, intr: Intrinsics) -> np.ndarray:
        """(H, W, 3) float32 unit camera-frame ray directions of ``intr`` (cached)."""
        return self._rays(intr)[0]

    def _rays(self, intr: Intrinsics) -> tuple[np.ndarray, list[np.ndarray]]:
        """((H, W, 3) unit directions, [dx, dy, dz] as contiguous (H*W,) float32 columns)."""
        hit = self._ray_cache.get(intr)
        if hit is None:
            d = pinhole_ray_dirs(intr)
            d.setflags(write=False)  # shared by every RenderResult of these intrinsics
            hit = (d, [np.ascontiguousarray(d[..., k].reshape(-1)) for k in range(3)])
            self._ray_cache[intr] = hit
        return hit

    def _gid_index(self, gid: np.ndarray) -> np.ndarray:
        """Map Open3D geometry ids (uint32, INVALID_ID for misses) to 0..G (G = miss slot)."""
        return np.minimum(gid, len(self.geometry_to_mesh)).astype(np.intp, copy=False)

    def _cast(self, rays: np.ndarray) -> dict:
        import open3d as o3d
        out = self.raycasting_scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=n_threads())
        return {k: v.numpy() for k, v in out.items()}

    # ------------------------------------------------------------------ rendering
    def render(self, pose_c2w: np.ndarray, intr: Intrinsics, with_rgb: bool = True) -> RenderResult:
        """Render the view of a camera at ``pose_c2w`` (4x4 camera-to-world, OpenCV axes).

        Returns a :class:`RenderResult` with (H, W) = ``intr.shape``.
        """
        # Implementation note: all per-pixel work is element-wise float32 numpy on contiguous
        # (N,) columns. 3x3 products are written out by hand: a BLAS matmul on (N, 3) arrays is
        # no faster and, with BLAS threads competing with Open3D's, was up to 10x slower.
        T = np.asarray(pose_c2w, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise RealgapError(f"render: pose must be a finite 4x4 matrix, got shape {T.shape}")
        H, W = intr.shape
        dirs_img, d = self._rays(intr)
        if self._raster is not None:
            return self._render_raster(T, intr, dirs_img, d, with_rgb)
        R = [[np.float32(x) for x in row] for row in T[:3, :3]]
        o = [np.float32(x) for x in T[:3, 3]]
        N = H * W
        rays = np.empty((N, 6), dtype=np.float32)
        for i in range(3):
            rays[:, i] = o[i]
            rays[:, 3 + i] = d[0] * R[i][0] + d[1] * R[i][1] + d[2] * R[i][2]
        out = self._cast(rays)
        t = out["t_hit"]
        hit = np.isfinite(t)
        t0 = np.where(hit, t, np.float32(0.0))
        depth = t0 * d[2]
        points = np.empty((N, 3), dtype=np.float32)
        for i in range(3):
            np.multiply(rays[:, 3 + i], t0, out=points[:, i])
            points[:, i] += o[i]
        points[~hit] = 0.0
        gi = self._gid_index(out["geometry_ids"])
        inst = self._gid_to_instance[gi]
        # world normals -> camera frame (n_cam = R^T n_world), flipped to face the camera
        pn = out["primitive_normals"]
        nw = [np.ascontiguousarray(pn[:, k]) for k in range(3)]
        nc = [nw[0] * R[0][j] + nw[1] * R[1][j] + nw[2] * R[2][j] for j in range(3)]
        facing = nc[0] * d[0] + nc[1] * d[1] + nc[2] * d[2]  # cos between normal and ray
        sign = np.where(facing > 0, np.float32(-1.0), np.float32(1.0))
        sign[~hit] = 0.0
        n_cam = np.empty((N, 3), dtype=np.float32)
        for j in range(3):
            np.multiply(nc[j], sign, out=n_cam[:, j])
        rgb = None
        if with_rgb:
            tri = self._tri_offset[gi] + np.where(hit, out["primitive_ids"], 0)
            uv = out["primitive_uvs"]
            rgb = self._vertex_colour_rgb(tri, np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1]),
                                          facing, hit).reshape(H, W, 3)
        return RenderResult(
            depth=depth.reshape(H, W),
            hit=hit.reshape(H, W),
            points_world=points.reshape(H, W, 3),
            normals_cam=n_cam.reshape(H, W, 3),
            instance_ids=inst.reshape(H, W),
            ray_dirs_cam=dirs_img,
            t_hit=t.reshape(H, W),
            rgb=rgb,
        )

    def _render_raster(self, T: np.ndarray, intr: Intrinsics, dirs_img: np.ndarray, d: list[np.ndarray],
                       with_rgb: bool) -> RenderResult:
        """:meth:`render` through :class:`synth.render.raster.Rasterizer` (same outputs)."""
        H, W = intr.shape
        o = self._raster.render(T, intr.fx, intr.fy, intr.cx, intr.cy, W, H, d[2].reshape(H, W),
                                with_uv=with_rgb, n_threads=n_threads())
        rgb = None
        if with_rgb:
            hit = o["hit"].reshape(-1)
            tri = np.where(hit, o["triangle"].reshape(-1), 0)
            uv = o["uv"].reshape(-1, 2)
            nc = o["normals_cam"].reshape(-1, 3)
            rgb = self._vertex_colour_rgb(tri, np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1]),
                                          None, hit, nc, d).reshape(H, W, 3)
        return RenderResult(depth=o["depth"], hit=o["hit"], points_world=o["points_world"],
                            normals_cam=o["normals_cam"], instance_ids=o["instance_ids"], ray_dirs_cam=dirs_img,
                            t_hit=o["t_hit"], rgb=rgb, points_cam_data=o["points_cam"])

    def _vertex_colour_rgb(self, tri: np.ndarray, u: np.ndarray, v: np.ndarray, cos: np.ndarray | None,
                           hit: np.ndarray, normals: np.ndarray | None = None, dirs=None) -> np.ndarray:
        """(N, 3) uint8 head-light shaded vertex colours (see :func:`shade_rgb`) of triangles
        ``tri`` (global index, all meshes concatenated) at barycentric weights (u, v) of corners
        1 and 2; ``cos`` the cosine between normal and reversed ray, or None to compute it from
        ``normals`` (N, 3) (facing the camera) and the ray components ``dirs`` = (dx, dy, dz);
        black where not ``hit``."""
        # Lambert factor (0..255 scale) per pixel, then per channel:
        # colour = c0 + u (c1 - c0) + v (c2 - c0) (barycentric vertex-colour interpolation)
        from synth.jit import available
        if self._col_stack is None:
            self._col_stack = (np.ascontiguousarray(np.stack(self._col_c0)), np.ascontiguousarray(np.stack(self._col_d1)),
                               np.ascontiguousarray(np.stack(self._col_d2)))
        c0, d1, d2 = self._col_stack
        if cos is None and not (available() and normals.dtype == np.float32 and all(x.dtype == np.float32 for x in dirs)):
            cos = -(normals[:, 0] * dirs[0] + normals[:, 1] * dirs[1] + normals[:, 2] * dirs[2])
        if available() and c0.dtype == np.float32 and u.dtype == np.float32 and (cos is None or cos.dtype == np.float32):
            rgb = np.empty((len(tri), 3), dtype=np.uint8)      # compiled: one pass, the same float32 steps
            a, b = np.float32(255.0 * (1.0 - AMBIENT)), np.float32(255.0 * AMBIENT)
            if cos is None:
                _vertex_colour_normals_kernel(np.ascontiguousarray(tri), u, v, np.ascontiguousarray(normals),
                                              np.ascontiguousarray(dirs[0]), np.ascontiguousarray(dirs[1]),
                                              np.ascontiguousarray(dirs[2]), np.ascontiguousarray(hit), c0, d1, d2, a, b,
                                              rgb)
            else:
                _vertex_colour_kernel(np.ascontiguousarray(tri), u, v, np.ascontiguousarray(cos),
                                      np.ascontiguousarray(hit), c0, d1, d2, a, b, rgb)
            return rgb
        f = np.minimum(np.abs(cos), np.float32(1.0))
        f *= np.float32(255.0 * (1.0 - AMBIENT))
        f += np.float32(255.0 * AMBIENT)
        f[~hit] = 0.0
        rgb = np.empty((len(tri), 3), dtype=np.uint8)
        for ch in range(3):
            x = self._col_d1[ch][tri]
            x *= u
            y = self._col_d2[ch][tri]
            y *= v
            x += y
            x += self._col_c0[ch][tri]
            x *= f
            x += 0.5
            np.clip(x, 0.0, 255.0, out=x)
            rgb[:, ch] = x
        return rgb

    def intrinsics_of(self, ray_dirs_cam: np.ndarray) -> Intrinsics | None:
        """The :class:`Intrinsics` whose cached ray grid is ``ray_dirs_cam`` (the same array
        object, as returned by :meth:`ray_dirs_cam`), else None."""
        for intr, (d, _) in self._ray_cache.items():
            if d is ray_dirs_cam:
                return intr
        return None

    def render_rows(self, row_c2w: np.ndarray, intr: Intrinsics) -> dict | None:
        """Per-pixel first hits of a view whose row v has pose ``row_c2w[v]`` ((H, 4, 4)
        camera-to-world: rolling shutter, sub-exposures) through
        :meth:`synth.render.raster.Rasterizer.render_rows` (visibility per band of rows whose image
        motion stays below 0.1 px, exact depth per row); None with the ``raycast`` back-end
        (callers then cast one ray per pixel). Returns that method's dict of arrays."""
        if self._raster is None:
            return None
        H, W = intr.shape
        _, d = self._rays(intr)
        return self._raster.render_rows(row_c2w, intr.fx, intr.fy, intr.cx, intr.cy, W, H, d[2].reshape(H, W),
                                        n_threads=n_threads())

    # ------------------------------------------------------------------ geometry queries
    def cast_rays(self, origins_world: np.ndarray, dirs_world: np.ndarray) -> dict[str, np.ndarray]:
        """First hits of N arbitrary rays (world frame).

        ``origins_world`` (N, 3) metres; ``dirs_world`` (N, 3), any non-zero length (they are
        normalised, so distances are metres). Returns a dict of

        * ``t_hit`` (N,) float32 distance to the first hit, metres (inf = no hit),
        * ``instance_ids`` (N,) int32 (k + 1 for ``scene.meshes[k]``, 0 = no hit),
        * ``normals_world`` (N, 3) float32 unit normals facing the ray origin (0 = no hit),
        * ``points_world`` (N, 3) float32 hit points, metres (0 = no hit).
        """
        o = np.asarray(origins_world, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(dirs_world, dtype=np.float64).reshape(-1, 3)
        if o.shape != d.shape:
            raise RealgapError(f"cast_rays: {len(o)} origins but {len(d)} directions")
        n = np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(n == 0) or not np.all(np.isfinite(n)):
            raise RealgapError("cast_rays: ray directions must be finite and non-zero")
        if len(o) == 0:
            return {"t_hit": np.zeros(0, np.float32), "instance_ids": np.zeros(0, np.int32),
                    "normals_world": np.zeros((0, 3), np.float32), "points_world": np.zeros((0, 3), np.float32)}
        d = d / n
        rays = np.ascontiguousarray(np.concatenate([o, d], axis=1), dtype=np.float32)
        out = self._cast(rays)
        t = out["t_hit"]
        hit = np.isfinite(t)
        inst = self._gid_to_instance[self._gid_index(out["geometry_ids"])]
        nrm = out["primitive_normals"].astype(np.float32)
        facing = np.einsum("ij,ij->i", nrm, rays[:, 3:])
        nrm *= (np.where(facing > 0, np.float32(-1.0), np.float32(1.0)) * hit)[:, None]
        pts = (rays[:, :3] + rays[:, 3:] * np.where(hit, t, 0)[:, None]) * hit[:, None]
        return {"t_hit": t, "instance_ids": inst, "normals_world": nrm, "points_world": pts.astype(np.float32)}

    def occluded(self, origins_world: np.ndarray, targets_world: np.ndarray,
                 eps_m: float = OCCLUSION_EPS_M) -> np.ndarray:
        """(N,) bool: True where geometry lies on the segment from origin to target.

        Shadow rays: the first and last ``eps_m`` metres of each segment are ignored, so a
        segment from the projector to a rendered surface point is not blocked by that surface
        itself. Segments shorter than ``2 * eps_m`` are never occluded. Inputs (N, 3) metres.
        """
        import open3d as o3d
        o = np.asarray(origins_world, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(targets_world, dtype=np.float64).reshape(-1, 3)
        if o.shape != q.shape:
            raise RealgapError(f"occluded: {len(o)} origins but {len(q)} targets")
        if len(o) == 0:
            return np.zeros(0, dtype=bool)
        d = q - o
        L = np.linalg.norm(d, axis=1)
        ok = L > 2 * eps_m
        u = d / np.where(ok, L, 1.0)[:, None]
        # shrink every segment by eps at both ends; then the ray is [0, 1] in units of its length
        start = o + u * eps_m
        seg = u * np.where(ok, L - 2 * eps_m, 0.0)[:, None]
        rays = np.ascontiguousarray(np.concatenate([start, seg], axis=1), dtype=np.float32)
        rays[~ok, 3:] = (0.0, 0.0, 1.0)  # any valid ray; result masked below
        occ = self.raycasting_scene.test_occlusions(o3d.core.Tensor.from_numpy(rays), tnear=0.0, tfar=1.0,
                                                    nthreads=n_threads())
        return occ.numpy().astype(bool) & ok

    def albedo_specular(self, instance_ids: np.ndarray, check: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Per-element (albedo, specular) float32 arrays of the materials of ``instance_ids``
        (any shape; 0 = background gives 0, 0). ``check=False`` skips the range check (ids
        this renderer produced)."""
        ids = np.asarray(instance_ids)
        if check and ids.size and (ids.min() < 0 or ids.max() > self.n_meshes):
            raise RealgapError(f"albedo_specular: instance ids must be in [0, {self.n_meshes}]")
        return np.take(self._albedo, ids), np.take(self._specular, ids)


@kernel
def _colour_pixel(i, t, u, v, f, c0, d1, d2, out):
    """``out[i]`` = the triangle ``t``'s vertex colour interpolated at (u[i], v[i]) times the shading factor ``f``,
    rounded and clipped to uint8 (float32 steps in the numpy version's order)."""
    for ch in range(3):
        x = d1[ch, t] * u[i]
        y = d2[ch, t] * v[i]
        x = x + y
        x = x + c0[ch, t]
        x = x * f
        x = x + np.float32(0.5)
        if x < np.float32(0.0):
            x = np.float32(0.0)
        elif x > np.float32(255.0):
            x = np.float32(255.0)
        out[i, ch] = np.uint8(x)


@kernel
def _vertex_colour_kernel(tri, u, v, cos, hit, c0, d1, d2, a, b, out):
    """:meth:`IdealRenderer._vertex_colour_rgb` in one compiled pass (float32 steps in the numpy
    version's order, so the bytes are identical)."""
    for i in range(tri.shape[0]):
        if not hit[i]:
            out[i, 0] = 0
            out[i, 1] = 0
            out[i, 2] = 0
            continue
        f = min(abs(cos[i]), np.float32(1.0))
        f = f * a
        f = f + b
        _colour_pixel(i, tri[i], u, v, f, c0, d1, d2, out)


@kernel
def _vertex_colour_normals_kernel(tri, u, v, nc, dx, dy, dz, hit, c0, d1, d2, a, b, out):
    """:func:`_vertex_colour_kernel` with the cosine computed here, as numpy computes
    ``-(n_x d_x + n_y d_y + n_z d_z)`` in float32."""
    cos = np.empty(1, np.float32)
    for i in range(tri.shape[0]):
        if not hit[i]:
            out[i, 0] = 0
            out[i, 1] = 0
            out[i, 2] = 0
            continue
        c = nc[i, 0] * dx[i] + nc[i, 1] * dy[i]
        c = c + nc[i, 2] * dz[i]
        cos[0] = -c
        f = min(abs(cos[0]), np.float32(1.0))
        f = f * a
        f = f + b
        _colour_pixel(i, tri[i], u, v, f, c0, d1, d2, out)
