"""Direct model: random depth noise along the viewing axis."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from synth.sensor.effects._common import (check_draw, cos_incidence, locally_flat, measured_samples, normal_draw,
                                          robust_std)
from synth.sensor.registry import STAGE_DEPTH, Effect, Signature, param, register_effect


@dataclass
class AxialNoiseParams:
    sigma0_m: float = param(0.0, "m")
    """Constant part of the std, metres."""
    sigma1: float = param(0.0, "1")
    """Part growing linearly with depth (std = sigma1 * z), dimensionless."""
    sigma2_per_m: float = param(0.0014, "1/m")
    """Part growing with the squared depth: sigma2 (z - z_offset)^2, 1/metres."""
    z_offset_m: float = param(0.0, "m")
    """Depth offset of the quadratic part, metres."""
    reflectance_exponent: float = param(0.0, "1")
    """std is multiplied by (albedo cos(incidence))^-exponent (ToF: 0.5, shot-noise-limited
    phase noise grows as the amplitude falls; structured light: 0)."""
    incidence_m: float = param(0.0, "m")
    """Incidence term of the std (Nguyen, Izadi & Lovell 2012's Kinect v1 axial model):
    + incidence_m theta^2 / (pi/2 - theta)^2 / sqrt(z / 1 m), theta the angle between the camera ray
    and the surface normal (capped at :data:`MAX_INCIDENCE_DEG`); their fit is 1e-4 m. Metres.
    Its distance law is ``incidence_z_exponent``."""
    incidence_z_exponent: float = param(-0.5, "1")
    """The incidence term grows as (z / 1 m)^incidence_z_exponent: -0.5 is Nguyen et al. 2012's
    empirical 1 / sqrt(z); 2 makes the term constant in disparity (the matcher's disparity error
    grows with the slant of the surface - elongated, dimmer dots, a broader correlation peak - and
    turns into depth as z^2 / (f b), the same law as the noise itself: Khoshelham & Elberink 2012),
    which the grazing floor and table of 7-Scenes chess follow better beyond 2 m (docs/sensor_lab.md).
    Dimensionless; fitted on planar references only."""


MAX_INCIDENCE_DEG = 85.0
"""The incidence term's angle is capped here (its factor is then 289: it grows without bound at 90)."""


def incidence_factor(theta_rad: np.ndarray) -> np.ndarray:
    """theta^2 / (pi/2 - theta)^2 (Nguyen et al. 2012), theta capped at :data:`MAX_INCIDENCE_DEG`:
    0 at normal incidence, 1 at 45 deg, 4 at 60, 64 at 80."""
    t = np.minimum(np.asarray(theta_rad, np.float64), np.radians(MAX_INCIDENCE_DEG))
    return t ** 2 / (np.pi / 2 - t) ** 2


def _native_fb_ratio(preset) -> float:
    """native f b / this preset's f b for a triangulating preset derived from a named device preset
    (e.g. its intrinsics scaled to a smaller image), at least 1; 1 for ToF or an unknown name."""
    if getattr(preset, "type", "") == "tof" or not preset.fb > 0:
        return 1.0
    from synth.sensor.presets import PRESETS
    native = PRESETS.get(preset.name)
    if native is None or not native.fb > 0:
        return 1.0
    return max(1.0, float(native.fb) / float(preset.fb))


@register_effect
class AxialNoise(Effect):
    """z += sigma(z) n, n ~ N(0, 1), sigma(z) = sigma0 + sigma1 z + sigma2 (z - z_offset)^2
    (+ the incidence term incidence_m theta^2 / (pi/2 - theta)^2 z^incidence_z_exponent; Nguyen et al.
    2012: z^-0.5).

    Physics: a triangulating sensor measures disparity d = f b / z with a roughly constant
    error sigma_d, so sigma_z = z^2 sigma_d / (f b) (Khoshelham & Elberink 2012: 1.425e-5 Z^2
    with Z in cm, i.e. sigma2 = 1.4e-3 /m; Nguyen et al. 2012: 0.0012 + 0.0019 (z - 0.4)^2 m).
    A ToF sensor's phase noise scales with 1/amplitude: use sigma1 and reflectance_exponent.
    The physical pipeline gets its noise from IR capture + matching instead. Draw: one
    N(0, 1) per pixel.
    """

    name = "axial_noise"
    SIGNATURE = Signature(
        "noise growing with z²",
        "The robust spread of the error grows roughly with the square of the distance; the ideal "
        "model has none.",
        panels=(("distance", "std"), ("distance", "bias"), ("incidence", "std")))
    IDENTITY_PARAMS = {"sigma0_m": 0.0, "sigma1": 0.0, "sigma2_per_m": 0.0}
    DRAW_FROM_SHAPE = True
    Params = AxialNoiseParams
    FITTABLE = {"sigma0_m": (0.0, 0.1), "sigma1": (0.0, 0.1), "sigma2_per_m": (0.0, 0.05),
                "z_offset_m": (0.0, 2.0), "reflectance_exponent": (0.0, 2.0), "incidence_m": (0.0, 0.005),
                "incidence_z_exponent": (-0.5, 2.0)}
    PLANE_ONLY = ("incidence_m", "incidence_z_exponent")
    """The incidence term is fitted on planar references only: the noise-curve term there compares
    the spread per distance and incidence (:func:`synth.lab.calibration.noise_curve`); the gap's
    pooled error distributions elsewhere cannot separate it from the distance terms."""
    FITTABLE_FOR = {"reflectance_exponent": ("tof",), "sigma1": ("tof",)}
    """Triangulation noise neither scales with the amplitude nor grows linearly with depth (it is
    constant in disparity: sigma0 + sigma2 z^2, Nguyen et al. 2012); fitting sigma1 there only
    trades off against sigma2 (seen on the two halves of TUM fr1/xyz: 0.0037 z^2 against
    0.0027 z + 0.0014 z^2). sigma0 and sigma2 still trade off over a narrow depth range."""
    stage = STAGE_DEPTH

    @classmethod
    def plausible_bounds(cls, preset) -> dict[str, tuple[float, float]]:
        """Relative to the device's own noise model (the preset's axial_noise defaults; 2 mm at
        1 m when it has none): sigma at 1 m s1 = sigma0 + sigma1 + sigma2 (1 - z_offset)^2.
        sigma0 <= 5 s1 and sigma1 <= 5 s1 / 1 m (a noise floor five times the device's whole
        noise at 1 m is a different device or another effect's errors), sigma2 <= 5 x the preset's
        sigma2 (or 5 s1 / 1 m^2 when it has none): published Kinect v1 values span 1.2e-3 -
        1.9e-3 /m (Nguyen et al. 2012, Khoshelham & Elberink 2012), so 5x covers worn or hot
        devices and bright rooms. z_offset <= the device's nearest depth: the quadratic's minimum
        (Nguyen's 0.4 m) lies at the near end of the working range; a minimum farther out would
        mean noise falling with distance, which no triangulating or ToF sensor shows.

        Triangulating sensors: a matcher's sub-pixel noise is a fraction of a pixel of the image it
        matches, so the same device imaged with a smaller focal length (a 160 px wide stream of a
        640 px sensor, f b a quarter of the preset's) has up to native f b / f b times the depth
        noise; the noise bounds grow by that ratio (the device preset of the same name gives the
        native f b; never shrunk below 1)."""
        d = dict(preset.effect_params.get(cls.name, {}))
        s0, s1_, s2 = (float(d.get(k, 0.0)) for k in ("sigma0_m", "sigma1", "sigma2_per_m"))
        zo = float(d.get("z_offset_m", 0.0))
        at1 = s0 + s1_ + s2 * (1.0 - zo) ** 2
        if at1 <= 0:
            at1 = 0.002
        k = 5.0 * _native_fb_ratio(preset)
        return {"sigma0_m": (0.0, k * at1), "sigma1": (0.0, k * at1),
                "sigma2_per_m": (0.0, k * (s2 if s2 > 0 else at1)),
                "z_offset_m": (0.0, float(preset.min_depth_m))}

    def sample(self, rng, state):
        return normal_draw(rng, state.shape)

    @classmethod
    def fit_start(cls, measured, config, frames) -> dict[str, float]:
        """The noise level from local residuals: the robust std of the difference of horizontally
        adjacent residuals on one surface (ideal depths within 1 %), divided by sqrt(2), per depth
        bin of 0.25 m (>= 200 pixel pairs) - differences remove every bias that is smooth across
        the image (offsets, distortion bowls, a wrong scale); only pixels whose ideal depth is locally
        flat (within 3 % over 8 px: ``_common.locally_flat``) are used - fattened or shifted edges and
        steep slopes read as noise - unless they fill fewer than two bins: a coarse image whose
        measured pixels all lie on steep surfaces (a floor seen from 1 m at 160 px changes depth by
        several per cent within 8 px, while the flat back wall lies beyond the range limit) then uses
        every pair of horizontal neighbours on one surface (the robust std leaves the few edge pairs out). Triangulation: the residual is taken
        in disparity, f b / z_measured - f b / z_ideal, whose noise sigma_d is the same at every
        depth (and unchanged by a disparity offset applied after the noise), so sigma2 = mean
        sigma_d / (f b) and sigma(z) = sigma2 z^2; ToF: sigma0 + sigma1 z by weighted least
        squares over the bins. The other terms start at 0. Heavy disparity quantisation (a step
        several times the noise) hides the noise from differences - most adjacent pixels read the
        same level, their robust spread is 0 - so when ``config`` quantises the disparity (the
        disparity_quantization start runs first, :attr:`START_PRIORITY`) the noise is read from how
        often adjacent pixels of one surface read different levels (:func:`quantised_noise`); where that
        reads half a step or more (or nothing), the differences' standard deviation less the rounding's
        own variance (:func:`quantised_spread`: their robust spread is a multiple of the step). A bin
        whose pairs split clearly less often than noise-free ones would (:func:`_splits_below_noise_free`)
        is left out while two other bins remain: noise only adds splits, so there a range limit censors
        the pixels to the one level inside it (blind quantisation 4: 3.25-3.5 m just beyond the far
        limit, 0.2 % of its pairs split, read as sigma_d 0.002 px for 0.086). Spatially
        correlated noise (a matching window) makes the estimate low: the search refines it.
        Nothing when fewer than two bins have data."""
        zs, ss, ws = [], [], []
        pairs_z, pairs_d, pairs_m, pairs_i = [], [], [], []
        fb = float(config.preset.fb)
        step = _quantisation_step(config) if fb > 0 else 0.0
        pairs_f = []
        for _, m, r, ok in measured_samples(measured):
            z = r.depth.astype(np.float64)
            flat = locally_flat(np.where(r.hit, z, 0.0))
            if fb > 0:     # triangulation: the residual in disparity (a disparity offset leaves its noise alone)
                with np.errstate(divide="ignore"):
                    dm = np.where(ok & (m > 0), fb / np.maximum(m, 1e-9), np.nan)
                    di = np.where(ok, fb / np.maximum(z, 1e-9), np.nan)
                res = dm - di
            else:
                res = np.where(ok & (m > 0), m - z, np.nan)
            a, b = res[:, :-1], res[:, 1:]
            same = np.abs(z[:, 1:] - z[:, :-1]) < 0.01 * z[:, :-1]
            sel = np.isfinite(a) & np.isfinite(b) & same
            pairs_z.append(z[:, :-1][sel])
            pairs_d.append((b - a)[sel])
            pairs_f.append((flat[:, :-1] & flat[:, 1:])[sel])
            if step > 0:
                pairs_m.append((dm[:, 1:] - dm[:, :-1])[sel])
                pairs_i.append((di[:, 1:] - di[:, :-1])[sel])
        if not pairs_z:
            return {}
        pz, pd, pf = np.concatenate(pairs_z), np.concatenate(pairs_d), np.concatenate(pairs_f)
        if step > 0:
            pm, pi = np.concatenate(pairs_m), np.concatenate(pairs_i)
        bins = np.floor(pz / 0.25)
        flat_bins = np.unique(bins[pf], return_counts=True)[1]
        if (flat_bins >= 200).sum() >= 2:       # else every pair on one surface (see the docstring)
            pz, pd = pz[pf], pd[pf]
            if step > 0:
                pm, pi = pm[pf], pi[pf]
        rng = np.random.default_rng(0)
        censored = []           # quantised bins whose pairs split less often than any noise allows
        for lo in np.arange(0.0, 10.0, 0.25):
            sel = (pz >= lo) & (pz < lo + 0.25)
            if sel.sum() >= 200:
                zs.append(float(np.median(pz[sel])))
                sd = robust_std(pd[sel]) / np.sqrt(2.0)
                if step > 0:
                    idx = np.flatnonzero(sel)
                    if idx.size > 4000:
                        idx = rng.choice(idx, 4000, replace=False)
                    sq = quantised_noise(pm[idx], pi[idx], step)
                    if np.isfinite(sq) and sq < 0.5 * step:     # the differences cannot see below a level
                        sd = sq
                    else:
                        sd = quantised_spread(pd[sel], step)
                        if not np.isfinite(sq) and _splits_below_noise_free(pm[idx], pi[idx], step):
                            censored.append(len(zs) - 1)
                ss.append(sd)
                ws.append(float(np.sqrt(sel.sum())))
        if censored and len(zs) - len(censored) >= 2:
            keep = [k for k in range(len(zs)) if k not in censored]
            zs, ss, ws = [zs[k] for k in keep], [ss[k] for k in keep], [ws[k] for k in keep]
        if len(zs) < 2:
            return {}
        z, s, w = np.asarray(zs), np.asarray(ss), np.asarray(ws)
        name = cls.name
        if fb > 0:          # constant disparity noise sigma_d: sigma_z = z^2 sigma_d / fb, sigma2 = sigma_d / fb
            s2 = float(np.sum(w * s) / np.sum(w)) / fb
            return {f"{name}.sigma2_per_m": s2, f"{name}.sigma0_m": 0.0, f"{name}.sigma1": 0.0,
                    f"{name}.z_offset_m": 0.0}
        A = np.stack([np.ones_like(z), z], 1) * w[:, None]
        (s0, s1), *_ = np.linalg.lstsq(A, s * w, rcond=None)
        return {f"{name}.sigma0_m": float(max(s0, 0.0)), f"{name}.sigma1": float(max(s1, 0.0)),
                f"{name}.sigma2_per_m": 0.0}

    def sigma(self, z: np.ndarray, state=None) -> np.ndarray:
        p = self.params
        s = p.sigma0_m + p.sigma1 * z + p.sigma2_per_m * (z - p.z_offset_m) ** 2
        if p.incidence_m and state is not None:
            v = state.view
            cos_t, _ = cos_incidence(v, np.zeros(3, np.float32))
            theta = np.arccos(np.clip(cos_t, 0.0, 1.0))
            s = s + p.incidence_m * incidence_factor(theta) * np.maximum(z, 0.05) ** p.incidence_z_exponent
        if p.reflectance_exponent and state is not None:
            v = state.view
            cos_i, _ = cos_incidence(v, state.preset.projector_offset_m)
            a = np.clip(v.albedo * cos_i, 0.02, 1.0)
            s = s * a ** (-p.reflectance_exponent)
        return s.astype(np.float32)

    def apply(self, state, draw) -> None:
        n = check_draw(draw, "n", state.shape, self.name)
        z = state.depth
        s = self.sigma(z, state)
        state.depth = np.where(state.valid, z + s * n, 0.0).astype(np.float32)
        state.valid &= state.depth > 0
        vz = state.valid
        state.log[self.name] = {"mean_sigma_m": float(s[vz].mean()) if vz.any() else 0.0}


def _quantisation_step(config) -> float:
    """The disparity step (px) of ``config``'s enabled disparity_quantization (its fitted or start
    ``step_px``, else the device's matching step); 0 without one."""
    if "disparity_quantization" not in config.names(enabled_only=True):
        return 0.0
    step = float(config.effect("disparity_quantization").params.step_px or 0.0)
    if step <= 0:
        from synth.sensor.matching import MatchSetup
        step = float(MatchSetup.for_preset(config.preset).step)
    return step


def _level_pairs(measured_diff: np.ndarray, ideal_diff: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """The adjacent pairs the quantised-noise estimates count, as (measured, ideal) disparity
    differences (N,) px: both finite and the measured ones less than 2.5 steps apart (a larger one is
    an edge or a mismatch) - one selection for the measured and the noise-free side alike."""
    md, idf = np.asarray(measured_diff, np.float64), np.asarray(ideal_diff, np.float64)
    keep = np.isfinite(md) & np.isfinite(idf) & (np.abs(md) < 2.5 * step)
    return md[keep], idf[keep]


def _split_share(measured_diff: np.ndarray, step: float) -> float:
    """Share of adjacent pairs on different levels (their measured disparities ``measured_diff`` (N,)
    more than half a step apart, edges beyond 2.5 steps left out, as :func:`quantised_noise` counts)."""
    md = np.asarray(measured_diff, np.float64)
    md = md[np.isfinite(md) & (np.abs(md) < 2.5 * step)]
    return float(np.mean(np.abs(md) > 0.5 * step)) if md.size else float("nan")


def _split_share_noise_free(ideal_diff: np.ndarray, step: float) -> float:
    """The share of pairs on different levels without noise at a uniform phase: mean min(|t| / step, 1)
    of the ideal differences ``ideal_diff`` (N,) (:func:`quantised_noise`'s model at sigma 0)."""
    t = np.asarray(ideal_diff, np.float64)
    t = t[np.isfinite(t)]
    return float(np.mean(np.minimum(np.abs(t) / step, 1.0))) if t.size else float("nan")


SPLIT_DEFICIT_SDS = 3.0
"""Binomial standard errors by which adjacent pairs must split less often than noise-free ones at a
uniform phase for :func:`_splits_below_noise_free` (noise only adds splits: fewer is stuck levels)."""


def _splits_below_noise_free(measured_diff: np.ndarray, ideal_diff: np.ndarray, step: float) -> bool:
    """True when the pairs (``measured_diff``, ``ideal_diff`` (N,) px, as :func:`quantised_noise`) read
    different levels less often than noise-free pairs would, by more than :data:`SPLIT_DEFICIT_SDS`
    binomial standard errors: noise only adds splits, so a deficit means levels held where the ideal
    disparity crosses them - pixels a range limit censors to the one level inside it, not a small noise
    (whose share lies at or just above the noise-free one)."""
    md, idf = _level_pairs(measured_diff, ideal_diff, step)
    share, p0, n = _split_share(md, step), _split_share_noise_free(idf, step), md.size
    if not (n and np.isfinite(share) and np.isfinite(p0)):
        return False
    return share < p0 - SPLIT_DEFICIT_SDS * math.sqrt(max(p0 * (1.0 - p0), 1e-12) / n)


def quantised_spread(diff: np.ndarray, step: float) -> float:
    """The disparity noise sigma_d (px) from differences ``diff`` (N,) of adjacent pixels' residuals
    (px) when the disparities are quantised to levels ``step`` px apart and the noise is about half
    a step or more (where :func:`quantised_noise` stops).

    Two corrections of the plain robust spread: (1) the differences are multiples of the step (plus
    the small ideal differences), so 1.4826 x their median absolute deviation is itself a multiple
    of the step - 1.4826 step / sqrt(2) = 1.05 step whatever the noise from about 0.35 to 0.9 step
    (at step / noise 2 it read 0.131 px for 0.0625); the spread is the standard deviation instead, of
    the differences within max(4 x the robust spread, 3 steps) of their median (edges and mismatches
    left out; a clip at > 3.7 sigma loses < 0.5 % of the spread); (2) Sheppard's correction: rounding
    to a level adds an error uniform over one step (variance step^2 / 12), independent of the noise
    once it is about half a step or more, so sigma_d^2 = var(diff) / 2 - step^2 / 12 (without it the
    estimate is 15 % high at step / noise 2). When the spread is at or below the rounding's own (the
    noise is not resolved) the result is 10 % of the spread: a small positive start the search
    refines. NaN without differences."""
    d = np.asarray(diff, np.float64)
    d = d[np.isfinite(d)]
    if not d.size:
        return float("nan")
    med = float(np.median(d))
    clip = max(4.0 * robust_std(d), 3.0 * float(step))
    v = float(np.mean((d[np.abs(d - med) <= clip] - med) ** 2)) / 2.0
    return float(np.sqrt(max(v - float(step) ** 2 / 12.0, 0.01 * v)))


_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(24)
_GH_W = _GH_W / _GH_W.sum()


def quantised_noise(measured_diff: np.ndarray, ideal_diff: np.ndarray, step: float) -> float:
    """The disparity noise sigma_d (px) under a quantisation of ``step`` px, from pairs of adjacent
    pixels on one surface: ``measured_diff`` (N,) the difference of their measured disparities (a
    multiple of the step), ``ideal_diff`` (N,) of their ideal ones.

    With the level grid at a uniformly distributed phase relative to the pixels' disparities, two
    values x and x + t fall in different levels with probability min(|t| / step, 1); here t =
    ideal_diff + n2 - n1 with n ~ N(0, sigma_d^2), so P(different levels) = E[min(|ideal_diff + sqrt(2)
    sigma_d N(0, 1)| / step, 1)] (Gauss-Hermite quadrature). The observed share of pairs on different
    levels (pairs more than 2.5 steps apart - an edge, a mismatch - are left out) is matched by a
    search over sigma_d in [0.002, 2] steps. NaN when fewer than 100 pairs, or when the share is at
    the noise-free rate or above the largest modelled one."""
    md, idf = _level_pairs(measured_diff, ideal_diff, step)
    if md.size < 100:
        return float("nan")
    observed = float(np.mean(np.abs(md) > 0.5 * step))
    sig = np.geomspace(0.002, 2.0, 80) * step
    t = idf[None, :, None] + np.sqrt(2.0) * sig[:, None, None] * _GH_X[None, None, :]
    p = (np.minimum(np.abs(t) / step, 1.0) * _GH_W).sum(-1).mean(-1)      # (80,) increasing in sigma
    if observed <= p[0] or observed >= p[-1]:
        return float("nan")
    return float(np.interp(observed, p, sig))
