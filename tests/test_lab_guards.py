"""A fitted model never throws the measurement away (issue 43 item 1): range limits bounded by the
measured valid depths, and "every candidate is inert" is an error saying why. Hand-made case: a
generator sequence (tests/hidden_effects.py, 160x120) and a careless model whose maximum range sits
at the median measured depth, cutting the far half."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.errors import RealgapError
from synth.lab import DiagnoseConfig, FitConfig, MeasuredSequence, diagnose
from synth.lab.fit import Objective, param_specs, search, set_params
from synth.lab.guards import bound_depth_limits, lost_fraction, measured_range

from tests import hidden_effects as he


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    p = tmp_path_factory.mktemp("guards") / "bias"
    he.generate(p, "depth_bias", seed=5, n_frames=3, width=160, height=120)
    ms = MeasuredSequence.load(p)
    v = np.concatenate([ms.measured_depth(k)[ms.measured_depth(k) > 0] for k in range(len(ms))])
    return ms, v


def _careless(ms, v):
    return ms.default_config(["axial_noise", "range_limits"]).with_params(
        {"range_limits.max_depth_m": float(np.median(v))})


def test_measured_range_and_bounds(seq):
    ms, v = seq
    rng = measured_range(ms, range(len(ms)))
    assert rng.low == pytest.approx(np.percentile(v, 0.5)) and rng.high == pytest.approx(np.percentile(v, 99.5))
    cfg = _careless(ms, v)
    specs, moved = bound_depth_limits(param_specs(cfg), cfg, rng)
    mx = next(s for s in specs if s.key == "range_limits.max_depth_m")
    mn = next(s for s in specs if s.key == "range_limits.min_depth_m")
    assert moved and mx.low == pytest.approx(rng.high) and mx.value >= rng.high
    assert mn.high <= rng.low
    other = [s for s in specs if not s.key.startswith("range_limits")]
    assert other == [s for s in param_specs(cfg) if not s.key.startswith("range_limits")]   # untouched


def test_careless_far_cut_is_undone_by_any_search(seq):
    ms, v = seq
    frames = [0, 1, 2]
    cfg = _careless(ms, v)
    lost0 = lost_fraction(ms, ms.simulate(cfg, 0, frames), frames)
    assert lost0 > 0.4                                   # the careless model cuts about the far half
    obj = Objective(ms, frames, FitConfig(max_pixels_per_frame=2000).compare_config(2000))
    x, g, _ = search(obj, cfg, param_specs(cfg, ["range_limits"]), FitConfig(max_evaluations=12))
    assert x["range_limits.max_depth_m"] >= np.percentile(v[v > 0], 99.5) - 1e-6
    fitted = set_params(cfg, x)
    assert lost_fraction(ms, ms.simulate(fitted, 0, frames), frames) < 0.05


def test_every_candidate_inert_is_an_error_saying_why(seq):
    ms, v = seq
    cfg = ms.default_config(["axial_noise", "range_limits"]).with_params(
        {"range_limits.max_depth_m": float(0.5 * v.min())})
    with pytest.raises(RealgapError, match=r"cuts 100 % of the measured pixels: max_depth_m 0\.\d\d m"):
        diagnose(ms, cfg, candidates=["depth_bias", "edge_fattening"],
                 fit_config=FitConfig(max_frames=2, max_pixels_per_frame=2000),
                 diagnose_config=DiagnoseConfig(refit_model=False, evaluate=False, refine_top=0))


def test_diagnose_refit_keeps_the_measurement(seq):
    ms, v = seq
    d = diagnose(ms, _careless(ms, v), candidates=["depth_bias"],
                 fit_config=FitConfig(max_frames=2, max_pixels_per_frame=2000, eval_pixels_per_frame=3000),
                 diagnose_config=DiagnoseConfig(model_evaluations=20, candidate_evaluations=8, refine_top=0,
                                                evaluate=False))
    assert d.model_params["range_limits.max_depth_m"] >= np.percentile(v, 99.5) * 0.999
    assert d.ranking and d.ranking[0].effect == "depth_bias"
