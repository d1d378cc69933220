"""Fitting: parameter spaces, the bounded coordinate search on hand-made objectives, and
parameter recovery on sequences of the independent generator (tests/hidden_effects.py)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from data_tools.errors import ConfigError
from synth.lab import FitConfig, MeasuredSequence, fit_model
from synth.lab.fit import ParamSpec, get_params, param_specs, search, set_params
from synth.sensor.config import SensorConfig

from tests import hidden_effects as he

FAST = dict(max_frames=3, max_pixels_per_frame=3000, eval_pixels_per_frame=6000)


@pytest.fixture(scope="module")
def gen(tmp_path_factory):
    """Generated sequences by hidden effect (160x120, 4 frames)."""
    root = tmp_path_factory.mktemp("lab_fit")
    cache = {}

    def get(effect, seed=2):
        key = (effect, seed)
        if key not in cache:
            out = root / f"{effect}_{seed}"
            cache[key] = (he.generate(out, effect, seed=seed, n_frames=4, width=160, height=120), out)
        params, out = cache[key]
        return MeasuredSequence.load(out), params
    return get


def test_param_spec_scales_round_trip():
    lin = ParamSpec("a.x", 30.0, 90.0, 78.0)
    log = ParamSpec("a.y", 1e-6, 1.0, 0.004, scale="log")
    ash = ParamSpec("a.z", -0.1, 0.1, 0.0, scale="asinh")
    for s, x in ((lin, 55.0), (log, 3e-3), (ash, -0.012), (ash, 0.0)):
        assert s.from_t(s.to_t(x)) == pytest.approx(x, abs=1e-12)
    # asinh: a grid over the bounds covers 0 and three decades on each side
    grid = [ash.from_t(t) for t in np.linspace(*ash.t_bounds, 7)]
    assert grid[3] == 0.0 and grid[0] == pytest.approx(-0.1) and 1e-4 < abs(grid[2]) < 1e-2
    intg = ParamSpec("a.k", 0, 20, 4, integer=True)
    assert intg.from_t(3.6) == 4.0 and intg.from_t(99) == 20.0


def test_param_specs_and_set_params_cover_config_parameters():
    cfg = SensorConfig.build("kinect_v1", ["axial_noise", "edge_fattening", "lens_distortion"])
    specs = {s.key: s for s in param_specs(cfg)}
    assert specs["axial_noise.sigma2_per_m"].scale == "asinh"
    assert specs["edge_fattening.radius_px"].integer
    assert "lens_distortion.k1" in specs and "lens_distortion.k2" in specs
    new = set_params(cfg, {"lens_distortion.k1": -0.2, "edge_fattening.radius_px": 5.4,
                           "axial_noise.sigma2_per_m": 0.003})
    assert new.effect("lens_distortion").coefficients(new.preset)[:2] == (-0.2, 0.0)
    assert new.effect("lens_distortion").params.k1 == -0.2
    assert new.effect("edge_fattening").params.radius_px == 5
    assert get_params(new, param_specs(new))["axial_noise.sigma2_per_m"] == 0.003
    assert cfg.effect("lens_distortion").params.coefficients == ()  # original untouched
    with pytest.raises(ConfigError):
        set_params(cfg, {"depth_bias.offset_m": 0.01})
    with pytest.raises(ConfigError):
        param_specs(cfg, ["depth_bias"])


def test_config_parameters_are_declared_by_their_effects():
    """Fittable numbers outside an effect's Params (the level phase = the preset's reference depth)
    are declared in the effect's own file, documented, and fitted only where they apply."""
    from synth.sensor.registry import ConfigParameter, effect_class, effect_names
    declared = {n: effect_class(n).CONFIG_PARAMETERS for n in effect_names() if effect_class(n).CONFIG_PARAMETERS}
    assert set(declared) == {"disparity_quantization"}
    for table in declared.values():
        for x in table.values():
            assert isinstance(x, ConfigParameter) and x.low < x.high and len(x.doc) > 40
    cfg = SensorConfig.build("kinect_v1", ["lens_distortion", "disparity_quantization"])
    assert {s.key for s in param_specs(cfg)} == {"lens_distortion.k1", "lens_distortion.k2",
                                                 "disparity_quantization.step_px", "disparity_quantization.level_phase"}
    # the level phase exists only where the device quantises relative to a reference plane
    stereo = SensorConfig.build("realsense_d435", ["disparity_quantization"])
    assert [s.key for s in param_specs(stereo)] == ["disparity_quantization.step_px"]


def test_lens_coefficients_are_fitted_on_top_of_the_calibrated_distortion():
    pre = SensorConfig.build("kinect_v1").preset.replace(distortion=(0.1, -0.2, 0.001, 0.0, 0.0))
    cfg = SensorConfig.build(pre, ["lens_distortion"])
    assert get_params(cfg, param_specs(cfg)) == {"lens_distortion.k1": 0.0, "lens_distortion.k2": 0.0}
    new = set_params(cfg, {"lens_distortion.k1": 0.05})
    assert new.effect("lens_distortion").coefficients(pre) == pytest.approx((0.15, -0.2, 0.001, 0.0, 0.0))
    assert get_params(new, param_specs(new))["lens_distortion.k1"] == pytest.approx(0.05)


def test_set_params_keeps_every_other_config_field():
    from synth.sensor.config import MotionLimits
    motion = MotionLimits(max_speed_m_s=0.7, max_angular_speed_rad_s=0.3)
    cfg = dataclasses.replace(SensorConfig.build("kinect_v1", ["axial_noise", "disparity_quantization",
                                                               "lens_distortion"]), motion=motion)
    new = set_params(cfg, {"axial_noise.sigma2_per_m": 0.002, "lens_distortion.k1": 0.1,
                           "disparity_quantization.level_phase": 0.4})
    assert new.motion == motion and new.preset.reference_depth_m != cfg.preset.reference_depth_m
    assert get_params(new, param_specs(new))["disparity_quantization.level_phase"] == pytest.approx(0.4)
    assert set_params(cfg, {}).motion == motion


class _Quadratic:
    """Objective of a config: a bowl in (sigma2, z_offset) with a flat-then-steep part, so a
    plain golden search over the full range would fail; counts calls."""

    def __init__(self):
        self.calls = 0

    def __call__(self, cfg):
        self.calls += 1
        p = cfg.effect("axial_noise").params
        return (math.asinh(p.sigma2_per_m / 5e-5) - math.asinh(0.0041 / 5e-5)) ** 2 + (p.z_offset_m - 0.3) ** 2 + 0.1


def test_search_finds_the_optimum_of_a_known_objective():
    cfg = SensorConfig.build("kinect_v1", ["axial_noise"])
    specs = [s for s in param_specs(cfg) if s.key in ("axial_noise.sigma2_per_m", "axial_noise.z_offset_m")]
    obj = _Quadratic()
    fc = FitConfig(max_evaluations=80, refine_iterations=10, sweeps=3)
    x, g, n = search(obj, cfg, specs, fc)
    assert x["axial_noise.sigma2_per_m"] == pytest.approx(0.0041, rel=0.05)
    assert x["axial_noise.z_offset_m"] == pytest.approx(0.3, abs=0.03)
    assert g == pytest.approx(0.1, abs=0.01) and n == obj.calls <= 80
    # the budget is respected
    obj2 = _Quadratic()
    search(obj2, cfg, specs, FitConfig(max_evaluations=5))
    assert obj2.calls <= 5


def test_fit_recovers_the_disparity_noise_of_independent_data(gen):
    """Generator: Gaussian noise of sigma_d px in the absolute disparity -> sigma_z = z^2 sigma_d / (f b),
    i.e. the model's axial noise with sigma2 = sigma_d / (f b)."""
    ms, truth = gen(None)
    cfg = ms.default_config(["axial_noise", "range_limits"])
    res = fit_model(ms, cfg, names=["axial_noise"], fit_config=FitConfig(**FAST, max_evaluations=60))
    want = truth["sigma_d_px"] / (ms.preset.fx * ms.preset.baseline_m)
    p = res.config.effect("axial_noise").params
    # the quadratic term carries the noise (sigma0 and sigma1 stay small at these depths)
    assert p.sigma2_per_m == pytest.approx(want, rel=0.15)
    assert res.gap < 0.5 * res.gap_before and not res.kept_start
    assert set(res.params) == {s.key for s in param_specs(cfg, ["axial_noise"])}
    j = res.to_json()
    assert j["gap"] == res.gap and j["evaluations"] == res.evaluations and j["effects"] == ["axial_noise", "range_limits"]


def test_fit_recovers_the_incidence_dropout_angle(gen):
    """Generator: dropout logistic in cos(theta) with its midpoint at cos50; the model's logistic in
    the angle must put its midpoint at arccos(cos50)."""
    ms, truth = gen("incidence_dropout", seed=4)
    sigma2 = truth["sigma_d_px"] / (ms.preset.fx * ms.preset.baseline_m)
    cfg = ms.default_config(["axial_noise", "incidence_dropout", "range_limits"]).with_params(
        {"axial_noise.sigma2_per_m": sigma2})
    res = fit_model(ms, cfg, names=["incidence_dropout"], fit_config=FitConfig(**FAST, max_evaluations=30))
    want = math.degrees(math.acos(truth["cos50"]))
    assert res.params["incidence_dropout.angle50_deg"] == pytest.approx(want, abs=4.0)
    assert res.gap < res.gap_before


def test_quantization_step_and_phase_from_the_periodogram(gen):
    """Generator: ABSOLUTE disparity rounded to multiples of step_px; the data-driven start finds
    the step and puts the model's levels (relative to its reference plane) on the same grid."""
    from synth.lab.fit import start_values
    ms, truth = gen("disparity_quantization", seed=6)
    cfg = ms.default_config(["axial_noise", "disparity_quantization", "range_limits"])
    st = start_values(ms, cfg, ["disparity_quantization"], [0, 1, 2, 3])
    assert st["disparity_quantization.step_px"] == pytest.approx(truth["step_px"], rel=0.01)
    new = set_params(cfg, st)
    pre = new.preset
    offset = pre.fb / pre.reference_depth_m / truth["step_px"]    # absolute level offset in steps
    assert min(offset % 1.0, 1.0 - offset % 1.0) < 0.05
    # no quantisation in the data -> no start proposed
    ms0, _ = gen(None)
    assert start_values(ms0, cfg, ["disparity_quantization"], [0, 1, 2, 3]) == {}


def test_fit_config_validation_and_round_trip():
    with pytest.raises(ConfigError):
        FitConfig(max_frames=0).validate()
    with pytest.raises(ConfigError):
        FitConfig(grid_points=1).validate()
    with pytest.raises(ConfigError, match="max_seconds"):
        FitConfig(max_seconds=0).validate()
    assert FitConfig().max_seconds is None      # the wall-clock guard is off by default
    with pytest.raises(ConfigError, match="fit config: unknown option"):
        FitConfig.from_dict({"nope": 1})
    fc = FitConfig(max_frames=3, seed=7)
    assert FitConfig.from_dict(fc.to_dict()).to_dict() == fc.to_dict()


def test_plausible_bounds_per_preset_keep_base_effects_physical():
    # the absurd fit: axial_noise.z_offset_m = 2.0 and range_limits.min_depth_m = 5.0 on
    # a Kinect; the search space of every preset now stops at what the device can have
    for name, zmin in (("kinect_v1", 0.45), ("structure", 0.4), ("kinect_v2", 0.5)):
        cfg = SensorConfig.build(name, ["axial_noise", "range_limits"])
        b = {s.key: (s.low, s.high) for s in param_specs(cfg)}
        assert b["axial_noise.z_offset_m"] == (0.0, pytest.approx(zmin))
        assert b["range_limits.min_depth_m"] == (0.0, pytest.approx(1.5 * zmin))
        assert b["range_limits.max_depth_m"][1] == pytest.approx(1.5 * cfg.preset.max_depth_m)
    kin = {s.key: s for s in param_specs(SensorConfig.build("kinect_v1", ["axial_noise"]))}
    assert kin["axial_noise.sigma2_per_m"].high == pytest.approx(5 * 0.0014)   # 5x the device's
    assert kin["axial_noise.sigma0_m"].high == pytest.approx(5 * 0.0014)       # 5x sigma at 1 m
    # a value ending on such a limit is reported as at bound
    from synth.lab.fit import FitResult
    r = FitResult.__new__(FitResult)
    r.params = {"axial_noise.z_offset_m": 0.45}
    r.bounds = {"axial_noise.z_offset_m": (0.0, 0.45)}
    assert "at upper bound 0.45" in r.at_bound["axial_noise.z_offset_m"]


def _bowl(a: float, b: float, c: float = 1.0):
    """gap = c + 1/2 [dx dy] [[a, b], [b, a]] [dx dy]^T around (0.5, 0.3); counts calls."""
    calls = []

    def gap_of(vals, seed_offset=0):
        calls.append(1)
        dx, dy = vals["e.x"] - 0.5, vals["e.y"] - 0.3
        return c + 0.5 * (a * dx * dx + 2 * b * dx * dy + a * dy * dy)
    return gap_of, calls


def test_joint_intervals_widen_by_the_variance_inflation_of_a_known_bowl():
    from synth.lab.fit import ParamSpec
    from synth.lab.intervals import joint_intervals, profile_intervals
    specs = [ParamSpec("e.x", -5.0, 5.0, 0.5), ParamSpec("e.y", -5.0, 5.0, 0.3)]
    best = {"e.x": 0.5, "e.y": 0.3}
    a, b = 2.02, 1.98                       # a strong trade-off: x + y is fixed, x - y barely
    gap_of, calls = _bowl(a, b)
    single, tau = profile_intervals(gap_of, specs, best, 1.0, steps=8)
    assert tau == pytest.approx(0.02)       # noise-free: 2 % of the gap
    # one at a time: 1/2 a dx^2 = tau -> dx = sqrt(2 tau / a), exact for a quadratic bowl
    half = math.sqrt(2 * tau / a)
    assert single["e.x"][1] - 0.5 == pytest.approx(half, rel=1e-6)
    n0 = len(calls)
    joint, infl, corr = joint_intervals(gap_of, specs, best, 1.0, tau, single)
    assert len(calls) - n0 == 2 * 3         # n (n + 1) evaluations
    vif = a * a / (a * a - b * b)           # A_ii (A^-1)_ii for [[a, b], [b, a]]
    assert infl["e.x"] == pytest.approx(math.sqrt(vif), rel=1e-6)
    assert corr["e.x|e.y"] == pytest.approx(-b / a, abs=1e-3)   # stored to 3 decimals
    for k, v0 in best.items():
        lo1, hi1 = single[k]
        assert joint[k][0] == pytest.approx(v0 - infl[k] * (v0 - lo1))
        assert joint[k][1] == pytest.approx(v0 + infl[k] * (hi1 - v0))
    # the exact joint region {gap <= g_best + tau} reaches x = 0.5 +- sqrt(2 tau (A^-1)_xx): inside
    reach = math.sqrt(2 * tau * a / (a * a - b * b))
    assert joint["e.x"][0] <= 0.5 - 0.9 * reach and joint["e.x"][1] >= 0.5 + 0.9 * reach
    # independent parameters: nothing to widen, no correlation reported
    gap2, _ = _bowl(2.0, 0.0)
    single2, _ = profile_intervals(gap2, specs, best, 1.0)
    joint2, infl2, corr2 = joint_intervals(gap2, specs, best, 1.0, 0.02, single2)
    assert infl2 == {"e.x": pytest.approx(1.0), "e.y": pytest.approx(1.0)} and corr2 == {}
    for k in single2:
        assert joint2[k] == pytest.approx(single2[k])


def test_joint_intervals_at_a_bound_stay_inside_the_bounds():
    from synth.lab.fit import ParamSpec
    from synth.lab.intervals import joint_intervals, profile_intervals
    specs = [ParamSpec("e.x", 0.5, 5.0, 0.5), ParamSpec("e.y", -1.0, 1.0, 0.3)]
    best = {"e.x": 0.5, "e.y": 0.3}         # x on its lower bound
    gap_of, _ = _bowl(2.0, 1.5)
    single, tau = profile_intervals(gap_of, specs, best, 1.0)
    joint, infl, _ = joint_intervals(gap_of, specs, best, 1.0, tau, single)
    assert joint["e.x"][0] == 0.5 and joint["e.x"][1] <= 5.0 and joint["e.y"][0] >= -1.0
    assert all(f >= 1.0 for f in infl.values())


def test_joint_intervals_ignore_couplings_that_are_noise():
    # three independent parameters and a rugged gap (noise of 1 tau on every evaluation, as on
    # real data): no spurious trade-off may be reported, nothing widened much
    from synth.lab.fit import ParamSpec
    from synth.lab.intervals import joint_intervals, profile_intervals
    specs = [ParamSpec(f"e.{k}", -5.0, 5.0, 0.0) for k in "xyz"]
    best = {"e.x": 0.0, "e.y": 0.0, "e.z": 0.0}
    rng = np.random.default_rng(5)

    def gap_of(vals, seed_offset=0):
        return 1.0 + sum(vals[k] ** 2 for k in best) + (1.0 * 0.02 * rng.standard_normal() if vals != best else 0.0)
    single, tau = profile_intervals(gap_of, specs, best, 1.0)
    joint, infl, corr = joint_intervals(gap_of, specs, best, 1.0, tau, single)
    assert corr == {} and max(infl.values()) < 1.3


def test_joint_intervals_leave_a_parameter_that_changes_nothing_alone():
    from synth.lab.fit import ParamSpec
    from synth.lab.intervals import joint_intervals, profile_intervals
    specs = [ParamSpec("e.x", -5.0, 5.0, 0.5), ParamSpec("e.y", -5.0, 5.0, 0.3), ParamSpec("e.z", 0.0, 1.0, 0.5)]
    best = {"e.x": 0.5, "e.y": 0.3, "e.z": 0.5}
    bowl, _ = _bowl(2.02, 1.98)
    gap_of = lambda vals, seed_offset=0: (bowl(vals) + 1e-4 * (vals["e.z"] - 0.5) ** 2      # noqa: E731
                                         + 2e-4 * (vals["e.z"] - 0.5) * (vals["e.x"] - 0.5))  # e.z: next to nothing
    single, tau = profile_intervals(gap_of, specs, best, 1.0)
    joint, infl, corr = joint_intervals(gap_of, specs, best, 1.0, tau, single)
    assert infl["e.z"] == 1.0 and joint["e.z"] == single["e.z"]
    assert set(corr) == {"e.x|e.y"} and infl["e.x"] == pytest.approx(math.sqrt(2.02 ** 2 / (2.02 ** 2 - 1.98 ** 2)))



def test_joint_intervals_leave_integers_and_bound_values_uncoupled():
    from synth.lab.fit import ParamSpec
    from synth.lab.intervals import joint_intervals, profile_intervals
    specs = [ParamSpec("e.x", -5.0, 5.0, 0.5), ParamSpec("e.y", -5.0, 5.0, 0.3),
             ParamSpec("e.r", 0.0, 20.0, 0.0, integer=True), ParamSpec("e.m", 0.0, 1.0, 0.0)]
    best = {"e.x": 0.5, "e.y": 0.3, "e.r": 0.0, "e.m": 0.0}
    bowl, calls = _bowl(2.02, 1.98)
    # r and m jump at 0 (as "0 = the device's value"): no quadratic model may couple them
    gap_of = lambda v, seed_offset=0: bowl(v) + (0.5 if v["e.r"] else 0.0) + (0.3 if v["e.m"] else 0.0)  # noqa: E731
    single, tau = profile_intervals(gap_of, specs, best, 1.0)
    n0 = len(calls)
    joint, infl, corr = joint_intervals(gap_of, specs, best, 1.0, tau, single)
    assert len(calls) - n0 == 2 * 3                      # only x and y are modelled
    assert infl["e.r"] == infl["e.m"] == 1.0 and joint["e.r"] == single["e.r"] and joint["e.m"] == single["e.m"]
    assert set(corr) == {"e.x|e.y"}


def test_the_evaluation_count_says_what_it_counts(gen):
    """``max_evaluations`` caps the search alone: the reported total is the sum of the stages, the
    search stays within its budget, and a screened search's raised budget is named (it was a bare
    "42 evaluations" for ``max_evaluations=3``, read as an ignored cap)."""
    from synth.lab.report import evaluations_text
    ms, _ = gen(None)
    cfg = ms.default_config(["axial_noise", "range_limits"])
    small = dict(FAST, intervals=False, max_pixels_per_frame=500, eval_pixels_per_frame=500)
    res = fit_model(ms, cfg, names=["axial_noise"], fit_config=FitConfig(**small, max_evaluations=3))
    st = res.stages
    assert res.evaluations == sum(s["evaluations"] for s in st.values())
    assert st["search"]["evaluations"] <= st["search"]["budget"]
    n_searched = len(res.params) - len(res.frozen)      # screened: every unfrozen parameter scanned once + 2 refinements
    assert st["search"]["budget"] == max(3, n_searched * (FitConfig().grid_points + 1) + 2 * FitConfig().refine_iterations)
    text = evaluations_text(st, res.evaluations, 3)
    assert text.startswith(f"{res.evaluations} evaluations (search {st['search']['evaluations']} of a budget of "
                           f"{st['search']['budget']}, raised from max_evaluations 3 by the screen; start ")
    unscreened = fit_model(ms, cfg, names=["axial_noise"],
                           fit_config=FitConfig(**small, max_evaluations=3, screen=False))
    assert unscreened.stages["search"] == {**unscreened.stages["search"], "budget": 3}
    assert unscreened.stages["search"]["evaluations"] <= 3 and "screen" not in unscreened.stages
    assert "raised" not in evaluations_text(unscreened.stages, unscreened.evaluations, 3)
