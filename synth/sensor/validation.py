"""Flat-wall validation of a simulated depth sensor (DepthSynth thesis, ch. 3 experiments).

A large matte wall is imaged at 0.5-4.5 m and, at a fixed distance, tilted 0-85 degrees about
the vertical axis. For each setting the depth error (measured - ideal) of every valid pixel
gives: its standard deviation vs distance, vs tilt and vs radial distance from the principal
point, the fraction of valid pixels vs tilt, and the depth staircase of the disparity
quantisation. The Kinect v1 curve is compared with the published models

* Khoshelham & Elberink 2012 (Sensors 12:1437): sigma_Z = 1.425e-5 Z^2 (Z in cm), i.e.
  1.4 mm at 1 m and 12.8 mm at 3 m;
* Nguyen, Izadi & Lovell 2012 (3DIMPVT): sigma_z = 0.0012 + 0.0019 (z - 0.4)^2 m;
* the quantisation step dz = z^2 s / (f b) (s = 1/8 px).

The check passes when, for 0.8-4 m, the simulated std lies within +-35 % of the band the two
models span: 0.65 min(models) <= std <= 1.35 max(models).

The experiment moves the camera, not the wall (one scene, one simulator): a camera at
distance z looking at the wall's centre, orbiting that point by the tilt angle, sees exactly the
geometry of a wall tilted about its vertical centre line. Errors are taken over the central
half of the image (the published models are centre values) after rejecting gross mismatches
(|error| > 6 median absolute deviations, counted separately as outliers); the radial profile
uses the whole image.

    res = flat_wall_experiment(FlatWallConfig())      # ~20 s at 640x480 on 2 cores
    res.save("out/")                                  # flat_wall.json + flat_wall.png
"""
from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError

BAND_TOLERANCE = 0.35
"""Allowed relative deviation from the band spanned by the published models."""


def khoshelham_sigma_m(z_m):
    """Khoshelham & Elberink 2012: sigma_Z = 1.425e-5 Z^2 with Z in cm; returns metres."""
    z_cm = np.asarray(z_m, float) * 100.0
    return 1.425e-5 * z_cm ** 2 / 100.0


def nguyen_sigma_m(z_m):
    """Nguyen et al. 2012 axial noise at 10-60 deg incidence: 0.0012 + 0.0019 (z - 0.4)^2 m."""
    z = np.asarray(z_m, float)
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def quantization_step_m(z_m, fb_px_m: float, step_px: float = 0.125):
    """Depth spacing of neighbouring disparity codes: z^2 s / (f b)."""
    return np.asarray(z_m, float) ** 2 * step_px / fb_px_m


@dataclass
class FlatWallConfig:
    """What the flat-wall experiment simulates."""

    preset: str = "kinect_v1"
    """Sensor preset name."""
    effects: str = "physical"
    """``physical``, ``direct`` or a comma-separated effect list."""
    distances_m: tuple[float, ...] = tuple(np.round(np.arange(0.5, 4.51, 0.25), 3))
    """Wall distances of the distance sweep, metres."""
    tilts_deg: tuple[float, ...] = tuple(float(a) for a in range(0, 86, 5))
    """Tilts of the tilt sweep, degrees (rotation about the vertical axis)."""
    tilt_distance_m: float = 1.2
    """Distance of the wall centre in the tilt sweep, metres."""
    staircase_m: tuple[float, float, float] = (1.9, 2.15, 0.004)
    """(start, stop, step) of the fine distance sweep that shows the quantisation staircase."""
    radial_distance_m: float = 2.0
    """Wall distance of the radial profile, metres."""
    frames: int = 2
    """Frames (seeds) per setting."""
    seed: int = 0
    """First seed."""
    crop: tuple[int, int] | None = None
    """Optional centred crop (width, height) of the sensor image (fast tests); None = full."""
    albedo: float = 0.8
    """Wall albedo."""


@dataclass
class FlatWallResult:
    """Curves of the experiment (all lengths in metres, angles in degrees)."""

    config: dict
    fb_px_m: float
    step_px: float
    distances_m: list
    std_m: list
    outlier_fraction: list
    valid_fraction: list
    khoshelham_m: list
    nguyen_m: list
    quant_step_m: list
    tilts_deg: list
    tilt_valid_fraction: list
    tilt_std_m: list
    radial_px: list
    radial_std_m: list
    staircase_true_m: list
    staircase_measured_m: list
    band_ratio: list = field(default_factory=list)
    """std / band edge per distance in 0.8-4 m (< 1: inside the band, see ``band_ok``)."""
    band_ok: bool = False
    dropout_angle_deg: float | None = None
    """Smallest tilt at which fewer than half the wall pixels are valid (interpolated)."""
    shadow_side: str | None = None
    """Where the projector shadow of a box before a wall falls: 'left' or 'right' (image)."""

    def model_band(self, z) -> tuple[np.ndarray, np.ndarray]:
        a, b = khoshelham_sigma_m(z), nguyen_sigma_m(z)
        return np.minimum(a, b), np.maximum(a, b)

    def summary(self) -> dict:
        """std vs the models at 1, 2, 3, 4 m and the dropout angle."""
        out = {}
        d = np.asarray(self.distances_m)
        for z in (1.0, 2.0, 3.0, 4.0):
            i = int(np.argmin(np.abs(d - z)))
            out[f"{z:g}m"] = {"sim_mm": round(self.std_m[i] * 1e3, 2),
                              "khoshelham_mm": round(float(khoshelham_sigma_m(d[i])) * 1e3, 2),
                              "nguyen_mm": round(float(nguyen_sigma_m(d[i])) * 1e3, 2),
                              "quant_step_mm": round(self.quant_step_m[i] * 1e3, 2)}
        out["dropout_angle_deg"] = self.dropout_angle_deg
        out["band_ok"] = self.band_ok
        out["shadow_side"] = self.shadow_side
        return out

    def to_json(self) -> dict:
        return asdict(self)

    def save(self, out_dir: str | os.PathLike, figure: bool = True) -> Path:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        from data_tools.results import atomic_write_json
        atomic_write_json(out / "flat_wall.json", {"summary": self.summary(), **self.to_json()}, indent=1)
        if figure:
            plot_flat_wall(self, out / "flat_wall.png")
        return out


def _robust(e: np.ndarray, step_m: float) -> tuple[float, float]:
    """(std after rejecting gross mismatches, rejected fraction). A mismatch is farther from the
    median than max(6 MAD, 4 quantisation steps): errors are quantised, so the MAD alone can
    be 0 when most pixels share one disparity level."""
    if e.size < 10:
        return float("nan"), float("nan")
    med = np.median(e)
    mad = np.median(np.abs(e - med)) * 1.4826
    lim = max(6 * mad, 4 * step_m, 1e-4)
    keep = np.abs(e - med) <= lim
    return float(np.std(e[keep])), float(1 - keep.mean())


def _pose_looking_at(distance: float, tilt_deg: float, wall_z: float = 5.0) -> np.ndarray:
    """Camera pose orbiting the wall centre (0, 0, wall_z) by ``tilt_deg`` about the vertical
    axis at ``distance``: equivalent to a wall tilted by that angle."""
    t = math.radians(tilt_deg)
    R = np.array([[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([0, 0, wall_z]) - R[:, 2] * distance
    return T


def flat_wall_experiment(config: FlatWallConfig = FlatWallConfig(), progress: bool = False) -> FlatWallResult:
    """Run the flat-wall experiment (see the module docstring)."""
    from synth.sensor import SensorSimulator, get_preset
    from synth.sensor.matching import MatchSetup
    from synth.sensor.testscenes import wall_scene
    pre = get_preset(config.preset)
    if config.crop is not None:
        pre = pre.cropped(*config.crop)
    if pre.type == "tof":
        raise ConfigError("the flat-wall experiment compares triangulation models; use a structured-light preset")
    wall_z = 5.0
    scene = wall_scene(wall_z, size_m=60.0, albedo=config.albedo)
    sim = SensorSimulator(pre, config.effects, scene)
    H, W = pre.height, pre.width
    roi = (slice(H // 4, H - H // 4), slice(W // 4, W - W // 4))
    setup = MatchSetup.for_preset(pre)
    it = _progress(progress)

    def frames(dist, tilt):
        for k in range(config.frames):
            yield sim.simulate(_pose_looking_at(dist, tilt, wall_z), seed=config.seed + k)

    dist, stds, outl, vfrac = [], [], [], []
    for z in it(config.distances_m, "distance"):
        es, vs = [], []
        for r in frames(z, 0.0):
            es.append((r.depth - r.ideal_depth)[roi][r.valid[roi]])
            vs.append(r.valid[roi].mean())
        s, o = _robust(np.concatenate(es), float(quantization_step_m(z, pre.fb, setup.step)))
        dist.append(float(z)); stds.append(s); outl.append(o); vfrac.append(float(np.mean(vs)))
    tv, ts = [], []
    for a in it(config.tilts_deg, "tilt"):
        es, vs = [], []
        for r in frames(config.tilt_distance_m, a):
            inr = (r.ideal_depth > pre.min_depth_m) & (r.ideal_depth < pre.max_depth_m)
            vs.append(r.valid[inr].mean() if inr.any() else 0.0)
            es.append((r.depth - r.ideal_depth)[r.valid & inr])
        tv.append(float(np.mean(vs)))
        ts.append(_robust(np.concatenate(es), float(quantization_step_m(config.tilt_distance_m * 1.5, pre.fb,
                                                                          setup.step)))[0])
    # radial profile at one distance
    rr = []
    ee = []
    uu, vv = np.meshgrid(np.arange(W) - pre.cx, np.arange(H) - pre.cy)
    rad = np.hypot(uu, vv)
    for r in frames(config.radial_distance_m, 0.0):
        rr.append(rad[r.valid]); ee.append((r.depth - r.ideal_depth)[r.valid])
    rr, ee = np.concatenate(rr), np.concatenate(ee)
    edges = np.linspace(0, rad.max() + 1e-6, 9)
    rad_c, rad_s = [], []
    qr = float(quantization_step_m(config.radial_distance_m, pre.fb, setup.step))
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (rr >= lo) & (rr < hi)
        if m.sum() > 50:
            rad_c.append(float((lo + hi) / 2)); rad_s.append(_robust(ee[m], qr)[0])
    # quantisation staircase: median measured depth at the centre vs true distance
    st_t, st_m = [], []
    c = (slice(H // 2 - 4, H // 2 + 4), slice(W // 2 - 4, W // 2 + 4))
    a0, a1, da = config.staircase_m
    for z in it(np.arange(a0, a1, da), "staircase"):
        r = sim.simulate(_pose_looking_at(z, 0.0, wall_z), seed=config.seed)
        if r.valid[c].any():
            st_t.append(float(z)); st_m.append(float(np.median(r.depth[c][r.valid[c]])))
    res = FlatWallResult(asdict(config), float(pre.fb), float(setup.step), dist, stds, outl, vfrac,
                         [float(x) for x in khoshelham_sigma_m(dist)], [float(x) for x in nguyen_sigma_m(dist)],
                         [float(x) for x in quantization_step_m(dist, pre.fb, setup.step)],
                         [float(a) for a in config.tilts_deg], tv, ts, rad_c, rad_s, st_t, st_m)
    # band check over 0.8-4 m
    d = np.asarray(dist)
    sel = (d >= 0.8 - 1e-9) & (d <= 4.0 + 1e-9)
    lo, hi = res.model_band(d[sel])
    s = np.asarray(stds)[sel]
    ratio = np.where(s > hi, s / ((1 + BAND_TOLERANCE) * hi), np.where(s < lo, (1 - BAND_TOLERANCE) * lo / s, 0.0))
    res.band_ratio = [float(x) for x in np.maximum(ratio, 0)]
    res.band_ok = bool(np.all((s >= (1 - BAND_TOLERANCE) * lo) & (s <= (1 + BAND_TOLERANCE) * hi)))
    res.dropout_angle_deg = _crossing(res.tilts_deg, res.tilt_valid_fraction, 0.5 * max(res.tilt_valid_fraction[0], 1e-9))
    res.shadow_side = projector_shadow_side(pre, config.effects)
    return res


def _crossing(x, y, level) -> float | None:
    for i in range(1, len(y)):
        if y[i - 1] >= level > y[i]:
            return float(x[i - 1] + (x[i] - x[i - 1]) * (y[i - 1] - level) / (y[i - 1] - y[i]))
    return None


def projector_shadow_side(preset, effects: str = "physical") -> str:
    """Image a box 0.6 m before a wall and report on which side ('left' / 'right') of the box
    the band of holes lies. Derivation: a projector at +x lights the scene from the image's
    right, so the shadow falls on the far side of the box from it: the LEFT, in a band
    f b (1/z_box - 1/z_wall) pixels wide."""
    from synth.sensor import SensorSimulator
    from synth.sensor.testscenes import box_before_wall_scene, camera_pose
    sc = box_before_wall_scene(2.0, 1.5, 0.2)
    r = SensorSimulator(preset, effects, sc).simulate(camera_pose(), seed=0)
    box = np.abs(r.ideal_depth - 1.4) < 0.01
    rows = np.nonzero(box.any(1))[0]
    cols = np.nonzero(box.any(0))[0]
    rs = slice(rows[0] + 5, rows[-1] - 5)
    band = 14
    left = (~r.valid[rs, max(cols[0] - band, 0):cols[0]]).sum()
    right = (~r.valid[rs, cols[-1] + 1:cols[-1] + 1 + band]).sum()
    return "left" if left > right else "right"


def _progress(enabled: bool):
    if not enabled:
        return lambda xs, desc: xs
    from data_tools.progress import progress_bar
    return lambda xs, desc: progress_bar(list(xs), desc=desc, leave=False)


def plot_flat_wall(res: FlatWallResult, path: str | os.PathLike) -> Path:
    """Four panels: std vs distance (with the published models and the quantisation step),
    the quantisation staircase, valid fraction and std vs tilt, std vs radial distance."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(2, 2, figsize=(12, 9))
    z = np.linspace(0.5, 4.5, 200)
    a = ax[0, 0]
    lo, hi = res.model_band(z)
    a.fill_between(z, (1 - BAND_TOLERANCE) * lo * 1e3, (1 + BAND_TOLERANCE) * hi * 1e3, color="0.88",
                   label="models +-35 %")
    a.plot(z, khoshelham_sigma_m(z) * 1e3, "b--", label="Khoshelham & Elberink 2012")
    a.plot(z, nguyen_sigma_m(z) * 1e3, "g--", label="Nguyen et al. 2012")
    a.plot(z, quantization_step_m(z, res.fb_px_m, res.step_px) * 1e3, "k:", label="quantisation step z^2/(8fb)")
    a.plot(res.distances_m, np.asarray(res.std_m) * 1e3, "ro-", label=f"simulated ({res.config['preset']})")
    a.set_xlabel("distance to the wall z [m]")
    a.set_ylabel("std of depth error [mm]")
    a.set_title("Axial noise vs distance (fronto-parallel wall)")
    a.set_yscale("log")
    a.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=8)
    a = ax[0, 1]
    t = np.asarray(res.staircase_true_m)
    a.plot(t, t, "k--", lw=1, label="ideal")
    a.step(t, res.staircase_measured_m, "r-", where="mid", label="simulated (centre median)")
    a.set_xlabel("true distance [m]")
    a.set_ylabel("measured depth [m]")
    step = quantization_step_m(np.mean(t), res.fb_px_m, res.step_px) * 1e3 if len(t) else float("nan")
    a.set_title(f"Quantisation staircase (dz = {step:.1f} mm at {np.mean(t) if len(t) else 0:.2f} m)")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=8)
    a = ax[1, 0]
    a.plot(res.tilts_deg, res.tilt_valid_fraction, "bo-", label="valid fraction")
    a.set_xlabel("wall tilt (angle between normal and optical axis) [deg]")
    a.set_ylabel("fraction of valid pixels", color="b")
    a.set_ylim(0, 1.05)
    if res.dropout_angle_deg is not None:
        a.axvline(res.dropout_angle_deg, color="b", ls=":", label=f"50 % dropout at {res.dropout_angle_deg:.1f} deg")
    a2 = a.twinx()
    a2.plot(res.tilts_deg, np.asarray(res.tilt_std_m) * 1e3, "rs-", label="std of depth error")
    a2.set_ylabel("std of depth error [mm]", color="r")
    a.set_title(f"Tilted wall at {res.config['tilt_distance_m']} m")
    a.grid(True, alpha=0.3)
    h1, l1 = a.get_legend_handles_labels()
    h2, l2 = a2.get_legend_handles_labels()
    a.legend(h1 + h2, l1 + l2, fontsize=8, loc="center left")
    a = ax[1, 1]
    a.plot(res.radial_px, np.asarray(res.radial_std_m) * 1e3, "mo-", label="simulated")
    zr = res.config["radial_distance_m"]
    a.axhline(khoshelham_sigma_m(zr) * 1e3, color="b", ls="--", label="Khoshelham 2012 (centre)")
    a.axhline(nguyen_sigma_m(zr) * 1e3, color="g", ls="--", label="Nguyen 2012 (centre)")
    a.set_xlabel("radial distance from the principal point [px]")
    a.set_ylabel("std of depth error [mm]")
    a.set_title(f"Noise vs image radius (wall at {zr} m)")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=8)
    fig.suptitle(f"Flat-wall validation: {res.config['preset']} ({res.config['effects']}); "
                 f"band check 0.8-4 m: {'PASS' if res.band_ok else 'FAIL'}; projector shadow: {res.shadow_side}")
    fig.tight_layout()
    path = Path(path)
    from data_tools.results import atomic_save_figure
    atomic_save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path
