"""Truncated signed distance (TSDF) fusion with Open3D's tensor ``VoxelBlockGrid``.

The volume is a sparse hash of dense voxel blocks (``block_resolution``^3 voxels each) that
stores, per voxel, the truncated signed distance (float32, in units of the truncation
distance), its integration weight (float32, number of fused observations) and optionally the
weighted mean colour (float32 RGB in [0, 1]). Blocks are allocated for the frustum of every
fused depth image, and the hash map grows as needed (``initial_block_count`` only sizes the
first allocation).

Conventions: depth images are (H, W) float32 z-depth in metres with 0 = no measurement,
colour images (H, W, 3) uint8 RGB, poses camera-to-world 4x4 (OpenCV optical axes), pixel
centres at integer coordinates.

Two corrections of Open3D's kernels (both measured on rendered scenes, tests in
tests/test_slam_tsdf.py):

* integration picks the pixel of a voxel by *truncating* its projected coordinates while ray
  casting shoots rays through integer pixel coordinates; integrating with the principal point
  moved by half a pixel turns the truncation into rounding, so model and images agree;
* the ray marcher reads the voxel *below* each sample (no interpolation), so its surface is up
  to a voxel off in a view-dependent direction; :meth:`TSDFVolume.raycast` can refine every
  hit on the trilinear TSDF (``refine``).

Open3D also sizes an internal ray-casting buffer only after a call that overflowed it (that
call misses blocks); :meth:`TSDFVolume.raycast_tensors` grows it beforehand.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import ConfigError, FormatError, RealgapError
from data_tools.mesh import TriMesh
from slam.registration import check_positive, config_from_dict, config_to_dict


def o3d_quiet():
    """Import open3d with its console logging limited to errors (the VoxelBlockGrid ray caster
    prints a warning whenever it re-sizes an internal buffer)."""
    import open3d as o3d
    if not getattr(o3d_quiet, "_done", False):
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        o3d_quiet._done = True
    return o3d


@dataclass
class TSDFConfig:
    """TSDF volume options (saved in RUN/config.json)."""

    voxel_size_m: float = 0.01
    """Edge length of one voxel, metres (mesh resolution; memory and time grow as 1/size^2)."""
    trunc_voxel_multiplier: float = 4.0
    """Truncation distance of the signed distance, in voxels (4 x 0.01 m = 4 cm)."""
    block_resolution: int = 8
    """Voxels per block edge (blocks are allocated and hashed as a whole). Open3D's ray caster
    crosses unallocated space one block at a time, and a jump that lands behind a surface gives
    a false hit or a hole (see :meth:`TSDFVolume.raycast`): 8-voxel blocks halve the jump. On a
    one-frame 1 cm volume of the test room (320 x 240) the raw cast misses 18 % of the pixels
    with 16-voxel blocks and 1 % with 8; frame-to-model tracking of the demo sequence ran
    about 1.5x faster (fewer empty voxels allocated, integrated and marched)."""
    initial_block_count: int = 20000
    """Blocks allocated up front; the hash map grows beyond this when needed."""
    depth_min_m: float = 0.1
    """Depth measurements closer than this are ignored, metres."""
    depth_max_m: float = 4.0
    """Depth measurements farther than this are ignored (depth truncation), metres."""
    integrate_color: bool = True
    """Fuse the colour images too (mesh vertex colours, rendered colour)."""
    mesh_weight_threshold: float = 3.0
    """Minimum integration weight (number of observations) of a voxel for the extracted mesh
    and point cloud; lower it for very short sequences."""
    raycast_weight_threshold: float = 1.0
    """Minimum integration weight of the zero crossing found by the ray caster (tracking and
    rendering)."""
    device: str = "CPU:0"
    """Open3D device of the volume (``CPU:0`` or ``CUDA:0``)."""

    def validate(self) -> "TSDFConfig":
        for n in ("voxel_size_m", "trunc_voxel_multiplier", "depth_min_m", "depth_max_m",
                  "mesh_weight_threshold", "raycast_weight_threshold"):
            v = getattr(self, n)
            if isinstance(v, int) and not isinstance(v, bool):
                setattr(self, n, float(v))
        check_positive(self, "voxel_size_m", "trunc_voxel_multiplier", "depth_max_m",
                       "initial_block_count", "block_resolution")
        check_positive(self, "depth_min_m", "mesh_weight_threshold", "raycast_weight_threshold",
                       allow_zero=True)
        if self.depth_min_m >= self.depth_max_m:
            raise ConfigError(f"TSDFConfig: depth_min_m ({self.depth_min_m}) must be below depth_max_m ({self.depth_max_m})")
        if self.block_resolution not in (4, 8, 16, 32):
            raise ConfigError(f"TSDFConfig.block_resolution must be 4, 8, 16 or 32, got {self.block_resolution}")
        return self

    @property
    def sdf_trunc_m(self) -> float:
        """Truncation distance, metres."""
        return self.voxel_size_m * self.trunc_voxel_multiplier


@dataclass
class RaycastResult:
    """What the ray caster sees from one pose (numpy arrays, (H, W) image grid)."""

    depth: np.ndarray
    """(H, W) float32 z-depth of the fused surface, metres; 0 where no surface was hit."""
    color: np.ndarray | None
    """(H, W, 3) float32 RGB in [0, 1] (zeros where nothing was hit), or None."""
    normal: np.ndarray | None
    """(H, W, 3) float32 unit surface normals in the camera frame (zeros where nothing was hit)."""
    weight: np.ndarray | None = None
    """(H, W) float32 integration weight (observations) at the hit, the mean over the 8 voxels
    of its cell (0 where nothing was hit); only with ``refine`` and ``with_weight`` (else None)."""

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool, True where the ray hit the fused surface."""
        return self.depth > 0


_ALL8 = np.frombuffer(np.ones(8, np.uint8).tobytes(), np.uint64)[0]
"""Eight True bytes read as one uint64 (all 8 corners of a ray-cast cell observed)."""


def range_map_factor(intr: Intrinsics) -> int:
    """Down-sampling factor of Open3D's ray-casting range map: the largest of 8, 4, 2, 1 that
    divides both image sides (other factors make Open3D's ray caster miss or hang)."""
    for f in (8, 4, 2):
        if intr.width % f == 0 and intr.height % f == 0:
            return f
    return 1


def fragments_needed(block_coords: np.ndarray, intr: Intrinsics, T_w2c: np.ndarray, down: int,
                     block_size_m: float, depth_min: float, depth_max: float, fragment: int = 16) -> int:
    """Number of 16x16 range-map fragments Open3D's ray caster needs for these blocks (the
    bounding rectangle of each block's projected corners on the down-sampled range map)."""
    if len(block_coords) == 0:
        return 0
    corners = np.array([[(i & 1) > 0, (i & 2) > 0, (i & 4) > 0] for i in range(8)], np.float64)
    P = (block_coords[:, None, :].astype(np.float64) + corners[None]) * block_size_m   # (M, 8, 3)
    Pc = P @ T_w2c[:3, :3].T + T_w2c[:3, 3]
    z = Pc[..., 2]
    front = z > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (intr.fx * Pc[..., 0] / z + intr.cx) / down
        v = (intr.fy * Pc[..., 1] / z + intr.cy) / down
    h_down, w_down = intr.height // down, intr.width // down
    big = 1 << 30
    u_min = np.where(front, np.floor(np.nan_to_num(u, nan=big)), big).min(1)
    u_max = np.where(front, np.ceil(np.nan_to_num(u, nan=-big)), -big).max(1)
    v_min = np.where(front, np.floor(np.nan_to_num(v, nan=big)), big).min(1)
    v_max = np.where(front, np.ceil(np.nan_to_num(v, nan=-big)), -big).max(1)
    u_min = np.minimum(u_min, w_down - 1)
    v_min = np.minimum(v_min, h_down - 1)
    u_max = np.maximum(u_max, 0)
    v_max = np.maximum(v_max, 0)
    z_min = np.where(front, z, np.inf).min(1)
    z_max = np.where(front, z, -np.inf).max(1)
    z_min = np.minimum(z_min, depth_max)
    z_max = np.maximum(z_max, depth_min)
    v_min, v_max = np.maximum(0, v_min), np.minimum(h_down - 1, v_max)
    u_min, u_max = np.maximum(0, u_min), np.minimum(w_down - 1, u_max)
    ok = (v_min < v_max) & (u_min < u_max) & (z_min < z_max)
    nv = np.ceil((v_max - v_min + 1) / fragment)
    nu = np.ceil((u_max - u_min + 1) / fragment)
    return int((nv * nu)[ok].sum())


def intrinsic_tensor(intr: Intrinsics):
    o3d = o3d_quiet()
    return o3d.core.Tensor(intr.K, dtype=o3d.core.float64)


class TSDFVolume:
    """A growing TSDF volume: integrate RGB-D frames, ray cast, extract a mesh or points."""

    def __init__(self, config: TSDFConfig | None = None):
        self.config = (config or TSDFConfig()).validate()
        o3d = o3d_quiet()
        c = o3d.core
        self.device = c.Device(self.config.device)
        names = ("tsdf", "weight", "color") if self.config.integrate_color else ("tsdf", "weight")
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            names, (c.float32,) * len(names), ((1,), (1,), (3,))[:len(names)],
            self.config.voxel_size_m, self.config.block_resolution,
            self.config.initial_block_count, self.device)
        self._fragment_capacity = 0
        self.last_block_coords = None
        """(M, 3) int32 tensor of the blocks touched by the latest integration (its frustum)."""
        self.frames_integrated = 0
        self._lookup = None
        self._lookup_key = None

    # ---------------------------------------------------------------- helpers
    def _depth_image(self, depth_m: np.ndarray):
        o3d = o3d_quiet()
        d = np.ascontiguousarray(depth_m, dtype=np.float32)
        if d.ndim != 2:
            raise RealgapError(f"depth image must be (H, W), got shape {d.shape}")
        d = np.where(np.isfinite(d), d, 0.0).astype(np.float32)
        return o3d.t.geometry.Image(o3d.core.Tensor(d, device=self.device))

    def _color_image(self, rgb: np.ndarray):
        o3d = o3d_quiet()
        c = np.ascontiguousarray(rgb)
        if c.ndim != 3 or c.shape[2] != 3:
            raise RealgapError(f"colour image must be (H, W, 3), got shape {c.shape}")
        c = (c.astype(np.float32) / 255.0) if c.dtype == np.uint8 else c.astype(np.float32)
        return o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(c), device=self.device))

    @staticmethod
    def _extrinsic(pose_c2w: np.ndarray):
        o3d = o3d_quiet()
        T = np.asarray(pose_c2w, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise RealgapError("pose must be a finite 4x4 matrix")
        return o3d.core.Tensor(np.linalg.inv(T), dtype=o3d.core.float64)

    # ---------------------------------------------------------------- fusion
    def integrate(self, depth_m: np.ndarray, rgb: np.ndarray | None, intr: Intrinsics,
                  pose_c2w: np.ndarray) -> None:
        """Fuse one frame: depth (H, W) metres (0 = none), rgb (H, W, 3) uint8 or None,
        camera-to-world pose (4, 4)."""
        cfg = self.config
        depth = np.asarray(depth_m, dtype=np.float32)
        if depth.shape != intr.shape:
            raise RealgapError(f"depth shape {depth.shape} does not match intrinsics {intr.shape}")
        depth = np.where(depth >= cfg.depth_min_m, depth, 0.0).astype(np.float32)
        dimg = self._depth_image(depth)
        K = intrinsic_tensor(intr)
        # Open3D's integration kernel picks the pixel of a projected voxel by truncating its
        # coordinates (pixel k covers [k, k+1)), while the ray caster (and every other part of
        # realgap) puts pixel centres at integers. Shifting the principal point by half a pixel
        # makes the truncation a rounding: without it the model sits half a pixel off the
        # images and frame-to-model tracking drifts.
        K_int = intrinsic_tensor(Intrinsics(intr.width, intr.height, intr.fx, intr.fy,
                                            intr.cx + 0.5, intr.cy + 0.5))
        ext = self._extrinsic(pose_c2w)
        blocks = self.vbg.compute_unique_block_coordinates(
            dimg, K, ext, 1.0, cfg.depth_max_m, cfg.trunc_voxel_multiplier)
        if cfg.integrate_color:
            if rgb is None:
                rgb = np.full(depth.shape + (3,), 128, np.uint8)
            if rgb.shape[:2] != depth.shape:
                raise RealgapError(f"colour shape {rgb.shape[:2]} does not match depth {depth.shape}")
            self.vbg.integrate(blocks, dimg, self._color_image(rgb), K_int, K_int, ext, 1.0,
                               cfg.depth_max_m, cfg.trunc_voxel_multiplier)
        else:
            self.vbg.integrate(blocks, dimg, K_int, ext, 1.0, cfg.depth_max_m, cfg.trunc_voxel_multiplier)
        self.last_block_coords = blocks
        self.frames_integrated += 1

    @property
    def num_blocks(self) -> int:
        return int(self.vbg.hashmap().size())

    def all_block_coords(self):
        """(M, 3) int32 tensor of every allocated block."""
        o3d = o3d_quiet()
        hm = self.vbg.hashmap()
        return hm.key_tensor()[hm.active_buf_indices().to(o3d.core.int64)]

    # ---------------------------------------------------------------- ray casting
    def raycast_tensors(self, intr: Intrinsics, pose_c2w: np.ndarray, attributes=("depth",),
                        block_coords=None, depth_min_m: float | None = None,
                        depth_max_m: float | None = None):
        """Open3D ray cast; returns the raw TensorMap (depth (H, W, 1) metres with 0 = miss;
        'vertex' and 'normal' (H, W, 3) in the camera frame; 'color' (H, W, 3) in [0, 1]).

        ``block_coords`` limits the search to those blocks (e.g. :attr:`last_block_coords`,
        the frustum of the last fused frame, as KinectFusion does); None = every block.
        """
        cfg = self.config
        if self.num_blocks == 0:
            raise RealgapError("the TSDF volume is empty: nothing to ray cast")
        if block_coords is None:
            block_coords = self.all_block_coords()
        attrs = list(attributes)
        if "color" in attrs and not cfg.integrate_color:
            attrs.remove("color")
        dmin = cfg.depth_min_m if depth_min_m is None else depth_min_m
        dmax = cfg.depth_max_m if depth_max_m is None else depth_max_m
        down = range_map_factor(intr)
        ext = self._extrinsic(pose_c2w)

        def cast():
            return self.vbg.ray_cast(block_coords, intrinsic_tensor(intr), ext, intr.width, intr.height,
                                     attrs, 1.0, dmin, dmax, cfg.raycast_weight_threshold,
                                     cfg.trunc_voxel_multiplier, down)

        # Open3D sizes its range-map fragment buffer only after a call that overflowed it (and
        # that call, like every call that needs exactly the buffer size, misses blocks). When
        # the need grows, a throw-away cast with every block listed twice grows the buffer to
        # twice the need first.
        need = fragments_needed(block_coords.cpu().numpy(), intr, np.linalg.inv(np.asarray(pose_c2w, np.float64)),
                                down, self.config.voxel_size_m * self.config.block_resolution, dmin, dmax)
        if need >= self._fragment_capacity:
            o3d = o3d_quiet()
            doubled = o3d.core.concatenate([block_coords, block_coords], 0)
            self.vbg.ray_cast(doubled, intrinsic_tensor(intr), ext, intr.width, intr.height, ["depth"],
                              1.0, dmin, dmax, cfg.raycast_weight_threshold, cfg.trunc_voxel_multiplier, down)
            self._fragment_capacity = 2 * need
        return cast()

    def raycast(self, intr: Intrinsics, pose_c2w: np.ndarray, with_color: bool = True,
                with_normal: bool = True, depth_max_m: float | None = None, block_coords=None,
                refine: bool = True, repair: bool = True, with_weight: bool = False,
                times: dict | None = None) -> RaycastResult:
        """Render the fused surface from ``pose_c2w`` (camera-to-world) with ``intr``.

        Open3D's ray marcher reads the TSDF of the voxel *below* each sample point (no
        interpolation), which puts its zero crossings up to a voxel off the surface, in a
        direction that depends on the view. With ``refine`` (default) every hit is moved to the
        zero of the trilinearly interpolated TSDF along its ray by two Newton steps inside the
        voxel cell Open3D reports (its 8 corner indices and interpolation weights), which makes
        the depth accurate to a small fraction of a voxel.

        The marcher also crosses unallocated space in steps of a whole block
        (``block_resolution`` voxels) and, on entering an allocated block *behind* the surface,
        reports a crossing interpolated from the stale value of before the jump: a hit up to
        several centimetres in front of the surface (or, past the whole band, a hole). With
        ``refine`` every hit is therefore verified on the trilinear TSDF (all 8 corners observed,
        value within a quarter voxel of zero); a hit that fails is searched again along its ray
        (one block length on either side, one-voxel steps, first observed + to - crossing) and
        dropped (depth 0) when no crossing is found (see :meth:`_repair_hits`). With ``repair =
        False`` the hits that fail the check are dropped without the search (about 10 % of the
        pixels of a real Kinect model view, half of them false; the search costs more than the
        rest of the refinement). With ``refine`` and ``with_weight`` the result also holds the
        integration weight at each hit (``weight``).
        """
        attrs = ["depth"] + (["color"] if with_color and self.config.integrate_color else [])
        if with_normal:
            attrs.append("normal")
        if refine:
            attrs += ["index", "interp_ratio", "mask"]
        import time
        t = [time.perf_counter()]
        r = self.raycast_tensors(intr, pose_c2w, attrs, block_coords, depth_max_m=depth_max_m)
        depth = r["depth"].cpu().numpy()[..., 0].astype(np.float32)
        depth[~np.isfinite(depth)] = 0.0
        color = r["color"].cpu().numpy().astype(np.float32) if "color" in attrs else None
        normal = r["normal"].cpu().numpy().astype(np.float32) if with_normal else None
        t.append(time.perf_counter())
        if refine:
            depth, verified, weight = self._refine_depth(depth, r, intr, pose_c2w, with_weight)
            t.append(time.perf_counter())
            suspect = (depth > 0) & ~verified
            if repair:
                depth = self._repair_hits(depth, suspect, intr, pose_c2w, color, normal)
            else:
                depth[suspect] = 0.0
            t.append(time.perf_counter())
        for name, a, b in zip(("raycast_open3d", "raycast_refine", "raycast_repair"), t, t[1:]):
            if times is not None:   # seconds per step, added up (the tracking profile)
                times[name] = times.get(name, 0.0) + b - a
        miss = depth <= 0
        if color is not None:
            color[miss] = 0.0
        if normal is not None:
            normal[miss] = 0.0
        if not refine:
            weight = None
        elif weight is not None:
            weight[miss] = 0.0
        return RaycastResult(depth, color, normal, weight)

    def _refine_depth(self, depth: np.ndarray, r, intr: Intrinsics, pose_c2w: np.ndarray,
                      with_weight: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Newton refinement of ray-cast depths on the trilinear TSDF (see :meth:`raycast`).

        Returns ``(depth, verified, weight)``: ``verified`` (H, W) is True where all 8 corners of
        the cell Open3D reported are observed and the refined depth is within a voxel of a zero
        of their trilinear TSDF; other hits are left for :meth:`_repair_hits`. ``weight`` (H, W):
        the mean integration weight of those 8 corners at the refined hits (0 elsewhere), only
        ``with_weight`` (else None).

        Along a ray the trilinear TSDF of one cell is a cubic in the depth offset ``s``
        (metres): its coefficients are computed once per hit, then two Newton steps run on the
        cubic. float32 throughout (offsets of at most two voxels; the values agree with a
        float64 evaluation to well below a micrometre)."""
        hit = depth > 0
        verified = np.zeros(depth.shape, bool)
        mask = np.ascontiguousarray(r["mask"].cpu().numpy())
        full = mask.view(np.uint64)[..., 0] == _ALL8 if mask.dtype == np.bool_ and mask.shape[-1] == 8 \
            else mask.all(axis=-1)
        sel = np.flatnonzero(hit & full)
        if len(sel) == 0:
            return depth, verified, np.zeros(depth.shape, np.float32) if with_weight else None
        idx = r["index"].cpu().numpy().reshape(-1, 8)[sel]              # (N, 8) linear voxel indices
        w = r["interp_ratio"].cpu().numpy().reshape(-1, 8)[sel]         # (N, 8) trilinear weights
        tsdf = self.vbg.attribute("tsdf").cpu().numpy().reshape(-1)
        c = tsdf[idx]                                    # corner k: dx=k&1, dy=k>>1&1, dz=k>>2&1
        with np.errstate(divide="ignore", invalid="ignore"):
            x = w[:, 1] / (w[:, 0] + w[:, 1])
            y = w[:, 2] / (w[:, 0] + w[:, 2])
            z = w[:, 4] / (w[:, 0] + w[:, 4])
        good = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
        v, u = np.divmod(sel, depth.shape[1])
        R = (np.asarray(pose_c2w, np.float64)[:3, :3] / self.config.voxel_size_m).astype(np.float32)
        a = ((u - intr.cx) / intr.fx).astype(np.float32)
        b = ((v - intr.cy) / intr.fy).astype(np.float32)
        # ray direction in voxel units per metre of depth
        bx = R[0, 0] * a + R[0, 1] * b + R[0, 2]
        by = R[1, 0] * a + R[1, 1] * b + R[1, 2]
        bz = R[2, 0] * a + R[2, 1] * b + R[2, 2]
        # trilinear f = c0 + Bx + Cy + Dz + Exy + Fxz + Gyz + Hxyz in the cell's unit cube
        c0, c1, c2, c3, c4, c5, c6, c7 = c.T
        B, C, D = c1 - c0, c2 - c0, c4 - c0
        E, F, G = c3 - c2 - c1 + c0, c5 - c4 - c1 + c0, c6 - c4 - c2 + c0
        H = c7 - c6 - c5 + c4 - c3 + c2 + c1 - c0
        # along the ray q(s) = (x, y, z) + s (bx, by, bz): cubic p0 + p1 s + p2 s^2 + p3 s^3
        gx = B + E * y + F * z + H * y * z
        gy = C + E * x + G * z + H * x * z
        gz = D + F * x + G * y + H * x * y
        p0 = c0 + B * x + C * y + D * z + E * x * y + F * x * z + G * y * z + H * x * y * z
        p1 = gx * bx + gy * by + gz * bz
        p2 = E * bx * by + F * bx * bz + G * by * bz + H * (x * by * bz + y * bx * bz + z * bx * by)
        p3 = H * bx * by * bz
        s = np.zeros_like(p0)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for _ in range(2):
                f = p0 + s * (p1 + s * (p2 + s * p3))
                df = p1 + s * (2 * p2 + s * (3 * p3))
                s = s + np.where(good & (df < -1e-6), -f / df, 0.0).astype(np.float32)
            # accept only moves that stay near the original cell (a well-posed crossing)
            s = np.where(good & np.isfinite(s) & (np.abs(s) <= 2.0 * self.config.voxel_size_m), s, 0.0)
            # a true crossing leaves a near-zero TSDF after the Newton steps (the trilinear model
            # of the reported cell may be extrapolated up to a voxel or two); a false one (see
            # :meth:`raycast`) sits in free space where the TSDF is near +1, or in an unobserved cell
            f = p0 + s * (p1 + s * (p2 + s * p3))
        verified.reshape(-1)[sel] = good & (np.abs(f) <= 1.0 / self.config.trunc_voxel_multiplier)
        out = depth.copy()
        out.reshape(-1)[sel] += s.astype(np.float32)
        weight = None
        if with_weight:
            wts = self.vbg.attribute("weight").cpu().numpy().reshape(-1)
            weight = np.zeros(depth.shape, np.float32)
            weight.reshape(-1)[sel] = wts[idx].mean(axis=1)
        return out, verified, weight

    # ---------------------------------------------------------------- TSDF sampling
    def _block_lookup(self):
        """(lo (3,), table) with ``table[key - lo]`` = buffer index of block ``key`` (-1 = none):
        a dense copy of the hash map over the bounding box of the allocated blocks, rebuilt
        after every integration."""
        key = (self.frames_integrated, self.num_blocks, id(self.vbg))
        if self._lookup_key != key:
            o3d = o3d_quiet()
            hm = self.vbg.hashmap()
            act = hm.active_buf_indices().to(o3d.core.int64)
            keys = hm.key_tensor()[act].cpu().numpy().astype(np.int64)
            bufs = act.cpu().numpy().astype(np.int64)
            if len(keys) == 0:
                self._lookup = (np.zeros(3, np.int64), np.full((1, 1, 1), -1, np.int32))
            else:
                lo = keys.min(0)
                table = np.full(tuple(keys.max(0) - lo + 1), -1, np.int32)
                table[tuple((keys - lo).T)] = bufs
                self._lookup = (lo, table)
            self._lookup_key = key
        return self._lookup

    def _voxel_index(self, coords: np.ndarray) -> np.ndarray:
        """Linear index into the voxel attributes of integer voxel coordinates (..., 3)
        (voxel k sits at k * voxel_size metres); -1 where the block is not allocated.
        Block coordinates are computed in int32 (volumes up to 2^31 voxels per axis)."""
        res = self.config.block_resolution                      # a power of two (validated)
        shift = res.bit_length() - 1
        lo, table = self._block_lookup()
        c = coords.astype(np.int32, copy=False)
        s0, s1, s2 = table.shape
        rel = (c >> shift) - lo.astype(np.int32)
        flat = (rel[..., 0] * s1 + rel[..., 1]) * s2 + rel[..., 2]
        # negative offsets wrap to huge unsigned values: one comparison per axis
        inside = ((rel[..., 0].view(np.uint32) < s0) & (rel[..., 1].view(np.uint32) < s1)
                  & (rel[..., 2].view(np.uint32) < s2))
        np.putmask(flat, ~inside, 0)
        buf = table.reshape(-1)[flat].astype(np.int64)
        np.putmask(buf, ~inside, -1)
        o = c & (res - 1)
        lin = (buf << (3 * shift)) + (o[..., 0] + (o[..., 1] << shift) + (o[..., 2] << (2 * shift)))
        np.putmask(lin, buf < 0, -1)
        return lin

    def sample_tsdf(self, points_w: np.ndarray, nearest: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """TSDF at world points (N, 3) metres: trilinear, or the nearest voxel's value.

        Returns ``(tsdf (N,), grad (N, 3), ok (N,), corners (N, 8))``: the signed distance in
        units of the truncation distance, its gradient per metre (world frame; zeros with
        ``nearest``), True where every voxel used is allocated and has at least
        ``raycast_weight_threshold`` observations, and the corners' linear voxel indices (-1
        where missing; corner k is offset by (k & 1, k >> 1 & 1, k >> 2 & 1) voxels; one
        column with ``nearest``).
        """
        cfg = self.config
        q = np.asarray(points_w, np.float64).reshape(-1, 3) / cfg.voxel_size_m
        finite = np.isfinite(q).all(1)
        q = np.where(finite[:, None], q, 0.0)
        tsdf_all = self.vbg.attribute("tsdf").cpu().numpy().reshape(-1)
        w_all = self.vbg.attribute("weight").cpu().numpy().reshape(-1)
        w_min = max(cfg.raycast_weight_threshold, 1e-6)
        if nearest:
            lin = self._voxel_index(np.rint(q).astype(np.int64))[:, None]
        else:
            base = np.floor(q).astype(np.int64)
            offs = np.array([[k & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], np.int64)
            lin = self._voxel_index(base[:, None, :] + offs[None])
        safe = np.maximum(lin, 0)
        v = np.where(lin >= 0, tsdf_all[safe], 0.0).astype(np.float64)
        ok = finite & np.all((lin >= 0) & (w_all[safe] >= w_min), axis=1)
        if nearest:
            return v[:, 0], np.zeros((len(q), 3)), ok, lin
        fr = q - base
        x, y, z = fr[:, 0], fr[:, 1], fr[:, 2]
        c0, c1, c2, c3, c4, c5, c6, c7 = v.T             # corner k at (k & 1, k >> 1 & 1, k >> 2 & 1)
        d01, d23, d45, d67 = c1 - c0, c3 - c2, c5 - c4, c7 - c6
        c00, c10, c01, c11 = c0 + x * d01, c2 + x * d23, c4 + x * d45, c6 + x * d67
        e0, e1 = c10 - c00, c11 - c01
        f0, f1 = c00 + y * e0, c01 + y * e1
        f = f0 + z * (f1 - f0)
        grad = np.stack([(d01 + y * (d23 - d01)) * (1 - z) + (d45 + y * (d67 - d45)) * z,
                         e0 + z * (e1 - e0), f1 - f0], -1)
        return f, grad / cfg.voxel_size_m, ok, lin

    def _repair_hits(self, depth: np.ndarray, suspect: np.ndarray, intr: Intrinsics,
                     pose_c2w: np.ndarray, color: np.ndarray | None, normal: np.ndarray | None
                     ) -> np.ndarray:
        """Search the zero crossing again along the rays of the ``suspect`` hits (see
        :meth:`raycast`): nearest-voxel samples one voxel apart (the negative band behind a
        surface is ``trunc_voxel_multiplier`` voxels deep, so no crossing falls between two
        samples; half-voxel steps cost twice as much for the same hits) over one block length and a
        voxel on either side of the reported depth, the first observed + to - sign change,
        then a secant and a Newton step on the trilinear TSDF; the result must pass the same
        quarter-voxel check, else the pixel becomes a miss (depth 0). ``color`` and ``normal``
        are updated in place for repaired pixels (normal: minus the TSDF gradient, Open3D's
        convention; colour: trilinear mean). Returns the new depth."""
        out = depth.copy()
        v, u = np.nonzero(suspect)
        if len(v) == 0:
            return out
        cfg = self.config
        vs = cfg.voxel_size_m
        tol = 0.25 / cfg.trunc_voxel_multiplier
        T = np.asarray(pose_c2w, np.float64)
        R, C = T[:3, :3], T[:3, 3]
        d_w = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(len(u))], -1) @ R.T
        z = depth[v, u].astype(np.float64)
        # most suspects are true crossings just outside the cell Open3D reported: two Newton
        # steps on the trilinear TSDF sampled here settle them
        zt = z.copy()
        for _ in range(2):
            f, g, _, _ = self.sample_tsdf(C + zt[:, None] * d_w)
            dfdz = (g * d_w).sum(1)
            with np.errstate(divide="ignore", invalid="ignore"):
                st = np.where(dfdz < -1e-9, -f / dfdz, np.inf)
            zt = np.where(np.abs(st) <= vs, zt + st, zt)
        f, g, okt, lin = self.sample_tsdf(C + zt[:, None] * d_w)
        settled = okt & (np.abs(f) <= tol) & (np.abs(zt - z) <= 2 * vs)
        out[v[settled], u[settled]] = zt[settled].astype(np.float32)
        self._set_attributes(v[settled], u[settled], zt[settled], d_w[settled], g[settled], lin[settled],
                             C, R, color, normal)
        rest = ~settled
        v, u, d_w, z = v[rest], u[rest], d_w[rest], z[rest]
        if len(v) == 0:
            return out
        step = vs / np.linalg.norm(d_w, axis=1)                         # depth step of one voxel
        reach = cfg.block_resolution + 1
        offs = np.arange(-reach, reach + 1, dtype=np.float64)
        zs = z[:, None] + offs[None, :] * step[:, None]                 # (M, S) depths along each ray
        fs, _, oks, _ = self.sample_tsdf((C + zs[..., None] * d_w[:, None, :]).reshape(-1, 3), nearest=True)
        fs, oks = fs.reshape(zs.shape), oks.reshape(zs.shape)
        cross = oks[:, :-1] & oks[:, 1:] & (fs[:, :-1] > 0) & (fs[:, 1:] <= 0) & (zs[:, :-1] > 0)
        found = cross.any(1)
        j = np.argmax(cross, axis=1)
        rows = np.arange(len(z))
        # secant on the trilinear TSDF over the bracketing samples, then one Newton step
        za, zb = zs[rows, j], zs[rows, j + 1]
        fa, _, _, _ = self.sample_tsdf(C + za[:, None] * d_w)
        fb, _, _, _ = self.sample_tsdf(C + zb[:, None] * d_w)
        with np.errstate(divide="ignore", invalid="ignore"):
            zn = np.where(fa > fb, za + fa / (fa - fb) * (zb - za), 0.5 * (za + zb))
        fn, gn, _, _ = self.sample_tsdf(C + zn[:, None] * d_w)
        dfdz = (gn * d_w).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            zn2 = zn - np.where(dfdz < -1e-9, fn / dfdz, 0.0)
        zn = np.where(np.isfinite(zn2) & (np.abs(zn2 - zn) <= 2 * step), zn2, zn)
        fn, gn, okn, lin = self.sample_tsdf(C + zn[:, None] * d_w)
        good = found & okn & (np.abs(fn) <= tol) & np.isfinite(zn) & (zn > 0)
        out[v, u] = np.where(good, zn, 0.0).astype(np.float32)
        self._set_attributes(v[good], u[good], zn[good], d_w[good], gn[good], lin[good], C, R, color, normal)
        return out

    def _set_attributes(self, v, u, z, d_w, grad, lin, C, R, color, normal) -> None:
        """Normals (minus the TSDF gradient, Open3D's convention, camera frame) and trilinear
        colours of re-found hits at pixels (v, u), written into ``normal`` / ``color``."""
        if len(v) == 0:
            return
        if normal is not None:
            n_w = -grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-12)
            normal[v, u] = (n_w @ R).astype(np.float32)
        if color is not None:
            col = self.vbg.attribute("color").cpu().numpy().reshape(-1, 3)
            q = (C + z[:, None] * d_w) / self.config.voxel_size_m
            fr = q - np.floor(q)
            offs8 = np.array([[k & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)])
            wts = np.prod(np.where(offs8[None] == 1, fr[:, None, :], 1 - fr[:, None, :]), axis=-1)
            color[v, u] = ((wts[..., None] * col[lin]).sum(1) / 255.0).astype(np.float32)

    # ---------------------------------------------------------------- extraction
    def extract_mesh(self, weight_threshold: float | None = None) -> TriMesh:
        """Marching-cubes mesh of the zero level set (world frame, metres), with vertex colours
        when colour is fused, in canonical order (:meth:`TriMesh.canonical`: the same volume gives
        the same file). Voxels with fewer than ``weight_threshold`` observations (default
        :attr:`TSDFConfig.mesh_weight_threshold`) are left out."""
        w = self.config.mesh_weight_threshold if weight_threshold is None else weight_threshold
        w = max(float(w) - 0.5, 0.0)  # Open3D keeps weights strictly above; weights count frames
        if self.num_blocks == 0:
            return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), name="tsdf")
        try:
            m = self.vbg.extract_triangle_mesh(w)
        except RuntimeError as e:  # Open3D fails on an empty surface instead of returning one
            if "shape {0}" in str(e):
                return TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), name="tsdf")
            raise
        v = m.vertex["positions"].cpu().numpy().astype(np.float64)
        f = m.triangle["indices"].cpu().numpy().astype(np.int32) if "indices" in m.triangle \
            else np.zeros((0, 3), np.int32)
        colors = None
        if self.config.integrate_color and "colors" in m.vertex:
            colors = np.clip(m.vertex["colors"].cpu().numpy().astype(np.float64), 0.0, 1.0)
        # canonical order: Open3D's hash map orders blocks by the thread schedule
        return TriMesh(v, f, name="tsdf", vertex_colors=colors).canonical()

    def extract_point_cloud(self, weight_threshold: float | None = None
                            ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Surface points (N, 3) metres, colours (N, 3) in [0, 1] or None, normals (N, 3)."""
        w = self.config.mesh_weight_threshold if weight_threshold is None else weight_threshold
        w = max(float(w) - 0.5, 0.0)  # Open3D keeps weights strictly above; weights count frames
        if self.num_blocks == 0:
            return np.zeros((0, 3)), None, np.zeros((0, 3))
        try:
            pc = self.vbg.extract_point_cloud(w)
        except RuntimeError as e:
            if "shape {0}" in str(e):
                return np.zeros((0, 3)), None, np.zeros((0, 3))
            raise
        pts = pc.point["positions"].cpu().numpy().astype(np.float64)
        nrm = pc.point["normals"].cpu().numpy().astype(np.float64) if "normals" in pc.point \
            else np.zeros_like(pts)
        col = None
        if self.config.integrate_color and "colors" in pc.point:
            col = np.clip(pc.point["colors"].cpu().numpy().astype(np.float64), 0.0, 1.0)
        return pts, col, nrm

    # ---------------------------------------------------------------- persistence
    def save(self, path: str | os.PathLike) -> None:
        """Write the volume as ``path`` (Open3D npz) plus ``path``.json with its config."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.vbg.save(str(path))
        from data_tools.results import atomic_write_json
        atomic_write_json(str(path) + ".json",
                          {"tsdf": config_to_dict(self.config), "frames_integrated": self.frames_integrated})

    @classmethod
    def load(cls, path: str | os.PathLike) -> "TSDFVolume":
        path = Path(path)
        meta_path = Path(str(path) + ".json")
        if not path.is_file():
            raise FormatError(path, "TSDF volume file not found")
        if not meta_path.is_file():
            raise FormatError(meta_path, "TSDF volume description not found")
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as e:
            raise FormatError(meta_path, f"not valid JSON ({e.msg})") from None
        vol = cls(config_from_dict(TSDFConfig, meta.get("tsdf", {}), str(meta_path), strict=True))
        o3d = o3d_quiet()
        try:
            vol.vbg = o3d.t.geometry.VoxelBlockGrid.load(str(path)).to(vol.device)
        except Exception as e:
            raise FormatError(path, f"cannot read the voxel block grid ({e})") from None
        vol.frames_integrated = int(meta.get("frames_integrated", 0))
        return vol
