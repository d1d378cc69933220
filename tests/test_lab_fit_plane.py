"""Fits on planar-target captures (issue #43 items 3 and 4): what an evaluation reuses (the same
depth with and without the shared simulator resources; masked frames served by the compare
cache), the sensitivity screen (hand-made gap: hand-computed sensitivities; a fit that freezes an
inert parameter and says so), and the noise-vs-distance term on a hand-made plane sequence with a
known noise curve (tests/plane_sequences.py: no simulator involved)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from synth.lab import FitConfig, MeasuredSequence, fit_model
from synth.lab.fit import Objective, ParamSpec, set_params

from tests.plane_sequences import plane_reference

FAST = dict(max_frames=3, max_pixels_per_frame=3000, eval_pixels_per_frame=6000)


def nguyen_like(z):
    """The known curve: 1.5 mm + 2.5 mm/m^2 (z - 0.3 m)^2 (Nguyen et al.'s form, other numbers)."""
    return 0.0015 + 0.0025 * (z - 0.3) ** 2


@pytest.fixture(scope="module")
def curve_ref(tmp_path_factory):
    """24 frames of a flat target at 0.55-2.95 m, 160x120, noise ``nguyen_like``, seeded."""
    return plane_reference(tmp_path_factory.mktemp("plane_curve"), np.linspace(0.55, 2.95, 24), nguyen_like, seed=1)


def test_shared_simulator_resources_give_the_same_depth(curve_ref):
    """Simulators of one sequence share the pattern, reference images and rays; the depth is the
    one a simulator with its own resources makes, also after another model changed the reference."""
    ms = MeasuredSequence.load(curve_ref, max_frames=2)
    cfg = ms.default_config("physical")
    other = set_params(cfg, {"ir_capture.speckle_contrast": 0.5, "ir_capture.psf_sigma_px": 0.9})
    a = ms.simulate(cfg, seed=3)
    b = ms.simulate(other, seed=3)
    a2 = ms.simulate(cfg, seed=3)
    assert sum(k[0] == "reference" for k in ms._sim_shared) == 2 and any(k[0] == "pattern" for k in ms._sim_shared)
    alone = MeasuredSequence.load(curve_ref, max_frames=2)
    alone._sim_shared = None
    for x, y in zip(a + b, alone.simulate(cfg, seed=3) + alone.simulate(other, seed=3)):
        assert np.array_equal(x, y)
    assert all(np.array_equal(x, y) for x, y in zip(a, a2))
    assert not all(np.array_equal(x, y) for x, y in zip(a, b))


def test_masked_frames_are_served_by_the_compare_cache(curve_ref):
    ms = MeasuredSequence.load(curve_ref, max_frames=2)
    assert ms.has_masks and ms.has_plane_reference
    d = ms.measured_depth(0)
    assert ms.observation(0, d).ideal is ms.observation(0, d * 1.01).ideal
    obj = Objective(ms, [0, 1], FitConfig().compare_config(2000))
    cfg = ms.default_config(["axial_noise"])
    obj(cfg)
    hits = ms.compare_cache.hits
    obj(set_params(cfg, {"axial_noise.sigma2_per_m": 0.003}))
    assert ms.compare_cache.hits == hits + 2


def test_screen_sensitivities_by_hand():
    """gap = (a - 0.3)^2 + 0 b + 0.001 c + 10 (d - 0.5)^2 from a = 0.8, b = c = d = 0.5 (linear
    scales on [0, 1]): tau = 2 % of 0.2505 (the gap does not depend on the seed); a's probes at
    0.55 and 1.0 (0.25 of the range; the upper bound is within it) change the gap by -0.1875 and
    +0.24; b: 0; c: 0.00025 -> b and c frozen; d's probes at 0.25 and 0.75 both raise it by 0.625:
    bracketed (scanned locally), fitted after a (a probe of a lowered the gap)."""
    from synth.lab.intervals import screen_parameters
    specs = [ParamSpec(f"e.{k}", 0.0, 1.0, 0.8 if k == "a" else 0.5) for k in "abcd"]

    def gap_of(v, seed_offset=0):
        return (v["e.a"] - 0.3) ** 2 + 0.001 * v["e.c"] + 10 * (v["e.d"] - 0.5) ** 2
    start = {"e.a": 0.8, "e.b": 0.5, "e.c": 0.5, "e.d": 0.5}
    scr = screen_parameters(gap_of, specs, start, gap_of(start))
    assert scr.tau == pytest.approx(0.02 * 0.2505)
    assert scr.sensitivity["e.a"] == pytest.approx(0.24 / scr.tau)
    assert scr.improvement["e.a"] == pytest.approx(0.1875)
    assert scr.sensitivity["e.b"] == 0.0 and scr.sensitivity["e.c"] == pytest.approx(0.00025 / scr.tau)
    assert scr.sensitivity["e.d"] == pytest.approx(0.625 / scr.tau) and scr.bracketed == ["e.d"]
    assert scr.order == ["e.a", "e.d"] and set(scr.frozen) == {"e.b", "e.c"}
    assert "does not constrain" in scr.frozen["e.b"] and scr.evaluations == 2 + 8


def test_fit_freezes_an_inert_parameter_and_says_so(curve_ref):
    """Static frames (1 s apart): the rolling shutter's readout time changes nothing -> frozen at its
    start, interval = its bounds, named in the fit record; the noise is fitted."""
    ms = MeasuredSequence.load(curve_ref, frame_slice="0::2")
    cfg = ms.default_config(["axial_noise", "rolling_shutter"])
    res = fit_model(ms, cfg, fit_config=FitConfig(screen=True, **FAST))
    key = "rolling_shutter.readout_time_s"
    assert res.sensitivity[key] == 0.0 and key in res.frozen
    assert res.params[key] == res.start_params[key]
    assert tuple(res.intervals[key]) == tuple(res.bounds[key])
    assert "axial_noise.sigma2_per_m" not in res.frozen
    js = res.to_json()
    assert key in js["frozen"] and sum(s["evaluations"] for s in js["stages"].values()) == res.evaluations
    assert js["stages"]["screen"]["evaluations"] >= 2 * len(res.params) - 2


def test_noise_curve_statistics_by_hand():
    """A plane at 1.1 m (bin 1.0-1.25 m): measured residuals +-1 mm plus an offset of 5 mm (removed
    per frame and bin), simulated +-2 mm: robust std 1.4826 mm and 2.9652 mm, term ln 2."""
    from synth.lab.calibration import curve_term, noise_curve
    ideal = np.full((30, 40), 1.1, np.float32)
    sign = np.where(np.indices(ideal.shape).sum(0) % 2 == 0, 1.0, -1.0)
    o = SimpleNamespace(ideal=ideal, index=0, measured=(ideal + 0.005 + 0.001 * sign).astype(np.float32),
                        simulated=(ideal + 0.002 * sign).astype(np.float32))
    m, n = noise_curve([o], "measured")
    s, _ = noise_curve([o], "simulated")
    assert n[2] == 1200 and np.isnan(m[0]) and m[2] == pytest.approx(1.4826e-3, rel=1e-3)
    assert s[2] == pytest.approx(2.9652e-3, rel=1e-3)
    assert curve_term(m, s) == pytest.approx(np.log(2.0), rel=1e-3)
    assert Objective(SimpleNamespace(has_plane_reference=False), [0], FitConfig().compare_config(100),
                     noise_weight=1.0).noise_weight == 0.0


def test_fit_honours_the_noise_curve_on_held_out_frames(curve_ref):
    """Fitted on the even frames, the simulated plane-fit std of the odd frames is within 10 % of
    the measured one in every 0.25 m bin from 0.5 to 3 m; the gap alone (weight 0, the objective
    before #43) leaves the near bins >= 10 % too low."""
    from synth.lab.calibration import curve_table
    fit_ms = MeasuredSequence.load(curve_ref, frame_slice="0::2")
    held = MeasuredSequence.load(curve_ref, frame_slice="1::2")
    ratios = {}
    for w in (0.0, 1.0):
        res = fit_model(fit_ms, fit_ms.default_config(["axial_noise"]),
                        fit_config=FitConfig(noise_curve_weight=w, max_frames=6, intervals=False))
        ev = Objective(held, range(len(held)), FitConfig().compare_config(20000), 0, noise_weight=1.0)
        ev(res.config)
        rows = curve_table(ev.last_curve[1], 20000, 0)
        assert [r["bin_m"][0] for r in rows] == [0.5 + 0.25 * k for k in range(10)]
        ratios[w] = np.array([r["ratio"] for r in rows])
        if w:
            assert res.noise_curve["term"] < res.noise_curve["term_before"]
            assert len(res.noise_curve["bins"]) == 10
    assert np.all(np.abs(ratios[1.0] - 1.0) <= 0.10), ratios[1.0]
    assert np.any(np.abs(ratios[0.0] - 1.0) > 0.10), ratios[0.0]


def test_local_plane_removes_a_tilt_by_hand():
    """A strip of a floor at 2.5-2.6 m whose measured depth carries the +-1 mm checkerboard plus a
    reference-plane misfit affine in inverse depth (1/z' - 1/z = 1e-3 + 2e-3 u - 4e-3 v /m, u, v the
    pixel over the width, up to about 9 mm at the strip's ends): about its median the spread is
    several mm; about its local plane (the default) it is the checkerboard's 1.4826 mm again, as it
    is on the simulated side (no misfit) with or without; ``local_plane=False`` gives the median
    alone. Fewer than 30 pixels: the median alone either way."""
    from synth.lab.calibration import curve_groups, local_plane_residuals, noise_curve
    H, W = 30, 40
    v, u = np.indices((H, W)).astype(float)
    ideal = (2.5 + 0.1 * v / H).astype(np.float32)
    uu, vv = (u - W / 2) / W, (v - H / 2) / W
    sign = np.where((u + v) % 2 == 0, 1.0, -1.0)
    tilted = 1.0 / (1.0 / ideal + 1e-3 + 2e-3 * uu - 4e-3 * vv)
    o = SimpleNamespace(ideal=ideal, index=0, measured=(tilted + 0.001 * sign).astype(np.float32),
                        simulated=(ideal + 0.001 * sign).astype(np.float32))
    b = 8                                                   # 2.5-2.75 m
    m_plane = noise_curve([o], "measured", None)[0][b]
    m_median = noise_curve([o], "measured", None, local_plane=False)[0][b]
    s_plane = noise_curve([o], "simulated", None)[0][b]
    assert m_plane == pytest.approx(1.4826e-3, rel=0.02) and s_plane == pytest.approx(1.4826e-3, rel=0.02)
    assert m_median > 2.5e-3
    g = curve_groups([o], "measured", None, local_plane=False)[b][0][1]
    assert abs(np.median(g)) < 1e-9
    r = np.array([0.001, -0.001] * 10)
    assert np.allclose(local_plane_residuals(r + 0.004, np.full(20, 2.6), np.zeros((20, 2))), r)


def test_plane_noise_parts_by_hand():
    """benchmarks/plane_noise_parts.group_parts on a strip at 2.5-2.6 m with the +-1 mm checkerboard
    plus a bend of 0.05 z^2 u^2 (up to ~8 mm at the strip's ends): the median and the local plane
    keep the bend (their spread above 1.4826 mm), the local quadric takes it out."""
    from benchmarks.plane_noise_parts import group_parts
    H, W = 30, 40
    v, u = np.indices((H, W)).astype(float)
    z = (2.5 + 0.1 * v / H).ravel()
    uv = np.stack([((u - W / 2) / W).ravel(), ((v - H / 2) / W).ravel()], 1)
    sign = np.where((u + v) % 2 == 0, 1.0, -1.0).ravel()
    r = 0.001 * sign + 0.05 * z ** 2 * uv[:, 0] ** 2
    rs = lambda x: 1.4826 * np.median(np.abs(x - np.median(x)))      # noqa: E731
    p = group_parts(r, z, uv)
    assert rs(p["median"]) > 1.8e-3 and rs(p["plane"]) > 1.8e-3
    assert rs(p["quadric"]) == pytest.approx(1.4826e-3, rel=0.02)


def test_local_plane_sees_the_noise_of_a_twisted_target(tmp_path):
    """20 hand-made tilted frames (0-78 deg, 0.8-2.7 m, noise ``nguyen_incidence``) of a target
    twisted by 5e-3 /m (height 5e-3 x y m: a shape the frame's reference plane does not follow),
    160x120 at Kinect v1's whole field of view (f 145 px). The noise alone (the PNG's depth less the
    true twisted surface, put on the reference plane: the same pixels) gives the curve the estimator
    should read. About each (frame, bin) group's local plane the measured curve is within 6 % of it
    in every 0.25 m bin; about the median alone some bins read >= 15 % above it (the plane misfit
    counted as noise)."""
    from tests.plane_sequences import hand_made_plane_capture, twisted_depth
    from slam.plane_reference import PlaneReferenceConfig, make_plane_reference
    from synth.lab.calibration import noise_curve
    from synth.lab.features import FrameObservation
    import dataclasses
    tilts = np.tile([0, 50, 65, 72, 78], 4)
    dist = np.linspace(0.8, 2.7, 20) * np.cos(np.radians(tilts))
    W, H, f = 160, 120, 145.0
    cap = hand_made_plane_capture(tmp_path / "cap", dist, nguyen_incidence, 2, W, H, tilts, 0.005, f)
    make_plane_reference(tmp_path / "cap", tmp_path / "ref", PlaneReferenceConfig(), progress=False)
    ms = MeasuredSequence.load(tmp_path / "ref")
    obs = ms.observations([ms.measured_depth(k) for k in range(len(ms))])
    noise_only = []
    for k, o in enumerate(obs):
        m = ms.measured_depth(k)
        true = twisted_depth(cap["poses"][o.index], f, f, (W - 1) / 2, (H - 1) / 2, W, H, 0.005)
        noise_only.append(dataclasses.replace(o, measured=np.where((m > 0) & (o.ideal > 0) & (true > 0), o.ideal + (m - true), 0.0)))
    truth = noise_curve(noise_only, "measured", None)[0]
    plane = noise_curve(obs, "measured", None)[0] / truth
    median = noise_curve(obs, "measured", None, local_plane=False)[0] / truth
    ok = np.isfinite(plane)
    assert ok.sum() >= 9 and np.all(np.abs(plane[ok] - 1) <= 0.06), plane
    assert np.nanmax(median) >= 1.15, median


def nguyen_incidence(z, theta):
    """The known curve with incidence: 1.2 mm + 1.9 mm/m^2 (z - 0.4 m)^2 + 0.3 mm theta^2 / (pi/2 -
    theta)^2 / sqrt(z) (Nguyen et al. 2012's form, 3 x their incidence coefficient)."""
    from synth.sensor.effects.axial_noise import incidence_factor
    return 0.0012 + 0.0019 * (z - 0.4) ** 2 + 0.0003 * incidence_factor(theta) / np.sqrt(np.maximum(z, 0.05))


def test_incidence_factor_by_hand():
    """theta^2 / (pi/2 - theta)^2: 0 at 0, 1 at 45 deg, 4 at 60 deg, capped at 85 deg (289)."""
    from synth.sensor.effects.axial_noise import incidence_factor
    f = incidence_factor(np.radians([0.0, 45.0, 60.0, 85.0, 89.0]))
    assert f == pytest.approx([0.0, 1.0, 4.0, 289.0, 289.0])


def _fit_tilted_planes(tmp_path, noise, seed: int):
    """20 hand-made plane frames turned by 0, 50, 65, 72 or 78 deg at 0.8-2.7 m along the axis with ``noise``;
    ``axial_noise`` fitted on the even frames. Returns (the fit's result, the odd frames)."""
    tilts = np.tile([0, 50, 65, 72, 78], 4)
    dist = np.linspace(0.8, 2.7, 20) * np.cos(np.radians(tilts))
    ref = plane_reference(tmp_path, dist, noise, seed=seed, tilts_deg=tilts)
    fit, held = MeasuredSequence.load(ref, frame_slice="0::2"), MeasuredSequence.load(ref, frame_slice="1::2")
    res = fit_model(fit, fit.default_config(["axial_noise"]),
                    fit_config=FitConfig(max_frames=6, max_pixels_per_frame=4000, eval_pixels_per_frame=8000,
                                         intervals=False))
    return res, held


def test_fit_recovers_a_known_incidence_curve_on_held_out_frames(tmp_path):
    """20 hand-made plane frames (no simulator), each turned by exactly 0, 50, 65, 72 or 78 deg, at
    0.8-2.7 m along the axis, noise ``nguyen_incidence``; fitted on the even frames (the incidence
    term is fitted there: a planar reference), checked on the odd ones: the incidence coefficient
    within 20 % of 0.3 mm, and the simulated plane-fit std within 10 % of the measured in every
    0.25 m bin (a z^2 curve alone was 1.28 x too high at normal incidence and 0.81 x at grazing)."""
    from synth.lab.calibration import curve_table
    res, held = _fit_tilted_planes(tmp_path, nguyen_incidence, seed=2)
    assert res.params["axial_noise.incidence_m"] == pytest.approx(0.0003, rel=0.2)
    rows = curve_table(held.observations(held.simulate(res.config, 0)), None, 0)
    assert len(rows) >= 8 and all(abs(r["ratio"] - 1) <= 0.10 for r in rows), rows
    # elsewhere (no planar reference) the incidence term is not a fitted parameter
    from synth.lab.params import param_specs
    cfg = held.default_config(["axial_noise"])
    assert "axial_noise.incidence_m" not in [s.key for s in param_specs(cfg)]
    assert "axial_noise.incidence_m" in [s.key for s in param_specs(cfg, plane=True)]


def _checker_frame(index, amp_measured, amp_simulated, z=1.1):
    """A plane at ``z`` (bin 1.0-1.25 m), residuals +-amp (robust std 1.4826 amp) on a checkerboard."""
    ideal = np.full((30, 40), z, np.float32)
    sign = np.where(np.indices(ideal.shape).sum(0) % 2 == 0, 1.0, -1.0)
    return SimpleNamespace(ideal=ideal, index=index, measured=(ideal + amp_measured * sign).astype(np.float32),
                           simulated=(ideal + amp_simulated * sign).astype(np.float32))


def test_curve_bootstrap_by_hand():
    """Identical frames: every replicate gives the same std, so the interval has no width (1.4826 mm,
    ratio exactly 2). Two frames of +-1 and +-3 mm: a replicate draws {1, 1}, {1, 3} or {3, 3} (chance
    1/4, 1/2, 1/4), whose pooled robust std is 1.4826, 2.9652 (the median |r| of a 50/50 mix is 2 mm)
    or 4.4478 mm: the 95 % interval spans 1.4826-4.4478 mm, the ratio (simulated +-2 mm on both
    frames) 2/3-2. Blocks of 2 frames draw both frames together: no spread again."""
    from synth.lab.calibration import curve_groups, curve_uncertainty
    same = [_checker_frame(k, 0.001, 0.002) for k in range(4)]
    u = curve_uncertainty(curve_groups(same, "measured", None), [curve_groups(same, "simulated", None)], 4, n_boot=50)
    assert u[2]["frames"] == 4 and u[0]["frames"] == 0 and np.isnan(u[0]["measured_ci"][0])
    assert u[2]["measured_ci"] == pytest.approx((1.4826e-3, 1.4826e-3), rel=1e-3)
    assert u[2]["ratio_ci"] == pytest.approx((2.0, 2.0), rel=1e-3)
    two = [_checker_frame(0, 0.001, 0.002), _checker_frame(1, 0.003, 0.002)]
    u = curve_uncertainty(curve_groups(two, "measured", None), [curve_groups(two, "simulated", None)], 2, n_boot=200)
    assert u[2]["measured_ci"] == pytest.approx((1.4826e-3, 4.4478e-3), rel=1e-3)
    assert u[2]["ratio_ci"] == pytest.approx((2.0 / 3.0, 2.0), rel=1e-3)
    u = curve_uncertainty(curve_groups(two, "measured", None), [curve_groups(two, "simulated", None)], 2, n_boot=50,
                          block=2)
    assert u[2]["measured_ci"][0] == pytest.approx(u[2]["measured_ci"][1])


def test_bench_verdicts():
    """A bin is judged only with enough frames; OFF only when the whole ratio interval is outside 10 %."""
    from benchmarks.bench_plane_noise import verdict
    assert verdict(0.70, (0.3, 1.05), 7, 10) == "too few frames"
    assert verdict(1.05, (0.8, 1.3), 20, 10) == "within"
    assert verdict(0.85, (0.75, 0.95), 20, 10) == "unresolved"
    assert verdict(0.85, (0.80, 0.89), 20, 10) == "OFF"
    assert verdict(1.20, (1.12, 1.30), 20, 10) == "OFF"


def disparity_incidence(z, theta):
    """A known curve whose incidence term is constant in disparity: 1.0 mm + 1.6 mm/m^2 z^2 + 0.05 mm
    theta^2 / (pi/2 - theta)^2 (z / 1 m)^2 (axial_noise.incidence_z_exponent 2)."""
    from synth.sensor.effects.axial_noise import incidence_factor
    return 0.0010 + 0.0016 * z ** 2 + 0.00005 * incidence_factor(theta) * z ** 2


@pytest.mark.slow
def test_fit_recovers_an_incidence_term_constant_in_disparity(tmp_path):
    """As the incidence test above, with the incidence term growing as z^2 (Nguyen's law falls as
    1 / sqrt z: at 78 deg it would be 5.6 x too high at 0.8 m for the 2.5 m value): the fitted distance
    law is the disparity one (exponent >= 1.5) and every held-out 0.25 m bin is within 10 %."""
    from synth.lab.calibration import curve_table
    res, held = _fit_tilted_planes(tmp_path, disparity_incidence, seed=3)
    assert res.params["axial_noise.incidence_z_exponent"] >= 1.5, res.params
    rows = curve_table(held.observations(held.simulate(res.config, 0)), None, 0)
    assert len(rows) >= 8 and all(abs(r["ratio"] - 1) <= 0.10 for r in rows), rows


def test_hint_when_the_search_moves_do_not_hold_on_the_evaluation_frames():
    """The fit's line for a search whose moves were all put back on the evaluation frames names them
    and the wider search; none when a move was kept, nothing moved, or the search used every frame."""
    from types import SimpleNamespace

    from synth.lab.runs import unheld_moves_hint
    res = SimpleNamespace(gap_before=0.3873, gap=0.3873, reverted=["ir_capture.gain_e"], kept_start=False,
                          frames=[0, 8, 16, 23], eval_frames=list(range(24)))
    hint = unheld_moves_hint(res)
    assert "ir_capture.gain_e" in hint and "4 frames" in hint and "max_frames=12" in hint
    assert unheld_moves_hint(SimpleNamespace(**{**vars(res), "gap": 0.33})) is None
    assert unheld_moves_hint(SimpleNamespace(**{**vars(res), "reverted": []})) is None
    assert "every parameter" in unheld_moves_hint(SimpleNamespace(**{**vars(res), "reverted": [], "kept_start": True}))
    assert unheld_moves_hint(SimpleNamespace(**{**vars(res), "frames": list(range(24))})) is None
