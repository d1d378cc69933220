"""Physical stage 2: the IR camera captures the projected pattern."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.jit import kernel, run_row_bands
from synth.sensor.effects._common import check_draw
from synth.sensor.registry import STAGE_CAPTURE, Effect, param, register_effect


@dataclass
class IRCaptureParams:
    gain_e: float = param(30000.0, "e-")
    """Photo-electrons per unit radiance during one exposure (exposure x aperture x QE)."""
    full_well_e: float = param(20000.0, "e-")
    """Full-well capacity, electrons: brighter pixels saturate."""
    read_noise_e: float = param(5.0, "e-")
    """Read noise, electrons RMS."""
    speckle_contrast: float = param(0.1, "1")
    """Laser speckle: std of the multiplicative intensity noise of the pattern (0 = incoherent)."""
    psf_sigma_px: float = param(0.6, "px")
    """Gaussian optical blur (lens PSF + defocus) of the IR camera, pixels."""
    adc_bits: int = param(10, "bit", 6, 16)
    """ADC resolution; the raw image ``state.ir`` is in counts 0 .. 2^bits - 1."""
    companding: str = param("sqrt", "", choices=("sqrt", "linear"))
    """How counts become the 8-bit image the matcher sees: ``sqrt`` (square-root LUT, which
    equalises shot noise over the range) or ``linear``."""


_LUTS: dict = {}
"""(adc bits, companding) -> companding look-up table (pure function of the key)."""


@register_effect
class IRCapture(Effect):
    """Radiance -> IR image: speckle, optical blur, exposure, shot + read noise, saturation, ADC.

    Physics: the coherent laser light forms speckle (multiplicative noise of contrast c on the
    pattern), the lens blurs it (Gaussian PSF), the sensor converts it to electrons
    (``gain_e`` per unit radiance, plus the ambient radiance from ``ambient_light``), photon
    shot noise (Poisson, approximated by a Gaussian of variance S) and read noise are added,
    the well saturates at ``full_well_e`` and the ADC quantises to ``adc_bits``. The matcher
    sees an 8-bit companded image. Draws: two N(0, 1) fields per camera (speckle, temporal
    noise); the reference image uses a zero draw and is normalised to 90 % of the range.
    Approximations: Gaussian shot noise, white (pixel-sized) speckle, no dark current/FPN.
    """

    name = "ir_capture"
    REQUIRED_IN_PIPELINE = True
    DRAW_FROM_SHAPE = True
    Params = IRCaptureParams
    FITTABLE = {"gain_e": (100.0, 1e6), "full_well_e": (1000.0, 1e6), "read_noise_e": (0.0, 200.0),
                "speckle_contrast": (0.0, 1.0), "psf_sigma_px": (0.0, 3.0)}
    stage = STAGE_CAPTURE
    physical = True
    in_reference = True

    def sample(self, rng, state):
        from synth.fastrand import standard_normal  # the compiled ziggurat: ~2x numpy's speed
        sh = state.shape
        d = {"speckle": standard_normal(rng, sh), "noise": standard_normal(rng, sh)}
        if state.preset.type == "active_stereo":
            d["speckle_second"] = standard_normal(rng, sh)
            d["noise_second"] = standard_normal(rng, sh)
        return d

    def null_draw(self, state):
        return None

    def _capture(self, radiance, ambient, speckle, noise, reference: bool):
        import cv2

        from synth.jit import n_threads
        p = self.params
        H, W = radiance.shape
        for name, a in (("speckle", speckle), ("noise", noise), ("ambient", ambient)):
            if a is not None and a.shape != (H, W):  # the kernels below do not check bounds
                raise ValueError(f"ir_capture: {name} is {a.shape}, the radiance {(H, W)}")
        nthreads = n_threads()
        f32 = np.float32
        none = np.zeros((1, 1), np.float32)
        use_speckle = speckle is not None and p.speckle_contrast > 0
        rad = np.empty((H, W), np.float32)
        run_row_bands(lambda r0, r1: _expose_rows(
            r0, r1, np.ascontiguousarray(radiance, np.float32), speckle if use_speckle else none,
            f32(p.speckle_contrast), use_speckle, ambient if ambient is not None else none, ambient is not None, rad),
            H, nthreads)
        if p.psf_sigma_px > 0:
            rad = cv2.GaussianBlur(rad, (0, 0), p.psf_sigma_px)
        top = float(2 ** int(p.adc_bits) - 1)
        if reference:  # the stored reference: noise-free, normalised to 90 % of the range
            hi = float(np.percentile(rad[rad > 0], 99.9)) if np.any(rad > 0) else 1.0
            scale = f32(0.9 * p.full_well_e / max(hi, 1e-12))
        else:
            scale = f32(p.gain_e)
        dn16 = np.empty((H, W), np.uint16)
        ir8 = np.empty((H, W), np.uint8)
        sat = np.empty((H, W), np.bool_)
        lut = self._lut(int(p.adc_bits), p.companding)
        run_row_bands(lambda r0, r1: _adc_rows(
            r0, r1, np.ascontiguousarray(rad, np.float32), scale, noise if noise is not None else none,
            noise is not None, f32(p.read_noise_e) ** 2, f32(p.full_well_e), f32(top / p.full_well_e), f32(top),
            lut, dn16, ir8, sat), H, nthreads)
        return dn16, ir8, sat

    @staticmethod
    def _lut(bits: int, companding: str) -> np.ndarray:
        """(2^bits,) uint8 companded value of every ADC count (cached per bits/companding)."""
        key = (bits, companding)
        lut = _LUTS.get(key)
        if lut is None:
            top = float(2 ** bits - 1)
            dn = np.arange(2 ** bits, dtype=np.float32)
            if companding == "sqrt":
                im8 = np.rint(np.sqrt(dn * np.float32(1.0 / top)) * 255.0)
            else:
                im8 = np.rint(dn * np.float32(255.0 / top))
            lut = _LUTS[key] = im8.astype(np.uint8)
        return lut

    def apply(self, state, draw) -> None:
        if state.radiance is None:
            from data_tools.errors import ConfigError
            raise ConfigError("effect 'ir_capture' needs 'pattern_projection' earlier in the model")
        sh = state.shape
        if state.is_reference or draw is None:
            sp = nz = sp2 = nz2 = None
        else:
            sp = check_draw(draw, "speckle", sh, self.name)
            nz = check_draw(draw, "noise", sh, self.name)
            sp2 = nz2 = None
            if state.radiance_second is not None:  # active stereo: the second camera's draws
                sp2 = check_draw(draw, "speckle_second", sh, self.name)
                nz2 = check_draw(draw, "noise_second", sh, self.name)
        ref = state.is_reference
        state.ir, state.ir8, state.saturated = self._capture(state.radiance, state.product("ambient"), sp, nz, ref)
        if state.radiance_second is not None:
            state.ir_second, state.ir8_second, _ = self._capture(state.radiance_second,
                                                                 state.product("ambient_second"), sp2, nz2, ref)
        state.log[self.name] = {"saturated_px": int(state.saturated.sum()),
                                "mean_counts": float(state.ir.mean())}


@kernel
def _expose_rows(r0, r1, radiance, speckle, contrast, use_speckle, ambient, use_ambient, out):
    """Rows [r0, r1): radiance x max(0, 1 + contrast x speckle) + ambient (float32)."""
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for v in range(r0, r1):
        for u in range(radiance.shape[1]):
            x = radiance[v, u]
            if use_speckle:
                x = max(contrast * speckle[v, u] + one, zero) * x
            if use_ambient:
                x = x + ambient[v, u]
            out[v, u] = x


@kernel
def _adc_rows(r0, r1, rad, scale, noise, use_noise, read2, full_well, dn_per_e, top, lut, dn16, ir8, sat):
    """Rows [r0, r1) of the exposure: electrons S = rad x scale plus sqrt(S + read^2) x noise
    (shot + read noise), saturation at the full well, ADC counts rint(S x top / full well)
    clipped to [0, top], and the companded 8-bit value ``lut[counts]`` (float32 throughout)."""
    zero = np.float32(0.0)
    for v in range(r0, r1):
        for u in range(rad.shape[1]):
            S = rad[v, u] * scale
            if use_noise:
                S = S + np.sqrt(S + read2) * noise[v, u]
            sat[v, u] = S >= full_well
            dn = np.rint(S * dn_per_e)
            dn = min(max(dn, zero), top)
            c = np.uint16(dn)
            dn16[v, u] = c
            ir8[v, u] = lut[c]
