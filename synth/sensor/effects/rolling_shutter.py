"""Rolling shutter: image rows are exposed one after the other while the camera moves."""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_GEOMETRY, Effect, Signature, param, register_effect


@dataclass
class RollingShutterParams:
    readout_time_s: float = param(0.03, "s")
    """Time between the exposure of the first and the last row, seconds (0 = global shutter)."""
    reference_row: float = param(0.5, "1")
    """Which row the frame's timestamp and pose belong to, as a fraction of the image height: 0.5 =
    the centre row (a driver that stamps mid-exposure), 0 = the first row (a stamp at the start of
    the readout), 1 = the last. Datasets differ and rarely say; the lab fits it."""


def row_times_frames(H: int, readout_s: float, frame_dt_s: float, reference_row: float = 0.5) -> np.ndarray:
    """(H,) exposure time of each row relative to the reference row (the row exposed at the frame's
    timestamp: a fraction of the height, 0.5 = the centre row), in frame periods."""
    v = np.arange(H, dtype=np.float64)
    return (v / max(H - 1, 1) - reference_row) * readout_s / frame_dt_s


@register_effect
class RollingShutter(Effect):
    """Each row sees the scene from the pose the camera had when that row was exposed.

    Physics: a rolling-shutter CMOS sensor (the Kinect v1 IR camera's) reads rows sequentially
    over ``readout_time_s``; a moving camera therefore sees straight edges sheared and
    surfaces at the wrong depth. The projector is rigid with the camera, so it moves along.
    Implementation: the camera path is the constant-velocity interpolation through
    ``prev_pose`` and ``pose`` (one frame period apart); row v is re-rendered (ray cast) from
    the pose at its exposure time; the row at ``reference_row`` (default the centre) is exposed at
    ``pose``. With a constant velocity, moving the reference row shifts every row's pose by the same
    time (readout x the change): a dataset that stamps the first row's exposure (reference 0) seen
    through a centre-row model needs a global shift no readout can give, so the fitted readout
    comes out several times too long (an independent generator stamping the first row: 0.087 s
    fitted for 0.027 s true) - hence the fitted reference row. Depth is then reported in the frame
    of the row's own pose, as the device does. Runs in both the physical pipeline and the
    direct model (it changes what each pixel sees). No-op for a static camera.
    """

    name = "rolling_shutter"
    SIGNATURE = Signature(
        "edge displacement under motion",
        "Depth edges appear shifted: biased errors on both sides of edges and a bias that changes "
        "across the image.",
        panels=(("edge_distance", "bias"), ("radial", "bias")))
    KEEPS_INVALID = False  # each row is re-rendered at its own pose
    IDENTITY_PARAMS = {"readout_time_s": 0.0}
    Params = RollingShutterParams
    FITTABLE = {"readout_time_s": (0.0, 0.2), "reference_row": (0.0, 1.0)}
    stage = STAGE_GEOMETRY

    def apply(self, state, draw) -> None:
        from synth.sensor.state import cast_view
        rt = self.params.readout_time_s
        if not state.frame.moving or rt <= 0 or state.renderer is None or state.is_reference:
            state.log[self.name] = {"active": False}
            return
        H = state.shape[0]
        s = row_times_frames(H, rt, state.frame.frame_dt_s, self.params.reference_row)
        rows = state.frame.pose_at(s)
        state.view = cast_view(state.renderer, state.ray_dirs_cam, rows)
        state.publish("row_time_frames", s)
        state.depth = state.view.depth
        state.valid = state.view.hit.copy()
        shift = np.linalg.norm(rows[-1, :3, 3] - rows[0, :3, 3])
        state.log[self.name] = {"active": True, "top_to_bottom_translation_m": float(shift)}

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """Readout and reference row from how each row's measured depth sits in time.

        Along the constant-velocity path between a frame's previous pose and its own, the ideal depth
        of every pixel is rendered at times s = -1 .. 1 frame periods (:data:`START_STEPS` steps); a
        row exposed at t_v reads that depth at t_v (linear between two samples on one surface; where
        the pixel changes surface between two samples - a depth edge sweeping across it - the
        nearer sample's surface), plus noise sigma ~ z^2 (triangulation; its level read robustly
        from the measurement). The row times lie on t_v = (v / (H - 1) - reference_row) readout /
        frame period, and (readout, reference_row) minimise the truncated squared error
        sum min(((m - z(t_v)) / sigma)^2, 9) over the moving frames' measured pixels: a grid over
        readout 0 .. one frame period (a rolling shutter reads a frame within the frame's period)
        and reference row 0 .. 1, then finer grids about the best, and a conventional reference row
        (first, centre or last row) kept unless the data clearly ask for another
        (:func:`fit_row_times`). Smooth surfaces tell each
        row's time through the rate of their depth change; edges tell it sharply (which surface the
        pixel saw), and the truncation keeps pixels that other effects changed from pulling. Pixels
        whose depth comes within 3 sigma of the measured depths' range are left out (only their
        draws inside the range are valid: a one-sided residual). Why a start: the gap sees the
        rows' mean time well, readout x (0.5 - reference_row), but the spread of the rows' times
        weakly, so readout and reference row trade along a narrow valley a coarse search does not
        follow. Nothing for a static sequence."""
        from synth.sensor.effects._common import robust_std
        from synth.sensor.state import interpolate_pose
        dt = 1.0 / float(config.preset.fps)
        H = int(measured.intrinsics.height)
        svals = np.linspace(-1.0, 1.0, START_STEPS)
        Z, SAME, V, M, zm_all = [], [], [], [], []
        for k in frames:
            prev = measured.prev_poses[k]
            pose = measured.poses[k]
            if prev is None or np.array_equal(prev, pose):
                continue
            m = measured.measured_depth(k)
            rs = [measured.renderer.render(interpolate_pose(pose, prev, s), measured.intrinsics, with_rgb=False)
                  for s in svals]
            zs = np.stack([np.where(r.hit, r.depth, 0).astype(np.float64) for r in rs])      # (S, H, W)
            ids = np.stack([np.where(r.hit, r.instance_ids, -1) for r in rs])
            ok = (m > 0) & (zs > 0).all(0)
            mask = measured.mask(k)
            if mask is not None:
                ok &= mask
            # a sample pair on one surface interpolates linearly; on two, a step at the nearer sample
            same = (ids[1:] == ids[:-1]) & (np.abs(zs[1:] - zs[:-1]) < 0.05 * zs[:-1])
            vv, uu = np.nonzero(ok)
            Z.append(zs[:, vv, uu])
            SAME.append(same[:, vv, uu])
            M.append(m[vv, uu])
            V.append(vv)
            zm_all.append(m[m > 0])
        if not Z:
            return {}
        z, same = np.concatenate(Z, 1), np.concatenate(SAME, 1)        # (S, N), (S - 1, N)
        m, v = np.concatenate(M), np.concatenate(V)
        zc = z[START_STEPS // 2]
        sig = max(robust_std((m - zc) / zc ** 2), 1e-9) * zc ** 2
        zlo, zhi = np.percentile(np.concatenate(zm_all), [0.1, 99.9])
        inside = (z.max(0) + 3.0 * sig < zhi) & (z.min(0) - 3.0 * sig > zlo)
        moves = (z.max(0) - z.min(0)) > 0.1 * sig            # a pixel whose depth never changes says nothing
        sel = inside & moves
        if sel.sum() < 200:
            return {}
        z, same, m, v, sig = z[:, sel], same[:, sel], m[sel], v[sel], sig[sel]
        x = np.arange(H) / max(H - 1, 1)
        step = svals[1] - svals[0]
        cols = np.arange(m.size)

        def cost(readout: float, ref: float) -> float:
            t = (x[v] - ref) * readout / dt                    # (N,) frame periods
            f = np.clip((t - svals[0]) / step, 0.0, START_STEPS - 1 - 1e-9)
            i = f.astype(np.int64)
            w = f - i
            z0, z1 = z[i, cols], z[i + 1, cols]
            zhat = np.where(same[np.minimum(i, START_STEPS - 2), cols], z0 + w * (z1 - z0), np.where(w < 0.5, z0, z1))
            return float(np.minimum(((m - zhat) / sig) ** 2, 9.0).sum())

        lo, hi = cls.FITTABLE["readout_time_s"]
        R, rho = fit_row_times(cost, lo, min(hi, dt))
        if R <= lo:
            return {}
        return {f"{cls.name}.readout_time_s": float(R), f"{cls.name}.reference_row": float(rho)}


CONVENTIONAL_REFERENCE_ROWS = (0.0, 0.5, 1.0)
"""Reference rows a driver stamps: the start of the readout (first row), mid-exposure (centre row) and
its end (last row)."""

CONVENTION_CHI2 = 3.84
"""Cost increase (chi-square, 1 degree of freedom, 95 %) below which :func:`fit_row_times` prefers a
conventional reference row to the free one."""


def _grid_refine(cost, bounds, points) -> tuple:
    """(cost, x1, x2, ...) minimising ``cost(x1, x2, ...)`` over the box ``bounds`` ((lo, hi) per
    parameter): a grid of ``points`` (one count per parameter, ends included), then three finer
    9-point grids about the best, each a quarter of the step before (clipped to the box). Grid
    points are visited in order (the last parameter fastest) and a later one replaces the best only
    when strictly lower."""
    best = None
    for x in itertools.product(*(np.linspace(lo, hi, n) for (lo, hi), n in zip(bounds, points))):
        c = cost(*x)
        if best is None or c < best[0]:
            best = (c, *x)
    steps = [(hi - lo) / (n - 1) for (lo, hi), n in zip(bounds, points)]
    for _ in range(3):            # finer grids about the best
        x0 = best[1:]
        for x in itertools.product(*(np.clip(c0 + d * np.linspace(-1, 1, 9), lo, hi)
                                     for c0, d, (lo, hi) in zip(x0, steps, bounds))):
            c = cost(*x)
            if c < best[0]:
                best = (c, *x)
        steps = [d / 4 for d in steps]
    return best


def _min_readout(cost, ref: float, lo: float, hi: float) -> tuple[float, float]:
    """(cost, readout) minimising ``cost(readout, ref)`` over readout lo .. hi (s) at a fixed reference
    row (:func:`_grid_refine`, 33 points)."""
    return _grid_refine(lambda R: cost(R, ref), [(lo, hi)], [33])


def fit_row_times(cost, lo: float, hi: float) -> tuple[float, float]:
    """(readout s, reference row) minimising ``cost(readout, reference_row)`` (a negative
    log-likelihood in chi-square units: sum of squared normalised residuals) over readout lo .. hi and
    reference row 0 .. 1.

    The free minimum: a 33 x 17 grid, then three finer grids about the best (:func:`_grid_refine`).
    Why a convention test: the data fix each row's exposure time only where pixels change under the motion; when those lie
    in a band of rows (the floor at the bottom, the top beyond the range limit), only the time of
    that band - readout x (band row - reference row) - is measured, and readout and reference row
    trade along a valley whose floor is flat to within the noise (a free minimum then lands anywhere
    along it, 1.5-2x the true readout). A driver stamps the frame at one of
    :data:`CONVENTIONAL_REFERENCE_ROWS`; the best readout at each of those is kept unless the free
    reference row lowers the cost by more than :data:`CONVENTION_CHI2` (a likelihood-ratio test with
    one degree of freedom): a free reference row is used only when the data ask for it."""
    best = _grid_refine(cost, [(lo, hi), (0.0, 1.0)], [33, 17])
    conv = min((*_min_readout(cost, rho, lo, hi), rho) for rho in CONVENTIONAL_REFERENCE_ROWS)
    if conv[0] <= best[0] + CONVENTION_CHI2:
        return float(conv[1]), float(conv[2])
    return float(best[1]), float(best[2])


START_STEPS = 17
"""Times at which :meth:`RollingShutter.fit_start` renders each moving frame (evenly from one frame
period before to one after the frame's pose: steps of 1/8 period)."""
