"""Physical stage 3: block matching along the epipolar line -> disparity -> depth."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.jit import kernel
from synth.sensor.registry import STAGE_MATCHING, Effect, param, register_effect


@dataclass
class BlockMatchingParams:
    block_size: int = param(0, "px", 0, 63)
    """Window side, pixels (odd); 0 = the preset's."""
    prefilter: str = param("normalized", "", choices=("normalized", "xsobel"))
    """StereoBM pre-filter: ``normalized`` (local mean removal/contrast normalisation, what a
    correlator on a dot pattern does) or ``xsobel``."""
    prefilter_size: int = param(9, "px", 5, 255)
    """Pre-filter window, pixels (odd, >= 5)."""
    prefilter_cap: int = param(31, "1")
    """Clip of the pre-filtered image (1..63): limits the weight of bright dots."""
    uniqueness_ratio: int = param(10, "%")
    """Uniqueness check: the best SAD must beat every other disparity (outside +-1) by this
    percentage, else the pixel is a hole (ambiguous match)."""
    texture_threshold: int = param(0, "1", 0, 100000)
    """Minimum summed pre-filtered texture in the window (0 = off)."""
    speckle_window_px: int = param(200, "px²")
    """Connected regions of consistent disparity smaller than this are removed (holes), as the
    device removes isolated blobs; 0 = off."""
    speckle_range_steps: float = param(1.0, "steps")
    """Neighbouring disparities differing by more than this many device sub-pixel steps start a
    new region (so steep disparity gradients - grazing surfaces - fall apart into small
    regions and are removed)."""
    lr_max_diff_px: int = param(-1, "px", -1, 64)
    """Left-right consistency check tolerance (SGBM), pixels; -1 = off."""
    sgbm_p1: float = param(1.0, "1")
    """SGBM smoothness penalty for +-1 px disparity changes, per window pixel (P1 = this x
    block^2). OpenCV's usual 8 makes the sub-pixel estimate lock to integers on dot patterns."""
    sgbm_p2: float = param(4.0, "1")
    """SGBM penalty for larger disparity jumps, per window pixel (P2 = this x block^2)."""
    subpixel_iterations: int = param(2, "1", 0, 20)
    """Gauss-Newton sub-pixel refinement steps on the window-normalised images after the
    integer/1/16 px search (0 = keep the matcher's own interpolation, which locks to integer
    disparities on dot patterns)."""
    max_refine_px: float = param(1.0, "px", 0.0, 16.0)
    """Where the refinement moves farther than this, pixels (a window straddling a depth
    edge), the matcher's own sub-pixel value is kept."""


@register_effect
class BlockMatching(Effect):
    """IR image vs reference (structured light) or vs the second camera (active stereo).

    Physics/device: a correlator slides a ``block_size`` window along the (horizontal)
    epipolar line over the disparity range allowed by the depth range, picks the best SAD,
    refines it to sub-pixel (Gauss-Newton on window-normalised images) and quantises it to the
    device step (Kinect v1: 1/8 px), then
    rejects ambiguous matches (uniqueness) and small inconsistent blobs (speckle filter).
    Structured light matches against the stored reference image of the pattern on a plane at
    z0: 1/z = 1/z0 + d/(f b); stereo matches the two cameras: z = f b / d. The window causes
    edge fattening and the sub-pixel step causes quantisation: both emerge here; the direct
    effects ``edge_fattening`` and ``disparity_quantization`` are their analytic stand-ins.
    OpenCV StereoBM (``bm``) or StereoSGBM (``sgbm``, semi-global) do the search (1/16 px).
    """

    name = "block_matching"
    KEEPS_INVALID = False  # depth is recomputed from the IR images
    REQUIRED_IN_PIPELINE = True
    Params = BlockMatchingParams
    FITTABLE = {"prefilter_cap": (1, 63), "uniqueness_ratio": (0, 100), "speckle_window_px": (0, 2000),
                "speckle_range_steps": (0.0, 16.0), "sgbm_p1": (0.0, 64.0), "sgbm_p2": (0.0, 256.0)}
    stage = STAGE_MATCHING
    physical = True

    def validate(self) -> None:
        super().validate()
        from data_tools.errors import ConfigError
        p = self.params
        if p.block_size and (p.block_size < 3 or p.block_size % 2 == 0):
            raise ConfigError(f"effect 'block_matching': block_size must be 0 or odd >= 3, got {p.block_size}")

    def setup(self, preset):
        from synth.sensor.matching import MatchSetup
        return MatchSetup.for_preset(preset, self.params.block_size or None)

    def matcher_params(self, setup):
        from synth.sensor.matching import MatcherParams
        p = self.params
        rng16 = int(round(p.speckle_range_steps * setup.step * 16))
        return MatcherParams(p.prefilter, p.prefilter_size, p.prefilter_cap, p.uniqueness_ratio,
                             p.texture_threshold, p.speckle_window_px, max(rng16, 0) if p.speckle_window_px else 0,
                             p.lr_max_diff_px, int(round(p.sgbm_p1 * setup.block ** 2)),
                             int(round(p.sgbm_p2 * setup.block ** 2)), p.subpixel_iterations,
                             p.max_refine_px)

    def apply(self, state, draw) -> None:
        from data_tools.errors import ConfigError
        from synth.sensor.matching import match
        pre = state.preset
        if state.ir8 is None:
            raise ConfigError("effect 'block_matching' needs 'ir_capture' earlier in the model")
        setup = self.setup(pre)
        method = pre.matcher if pre.matcher in ("bm", "sgbm") else "bm"
        if pre.type == "active_stereo":
            if state.ir8_second is None:
                raise ConfigError("effect 'block_matching': the active-stereo rig has no second IR image")
            right = state.ir8_second
        else:
            if state.reference_ir8 is None:
                raise ConfigError("effect 'block_matching': no reference pattern image (structured light)")
            right = state.reference_ir8
        d = np.ascontiguousarray(match(state.ir8, right, setup, method, self.matcher_params(setup)), np.float32)
        z = np.empty(d.shape, np.float32)
        valid = np.empty(d.shape, np.bool_)
        # setup.quantize + setup.disparity_to_depth + the validity rule in one compiled pass
        _quantised_depth(d, np.float32(setup.step), np.float32(0.0 if setup.z0 is None else 1.0 / setup.z0),
                         np.float32(setup.fb), z, valid)
        state.disparity = d
        state.depth = z
        state.valid = valid
        state.log[self.name] = {"valid_px": int(valid.sum()), "min_disp": setup.min_disp,
                                "num_disp": setup.num_disp, "step_px": setup.step}


@kernel
def _quantised_depth(d, step, inv0, fb, z, valid):
    """In place: ``d`` (H, W) float32 disparity rounded to the device ``step`` (NaN where the
    matcher found none or the depth is not positive); ``z`` its depth 1 / (inv0 + d / fb), metres
    (0 where invalid); ``valid``. The float32 arithmetic of ``MatchSetup.quantize`` and
    ``MatchSetup.disparity_to_depth`` (tests/test_sensor_matching.py compares them)."""
    H, W = d.shape
    for y in range(H):
        for x in range(W):
            q = np.rint(d[y, x] / step) * step
            inv = inv0 + q / fb
            ok = np.isfinite(q) and np.isfinite(inv) and inv > 0
            zz = np.float32(1.0) / inv if ok else np.float32(0.0)
            if ok and zz > 0:
                d[y, x] = q
                z[y, x] = zz
                valid[y, x] = True
            else:
                d[y, x] = np.nan
                z[y, x] = 0.0
                valid[y, x] = False
