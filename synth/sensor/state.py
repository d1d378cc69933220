"""Per-frame state of the sensor simulation and the per-view geometry it starts from.

:class:`ViewGeometry` is what one camera (the IR camera, or the second IR camera of an active
stereo rig) sees: per-pixel surface samples in that camera's frame, with materials. It is
built from the ideal :class:`synth.render.RenderResult` or by casting rays through the
renderer (rolling shutter: one pose per image row).

:class:`SensorState` carries the ideal inputs and the working arrays every effect reads and
writes (depth, valid mask, radiance, IR image, disparity). Shapes are (H, W) image layout,
depth in metres, disparity in pixels, radiance in relative units (1 = a white Lambertian
surface facing the projector at 1 m, lit by a pattern value of 1).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import RealgapError


@dataclass
class ViewGeometry:
    """Surface samples seen by one camera (arrays (H, W, ...), float32, 0 where no hit)."""

    points_cam: np.ndarray
    """(H, W, 3) hit points in the frame of the camera at the time its row was exposed, metres."""
    normals_cam: np.ndarray
    """(H, W, 3) unit normals in that frame, facing the camera."""
    hit: np.ndarray
    """(H, W) bool."""
    instance_ids: np.ndarray
    """(H, W) int32, k + 1 for scene.meshes[k], 0 = none."""
    albedo: np.ndarray
    """(H, W) diffuse reflectance in [0, 1]."""
    specular: np.ndarray
    """(H, W) mirror-lobe weight in [0, 1]."""
    points_world: np.ndarray
    """(H, W, 3) hit points in the world frame, metres."""
    row_c2w: np.ndarray
    """(H, 4, 4) float64 camera-to-world pose of each image row (all equal for a global shutter)."""

    @property
    def depth(self) -> np.ndarray:
        """(H, W) float32 z-depth, metres (0 = no hit)."""
        return np.where(self.hit, self.points_cam[..., 2], np.float32(0.0)).astype(np.float32, copy=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.hit.shape

    @property
    def global_shutter(self) -> bool:
        """True when every row has the same pose."""
        return bool(np.all(self.row_c2w == self.row_c2w[0]))

    def cam_point_rows(self, offset_cam) -> np.ndarray:
        """(H, 3) float64 world position, at each row's pose, of a point fixed in the camera
        frame (e.g. the projector), metres."""
        off = np.asarray(offset_cam, dtype=np.float64)
        return self.row_c2w[:, :3, :3] @ off + self.row_c2w[:, :3, 3]


def geometry_from_render(render, renderer, pose_c2w: np.ndarray) -> ViewGeometry:
    """ViewGeometry of an ideal :class:`synth.render.RenderResult` (global shutter)."""
    hit = np.asarray(render.hit, dtype=bool)
    H, W = hit.shape
    pts = render.points_cam
    ids = np.asarray(render.instance_ids, dtype=np.int32)
    if renderer is not None:
        albedo, spec = renderer.albedo_specular(ids, check=False)
    else:
        albedo = np.where(hit, np.float32(0.5), np.float32(0.0))
        spec = np.zeros((H, W), np.float32)
    rows = np.broadcast_to(np.asarray(pose_c2w, dtype=np.float64), (H, 4, 4))
    return ViewGeometry(pts.astype(np.float32, copy=False), np.asarray(render.normals_cam, np.float32), hit, ids,
                        np.asarray(albedo, np.float32), np.asarray(spec, np.float32),
                        np.asarray(render.points_world, np.float32), rows)


def _cast(renderer, origins: np.ndarray, dirs: np.ndarray) -> dict:
    """First hits of unit rays (N, 3) float32: the renderer's RaycastingScene queried directly
    (its public ``raycasting_scene`` and ``geometry_to_mesh``), skipping the float64
    validation of ``IdealRenderer.cast_rays``; falls back to ``cast_rays`` for other renderers.
    Normals face the ray origin, as in ``cast_rays``."""
    rs = getattr(renderer, "raycasting_scene", None)
    g2m = getattr(renderer, "geometry_to_mesh", None)
    if rs is None or g2m is None:
        return renderer.cast_rays(origins, dirs)
    import open3d as o3d
    from synth.jit import n_threads
    rays = np.empty((len(origins), 6), np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    out = rs.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=n_threads())
    t = out["t_hit"].numpy()
    hit = np.isfinite(t)
    gid = out["geometry_ids"].numpy()
    lut = np.zeros(len(g2m) + 1, np.int32)
    lut[:-1] = np.asarray(g2m) + 1
    ids = lut[np.minimum(gid, len(g2m)).astype(np.intp)]
    n = out["primitive_normals"].numpy()
    facing = n[:, 0] * dirs[:, 0] + n[:, 1] * dirs[:, 1] + n[:, 2] * dirs[:, 2]
    sign = np.where(facing > 0, np.float32(-1.0), np.float32(1.0)) * hit
    return {"t_hit": t, "instance_ids": ids, "normals_world": n * sign[:, None]}


def cast_view(renderer, ray_dirs_cam: np.ndarray, row_c2w: np.ndarray,
              origin_offset_cam=(0.0, 0.0, 0.0)) -> ViewGeometry:
    """Ray-cast the view of a camera whose row v has pose ``row_c2w[v]`` (H, 4, 4) or (4, 4).

    With a rasterising renderer (:meth:`synth.render.IdealRenderer.render_rows`, when
    ``ray_dirs_cam`` is its cached ray grid) the view is rasterised per band of rows with
    exact per-row depth; otherwise one Open3D ray per pixel is cast.

    ``origin_offset_cam`` puts the camera centre at that point of the rig frame (the second
    camera of a stereo rig); the returned geometry is in the frame of that camera (same
    orientation as the rig). ``ray_dirs_cam`` (H, W, 3) unit directions of its pixels.
    Per-pixel rotations are written out component-wise in float32 (no (N, 3) matmuls).
    """
    H, W, _ = ray_dirs_cam.shape
    row_c2w = np.asarray(row_c2w, dtype=np.float64)
    if row_c2w.shape == (4, 4):
        row_c2w = np.broadcast_to(row_c2w, (H, 4, 4))
    R64 = row_c2w[:, :3, :3]
    off = np.asarray(origin_offset_cam, dtype=np.float64)
    rows = row_c2w.copy()
    rows[:, :3, 3] = R64 @ off + row_c2w[:, :3, 3]                           # the camera centre per row
    intr = renderer.intrinsics_of(ray_dirs_cam) if hasattr(renderer, "intrinsics_of") else None
    if intr is not None:
        out = renderer.render_rows(rows, intr)
        if out is not None:  # the rasteriser (synth.raster): same surfaces, exact depth per row
            albedo, spec = renderer.albedo_specular(out["instance_ids"], check=False)
            return ViewGeometry(out["points_cam"], out["normals_cam"], out["hit"], out["instance_ids"],
                                np.asarray(albedo, np.float32), np.asarray(spec, np.float32), out["points_world"],
                                rows)
    origin_rows = rows[:, :3, 3].astype(np.float32)                           # (H, 3)
    R = R64.astype(np.float32)
    d = [ray_dirs_cam[..., k] for k in range(3)]
    N = H * W
    dirs_w = np.empty((N, 3), np.float32)
    origins = np.empty((N, 3), np.float32)
    for i in range(3):
        dirs_w[:, i] = (d[0] * R[:, i, 0:1] + d[1] * R[:, i, 1:2] + d[2] * R[:, i, 2:3]).ravel()
        origins[:, i] = np.broadcast_to(origin_rows[:, i:i + 1], (H, W)).ravel()
    out = _cast(renderer, origins, dirs_w)
    t = np.asarray(out["t_hit"], np.float32).reshape(H, W)
    hit = np.isfinite(t)
    t0 = np.where(hit, t, np.float32(0.0))
    pts_cam = ray_dirs_cam * t0[..., None]
    n_w = np.asarray(out["normals_world"], np.float32).reshape(H, W, 3)
    n_cam = np.empty((H, W, 3), np.float32)
    for j in range(3):  # n_cam = R^T n_world
        n_cam[..., j] = n_w[..., 0] * R[:, 0, j:j + 1] + n_w[..., 1] * R[:, 1, j:j + 1] + n_w[..., 2] * R[:, 2, j:j + 1]
    ids = np.asarray(out["instance_ids"], np.int32).reshape(H, W)
    albedo, spec = renderer.albedo_specular(ids)
    if "points_world" in out:
        pw = np.asarray(out["points_world"], np.float32).reshape(H, W, 3)
    else:
        pw = (origins + dirs_w * t0.reshape(-1, 1)).reshape(H, W, 3)
    pw = np.where(hit[..., None], pw, np.float32(0.0))
    rows[:, :3, 3] = origin_rows  # the float32 origins the rays were cast from
    return ViewGeometry(pts_cam.astype(np.float32, copy=False), n_cam, hit, ids, np.asarray(albedo, np.float32),
                        np.asarray(spec, np.float32), pw, rows)


def plane_view(ray_dirs_cam: np.ndarray, z0: float, albedo: float = 1.0) -> ViewGeometry:
    """Analytic view of a fronto-parallel plane at depth ``z0`` (the reference-pattern plane)."""
    H, W, _ = ray_dirs_cam.shape
    t = (z0 / ray_dirs_cam[..., 2]).astype(np.float32)
    pts = ray_dirs_cam * t[..., None]
    nrm = np.zeros((H, W, 3), np.float32)
    nrm[..., 2] = -1.0
    hit = np.ones((H, W), bool)
    rows = np.broadcast_to(np.eye(4), (H, 4, 4))
    return ViewGeometry(pts.astype(np.float32), nrm, hit, np.ones((H, W), np.int32),
                        np.full((H, W), albedo, np.float32), np.zeros((H, W), np.float32),
                        pts.astype(np.float32), rows)


def empty_view(shape: tuple[int, int]) -> ViewGeometry:
    """A view where nothing is hit (scene without geometry in view)."""
    H, W = shape
    z3 = np.zeros((H, W, 3), np.float32)
    z = np.zeros((H, W), np.float32)
    return ViewGeometry(z3, z3.copy(), np.zeros((H, W), bool), np.zeros((H, W), np.int32), z, z.copy(),
                        z3.copy(), np.broadcast_to(np.eye(4), (H, 4, 4)))


# ------------------------------------------------------------------------------------------
# Camera motion within a frame
# ------------------------------------------------------------------------------------------

def _so3_log(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(R).as_rotvec()


def _so3_exp(w: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(w).as_matrix()


def interpolate_pose(pose_c2w: np.ndarray, prev_pose_c2w: np.ndarray, s) -> np.ndarray:
    """Pose(s) on the constant-velocity path through ``prev_pose`` (s = -1) and ``pose`` (s = 0).

    Rotation: geodesic (world-frame angular velocity); translation: linear. ``s`` is a scalar
    or an (N,) array (time in units of the frame period); returns (4, 4) or (N, 4, 4).
    """
    T1 = np.asarray(pose_c2w, dtype=np.float64)
    T0 = np.asarray(prev_pose_c2w, dtype=np.float64)
    s_arr = np.atleast_1d(np.asarray(s, dtype=np.float64))
    w = _so3_log(T1[:3, :3] @ T0[:3, :3].T)        # world-frame rotation over one frame
    v = T1[:3, 3] - T0[:3, 3]
    out = np.tile(np.eye(4), (len(s_arr), 1, 1))
    out[:, :3, :3] = _so3_exp(s_arr[:, None] * w[None, :]) @ T1[:3, :3]
    out[:, :3, 3] = T1[:3, 3] + s_arr[:, None] * v[None, :]
    return out[0] if np.ndim(s) == 0 else out


@dataclass
class DrawContext:
    """What :meth:`Effect.sample` of an effect with ``DRAW_FROM_SHAPE`` may read: a stand-in
    for the :class:`SensorState` in the background thread that draws such effects while the
    simulator runs the stages before them."""

    preset: Any
    """The :class:`~synth.sensor.presets.SensorPreset`."""
    intr: Intrinsics
    """Intrinsics of the frame's arrays."""
    physical: bool
    """True when the model runs the physical pipeline."""
    is_reference: bool = False
    """Always False: the reference image uses null draws."""

    @property
    def shape(self) -> tuple[int, int]:
        return self.intr.shape


@dataclass(frozen=True)
class FrameContext:
    """When a frame is taken and how the camera moves during it (read by the motion effects)."""

    pose_c2w: np.ndarray
    """(4, 4) camera-to-world pose of the frame (the row at the image centre), metres."""
    prev_pose_c2w: np.ndarray | None = None
    """(4, 4) pose one frame period earlier (None = a static camera)."""
    frame_dt_s: float = 1.0 / 30.0
    """Frame period, seconds."""
    index: int | None = None
    """Number of the frame in its sequence (None = a single frame)."""
    timestamp_s: float | None = None
    """Timestamp of the frame, seconds (None = not known)."""
    exposure_s: float = 0.0
    """Exposure time, seconds: the value of the model's effect that declares
    ``FRAME_EXPOSURE_PARAM`` (motion_blur's ``exposure_s``), else 0 (instantaneous)."""

    @property
    def moving(self) -> bool:
        """True when the camera moved since the previous frame."""
        return self.prev_pose_c2w is not None and not np.array_equal(self.prev_pose_c2w, self.pose_c2w)

    def pose_at(self, s) -> np.ndarray:
        """Pose(s) at time ``s`` frame periods after the frame's (scalar or (N,) array; s = -1 is
        the previous frame) on the constant-velocity path (:func:`interpolate_pose`)."""
        prev = self.pose_c2w if self.prev_pose_c2w is None else self.prev_pose_c2w
        return interpolate_pose(self.pose_c2w, prev, s)

    @property
    def linear_velocity_m_s(self) -> np.ndarray:
        """(3,) velocity of the camera centre in the world frame, metres per second (0 when static)."""
        if self.prev_pose_c2w is None:
            return np.zeros(3)
        return (np.asarray(self.pose_c2w, np.float64)[:3, 3] - np.asarray(self.prev_pose_c2w, np.float64)[:3, 3]) \
            / self.frame_dt_s

    @property
    def angular_velocity_rad_s(self) -> np.ndarray:
        """(3,) angular velocity of the camera in the world frame, radians per second (0 when static)."""
        if self.prev_pose_c2w is None:
            return np.zeros(3)
        R1 = np.asarray(self.pose_c2w, np.float64)[:3, :3]
        R0 = np.asarray(self.prev_pose_c2w, np.float64)[:3, :3]
        return _so3_log(R1 @ R0.T) / self.frame_dt_s


PRODUCTS = {
    "row_time_frames": "(H,) float64 time of each image row relative to the frame, in frame periods "
                       "(rolling_shutter); absent = every row at 0",
    "projector": "ProjectorProduct: the blurred pattern and the projection parameters (pattern_projection), "
                 "for effects that re-compute the radiance at other poses (motion_blur)",
    "projector_shadow": "(H, W) bool pixels whose surface the projector does not light (pattern_projection's "
                        "shadow test), for effects that re-compute the radiance of nearby sub-exposure views",
    "projector_shading": "(H, W) float32 radiance per unit pattern value of each pixel (pattern_projection, "
                         "moving frames only): fall-off, incidence, material and shadow, for motion_blur's "
                         "sub-exposures",
    "ambient": "(H, W) float32 ambient radiance reaching the IR camera (ambient_light); optics warp it",
    "ambient_second": "(H, W) float32 ambient radiance reaching the second camera (ambient_light)",
}
"""The products one effect publishes for later effects (:meth:`SensorState.publish`), by name."""


@dataclass(frozen=True)
class ProjectorProduct:
    """What ``pattern_projection`` publishes as ``"projector"``."""

    pattern_blurred: np.ndarray
    """The projector pattern image with the dot blur applied (pattern pixels)."""
    params: Any
    """The effect's parameters (power, fall-off, shadow method, ...)."""


@dataclass
class SensorState:
    """Everything one simulated frame reads and writes (see the module docstring)."""

    preset: Any
    """The :class:`~synth.sensor.presets.SensorPreset`."""
    intr: Intrinsics
    """Intrinsics of the arrays below (the padded reference grid when ``is_reference``)."""
    frame: FrameContext
    """Pose, timing and motion of the frame."""
    renderer: Any
    """The :class:`synth.render.IdealRenderer` (None for analytic states such as the reference)."""
    ray_dirs_cam: np.ndarray
    """(H, W, 3) float32 unit ray directions of the IR camera."""
    ideal: ViewGeometry
    """What a perfect camera sees at ``pose_c2w`` (never modified)."""
    view: ViewGeometry
    """What the IR camera sees (rolling shutter may replace it)."""
    depth: np.ndarray
    """(H, W) float32 working depth, metres (0 = invalid)."""
    valid: np.ndarray
    """(H, W) bool working valid mask."""
    model: dict = field(default_factory=dict)
    """{name: Effect} of the enabled effects of this model (for effects that use each other)."""
    physical: bool = False
    """True when the model runs the physical pipeline (pattern_projection is on)."""
    is_reference: bool = False
    """True while the stored reference image is being made (noise-free draws)."""
    pattern: np.ndarray | None = None
    """Physical pipeline: the projector's dot pattern image (pattern pixels, values in [0, 1])."""
    second_view: ViewGeometry | None = None
    """Active stereo: what the second IR camera sees."""
    radiance: np.ndarray | None = None
    """(H, W) float32 radiance reaching the IR camera (relative units), physical pipeline."""
    radiance_second: np.ndarray | None = None
    """Active stereo: (H, W) radiance reaching the second camera."""
    ir: np.ndarray | None = None
    """(H, W) uint16 captured IR image, ADC counts."""
    ir_second: np.ndarray | None = None
    """Active stereo: second camera's captured IR image."""
    ir8: np.ndarray | None = None
    """(H, W) uint8 companded IR image the matcher works on."""
    ir8_second: np.ndarray | None = None
    saturated: np.ndarray | None = None
    """(H, W) bool pixels at full well."""
    disparity: np.ndarray | None = None
    """(H, W) float32 disparity, pixels (structured light: relative to the reference plane,
    1/z = 1/z0 + d/(f b); stereo: d = f b / z); NaN where invalid."""
    reference_ir8: np.ndarray | None = None
    """Structured light: (H, W + pads) uint8 stored reference image."""
    log: dict = field(default_factory=dict)
    """Per-effect notes and statistics (JSON-able)."""
    products: dict = field(default_factory=dict)
    """What effects publish for later effects, by name (:data:`PRODUCTS`); use
    :meth:`publish` and :meth:`product`, never another effect's attributes."""

    @property
    def pose_c2w(self) -> np.ndarray:
        """(4, 4) camera-to-world pose of the frame (``frame.pose_c2w``)."""
        return self.frame.pose_c2w

    def publish(self, name: str, value) -> None:
        """Make ``value`` available to later effects as product ``name`` (one of :data:`PRODUCTS`)."""
        if name not in PRODUCTS:
            raise RealgapError(f"unknown sensor-state product {name!r}; known: {', '.join(PRODUCTS)}")
        self.products[name] = value

    def product(self, name: str, default=None):
        """Product ``name`` published by an earlier effect, or ``default``."""
        if name not in PRODUCTS:
            raise RealgapError(f"unknown sensor-state product {name!r}; known: {', '.join(PRODUCTS)}")
        return self.products.get(name, default)

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape

    def invalidate(self, mask: np.ndarray, effect: str) -> int:
        """Mark ``mask`` invalid (depth 0); logs and returns how many valid pixels were removed."""
        removed = int(np.count_nonzero(mask & self.valid))
        self.valid &= ~mask
        self.depth[~self.valid] = 0.0
        self.log.setdefault(effect, {})["removed_px"] = removed
        return removed

    def baseline_free(self) -> bool:
        """True when the device has no projector/second-camera offset (nothing to shadow)."""
        return float(np.linalg.norm(self.preset.projector_offset_m)) == 0.0 and self.preset.baseline_m == 0.0

    def require_renderer(self, effect: str):
        if self.renderer is None:
            raise RealgapError(f"sensor effect {effect!r} needs a scene renderer (none given)")
        return self.renderer
