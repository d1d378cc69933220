"""Sensor lab comparison core: features, the gap and its properties, breakdowns, maps, worst
regions, report and history. All fixtures are analytic (numpy ray casting of a tilted plane and
a box at 160x120), seeded, and need no simulator."""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from data_tools.camera import Intrinsics
from data_tools.errors import ConfigError, FormatError, RealgapError
from synth.lab import (CompareConfig, FrameObservation, append_history, compare, compare_preset,
                       error_map, load_history, load_result, run_lab, validity_map, worst_bins,
                       worst_blocks, worst_regions)
from synth.lab.compare import CompareCache, error_scale_m, wasserstein1
from synth.lab.feature_maps import (depth_edges, incidence_angle_deg, radial_distance, shadow_edge_distance,
                                    signed_edge_distance)
from synth.lab.history import step_labels

W, H, F = 160, 120, 150.0
INTR = Intrinsics(W, H, F, F, (W - 1) / 2, (H - 1) / 2)
PROJ = (0.075, 0.0, 0.0)
NAMES = {0: "(no geometry)", 1: "wall", 2: "plastic"}
EXACT = CompareConfig(max_pixels_per_frame=None)


# ------------------------------------------------------------------------------------------
# Analytic scene: plane Z + a Y + c X = z0 (far at the top) and an axis-aligned box in front
# ------------------------------------------------------------------------------------------

def _box_hit(origin, d, lo, hi, tmax_limit=np.inf):
    """Slab test of rays origin + t d (N, 3) with a box; returns (hit, t_near, entering axis)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (np.asarray(lo) - origin) / d
        t2 = (np.asarray(hi) - origin) / d
    tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    tmaxs = np.where(np.isnan(t2), np.inf, np.maximum(t1, t2))
    tn = tmin.max(axis=1)
    tf = tmaxs.min(axis=1)
    hit = (tn <= tf) & (tf > 1e-9) & (tn < tmax_limit)
    return hit, tn, tmin.argmax(axis=1)


def make_scene(box_dx=0.0, a=1.2, c=0.3, z0=2.5):
    """Ideal depth, normals, ids of the plane + box scene, and the box bounds."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    d = np.stack([(u - INTR.cx) / F, (v - INTR.cy) / F, np.ones_like(u)], -1).reshape(-1, 3)
    z = z0 / (1 + a * d[:, 1] + c * d[:, 0])
    n = np.tile(np.array([c, a, 1.0]) / np.linalg.norm([c, a, 1.0]), (d.shape[0], 1))
    ids = np.ones(d.shape[0], np.int32)
    lo = np.array([-0.3 + box_dx, -0.2, 1.2])
    hi = np.array([0.25 + box_dx, 0.25, 1.5])
    hit, tn, ax = _box_hit(np.zeros(3), d, lo, hi)
    hit &= tn < z
    z[hit] = tn[hit]
    nb = np.zeros((hit.sum(), 3))
    nb[np.arange(hit.sum()), ax[hit]] = 1.0
    n[hit] = nb
    ids[hit] = 2
    return z.reshape(H, W).astype(np.float32), n.reshape(H, W, 3).astype(np.float32), ids.reshape(H, W), (lo, hi)


def projector_shadow(ideal, box, proj):
    """Pixels whose surface point cannot see the projector because the box is in the way."""
    lo, hi = box
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    z = ideal.astype(np.float64).ravel()
    p = np.stack([(u.ravel() - INTR.cx) / F * z, (v.ravel() - INTR.cy) / F * z, z], -1)
    seg = np.asarray(proj)[None, :] - p
    hit, tn, _ = _box_hit(p, seg, lo, hi, tmax_limit=1.0)
    return (hit & (tn > 1e-6)).reshape(H, W)


def sigma(z):
    return 0.0005 + 0.0015 * z * z


def sense(ideal, rng, *, noise=1.0, bias=0.0, hole_rate=0.03, shadow=None, far_bias=None):
    """A toy sensor: depth-dependent Gaussian noise, bias, random holes, projector shadow."""
    d = ideal + noise * sigma(ideal) * rng.standard_normal(ideal.shape) + bias
    if far_bias is not None:
        d = d + np.where(ideal > 2.0, far_bias, 0.0)
    d[rng.random(ideal.shape) < hole_rate] = 0
    if shadow is not None:
        d[shadow] = 0
    d[ideal <= 0] = 0
    return d.astype(np.float32)


SHIFTS = (-0.2, 0.0, 0.15)
_SCENES = [make_scene(dx) for dx in SHIFTS]
_SHADOWS = [projector_shadow(s[0], s[3], PROJ) for s in _SCENES]
_WRONG = [projector_shadow(s[0], s[3], (-PROJ[0], 0, 0)) for s in _SCENES]


def frames(sim_seed=100, meas_seed=1, shadow="right", **sim):
    """Measured (noise 1, holes 3 %, correct shadow) and a simulated variant per frame."""
    out = []
    for k, (ideal, normals, ids, _) in enumerate(_SCENES):
        meas = sense(ideal, np.random.default_rng([meas_seed, k]), shadow=_SHADOWS[k])
        sh = {"right": _SHADOWS[k], "wrong": _WRONG[k], "none": None}[shadow]
        simd = sense(ideal, np.random.default_rng([sim_seed, k]), shadow=sh, **sim)
        out.append(FrameObservation(meas, simd, ideal, normals, ids, NAMES, INTR, PROJ, index=k))
    return out


def gap(**kw):
    return compare(frames(**kw), EXACT).gap


# ------------------------------------------------------------------------------------------
# Features
# ------------------------------------------------------------------------------------------

def test_fixture_has_a_visible_projector_shadow():
    assert all(150 < s.sum() < 1000 for s in _SHADOWS)  # ~5 px x ~56 px
    assert not any((s & w).any() for s, w in zip(_SHADOWS, _WRONG))


def test_signed_edge_distance_hand_example():
    z = np.full((6, 16), 2.0, np.float32)
    z[:, 6:10] = 1.0                      # foreground columns 6..9
    e = signed_edge_distance(z, 0.05)
    row = e[3]
    assert row[5] == 0.5 and row[4] == 1.5 and row[0] == 5.5      # background (far): +
    assert row[6] == -0.5 and row[7] == -1.5 and row[9] == -0.5   # foreground (near): -
    assert row[10] == 0.5 and row[15] == 5.5
    assert np.isinf(signed_edge_distance(np.full((4, 4), 1.0, np.float32))).all()
    # a 1 % step is not an edge at the default 5 % threshold; an empty pixel is
    z2 = np.full((3, 5), 1.0, np.float32)
    z2[:, 3:] = 1.01
    assert not depth_edges(z2).near.any()
    z2[1, 0] = 0
    ed = depth_edges(z2)
    assert ed.far[1, 0] and ed.near[1, 1] and ed.near[0, 0]


def test_projector_shadow_falls_opposite_to_the_projector():
    """Camera at 0, projector at +b along x: the shadow of a foreground lies at -u of its left
    edge, f b (1/z_f - 1/z_b) pixels wide, and edge_shadow marks exactly that side with +."""
    w, h, f, b, zf, zb = 60, 20, 100.0, 0.1, 1.0, 2.0
    intr = Intrinsics(w, h, f, f, (w - 1) / 2, (h - 1) / 2)
    u = np.arange(w) - intr.cx
    x_fg = (-0.05, 0.12)                  # foreground plane z_f, x in [x0, x1] (metres), all rows
    ideal = np.full((h, w), zb, np.float32)
    fg_cols = (u / f * zf >= x_fg[0]) & (u / f * zf <= x_fg[1])
    ideal[:, fg_cols] = zf
    # ray-cast the shadow: background point -> projector segment crosses z_f inside the foreground
    xb = u / f * zb
    s = 1 - zf / zb
    x_at_fg = xb + s * (b - xb)
    shadow_cols = ~fg_cols & (x_at_fg >= x_fg[0]) & (x_at_fg <= x_fg[1])
    cols = np.flatnonzero(shadow_cols)
    left_edge = np.flatnonzero(fg_cols)[0]
    assert cols.size == round(f * b * (1 / zf - 1 / zb))        # 5 px wide
    assert cols.max() == left_edge - 1                           # directly left of the foreground
    es = shadow_edge_distance(ideal, intr, (b, 0, 0))
    ed = signed_edge_distance(ideal)
    row = h // 2
    assert (es[row, cols] > 0).all() and (ed[row, cols] > 0).all()
    right = np.flatnonzero(~fg_cols & (np.arange(w) > left_edge))
    assert (es[row, right] < 0).all() and (ed[row, right] > 0).all()
    assert np.isnan(es[row, fg_cols]).all()
    np.testing.assert_allclose(es[row, cols], left_edge - cols - 0.5)
    # a projector at -x swaps the sides
    es2 = shadow_edge_distance(ideal, intr, (-b, 0, 0))
    assert (es2[row, cols] < 0).all() and (es2[row, right] > 0).all()
    # the analytic fixture agrees: every shadowed pixel is on the + side of edge_shadow
    ideal3, _, _, _ = _SCENES[1]
    es3 = shadow_edge_distance(ideal3, INTR, PROJ)
    assert (es3[_SHADOWS[1]] > 0).mean() > 0.95
    assert (es3[_WRONG[1]] < 0).mean() > 0.95


def test_incidence_and_radial_hand_values():
    intr = Intrinsics(5, 5, 10.0, 10.0, 2.0, 2.0)
    n = np.zeros((5, 5, 3), np.float32)
    n[..., 2] = -1.0                       # fronto-parallel, facing the camera
    ang = incidence_angle_deg(n, intr)
    assert ang[2, 2] == pytest.approx(0.0)
    assert ang[2, 4] == pytest.approx(math.degrees(math.atan(0.2)), abs=1e-9)
    n[2, 2] = (1, 0, 1)                    # 45 deg tilt
    assert incidence_angle_deg(n, intr)[2, 2] == pytest.approx(45.0)
    n[2, 2] = 0
    assert np.isnan(incidence_angle_deg(n, intr)[2, 2])
    # seen from a projector at +1 m along x, a fronto-parallel point at z=1 on the axis: 45 deg
    n[2, 2] = (0, 0, 1)
    depth = np.ones((5, 5), np.float32)
    assert incidence_angle_deg(n, intr, depth, (1.0, 0, 0))[2, 2] == pytest.approx(45.0)
    rn, rpx = radial_distance(intr)
    assert rn[2, 2] == 0 and rn[0, 0] == pytest.approx(1.0) and rpx[0, 0] == pytest.approx(math.sqrt(8))


# ------------------------------------------------------------------------------------------
# Gap properties
# ------------------------------------------------------------------------------------------

def test_wasserstein1_matches_scipy():
    from scipy.stats import wasserstein_distance

    rng = np.random.default_rng(0)
    for na, nb in ((1, 1), (7, 13), (200, 50)):
        a, b = rng.normal(size=na), rng.normal(0.3, 2, size=nb)
        assert wasserstein1(a, b) == pytest.approx(wasserstein_distance(a, b), rel=1e-12, abs=1e-15)
    a = rng.integers(0, 3, 40).astype(float)   # ties
    assert wasserstein1(a, a[::-1]) == 0.0


def test_w1_noise_floor_constant_matches_simulation():
    """E[W1] of two normal samples = W1_NULL_CONSTANT sigma sqrt(1/n + 1/m) (used by the floor)."""
    from synth.lab.gap_stats import W1_NULL_CONSTANT

    rng = np.random.default_rng(1)
    n, m, sd = 300, 700, 2.5
    w = [wasserstein1(rng.normal(0, sd, n), rng.normal(1, sd, m) - 1) for _ in range(300)]
    assert np.mean(w) == pytest.approx(W1_NULL_CONSTANT * sd * math.sqrt(1 / n + 1 / m), rel=0.06)


def test_worst_bins_are_silent_for_a_correct_model_and_name_the_failure_otherwise():
    for seeds in ((100, 1), (200, 1), (300, 5)):
        obs = frames(sim_seed=seeds[0], meas_seed=seeds[1])
        r = compare(obs, EXACT)
        assert worst_bins(r) == [] and worst_blocks(obs, EXACT) == []
    r = compare(frames(noise=1.2), EXACT)
    top = worst_bins(r)
    assert top and all("noise is too high" in x.description for x in top)
    assert all(x.details["term"] > 3 * x.details["noise_floor"] for x in top)


def test_gap_of_identical_sequences_is_exactly_zero():
    obs = frames()
    same = [FrameObservation(o.measured, o.measured.copy(), o.ideal, o.normals, o.material_ids,
                             NAMES, INTR, PROJ, o.index) for o in obs]
    r = compare(same)
    assert r.gap == 0.0 and r.spatial_term == 0.0
    assert all(g == 0.0 for g in r.frame_gaps)


def test_gap_is_stable_across_noise_draws():
    g1, g2 = gap(sim_seed=100), gap(sim_seed=200)
    g_double = gap(sim_seed=100, noise=2.0)
    assert abs(g1 - g2) < 0.1 * g_double
    assert g_double > 3 * max(g1, g2)


@pytest.mark.parametrize("param,values", [
    ("noise", [1.0, 1.5, 2.0, 3.0]),
    ("noise", [1.0, 0.6, 0.3, 0.0]),
    ("bias", [0.0, 0.002, 0.005, 0.01]),
    ("bias", [0.0, -0.003, -0.01]),
    ("hole_rate", [0.03, 0.1, 0.2, 0.4]),
    ("hole_rate", [0.03, 0.0]),
])
def test_gap_grows_as_a_parameter_moves_away_from_the_measured_one(param, values):
    gaps = [gap(**{param: v}) for v in values]
    assert all(b > a for a, b in zip(gaps, gaps[1:])), gaps


def test_ideal_model_is_worse_than_a_model_with_the_right_noise():
    ideal_model = gap(noise=0.0, hole_rate=0.0, shadow="none")
    right = gap()
    assert ideal_model > 5 * right


def test_shadow_on_the_wrong_side_is_caught():
    right = compare(frames(), EXACT)
    wrong = compare(frames(shadow="wrong"), EXACT)
    none = compare(frames(shadow="none"), EXACT)
    assert wrong.gap > right.gap and none.gap > right.gap
    assert wrong.spatial_term > 10 * max(right.spatial_term, 1e-4)
    # binned by edge_shadow, measured holes sit on the + (shadow) side, the wrong model's on -
    b = wrong.breakdowns["edge_shadow"]
    labels = b["labels"]
    near_plus = [labels.index(x) for x in ("0..1", "1..2", "2..4")]
    near_minus = [labels.index(x) for x in ("-1..0", "-2..-1", "-4..-2")]
    pm, ps = np.array(b["measured"]["invalid_fraction"]), np.array(b["simulated"]["invalid_fraction"])
    assert (pm[near_plus] > ps[near_plus] + 0.3).all()
    assert (ps[near_minus] > pm[near_minus] + 0.3).all()
    # edge_distance (+ = background on either side) cannot tell the sides apart as well
    assert wrong.feature_terms["edge_shadow"] > wrong.feature_terms["edge_distance"]


def test_far_bias_shows_only_in_far_distance_bins_hand_computed():
    """Noise-free fixture: measured = ideal, simulated = ideal + 5 mm beyond 2 m."""
    obs = []
    for k, (ideal, normals, ids, _) in enumerate(_SCENES):
        sim = np.where(ideal > 2.0, ideal + 0.005, ideal).astype(np.float32)
        obs.append(FrameObservation(ideal.copy(), sim, ideal, normals, ids, NAMES, INTR, PROJ, index=k))
    r = compare(obs, EXACT)
    b = r.breakdowns["distance"]
    edges = b["edges"]
    z = np.concatenate([o.ideal.ravel() for o in obs]).astype(np.float64)
    cfg = EXACT
    seen_far = seen_near = 0
    for i, (lo, hi) in enumerate(zip(edges, edges[1:])):
        if b["measured"]["count"][i] < cfg.min_bin_count:
            continue
        sel = (z >= lo) & (z < hi)
        if lo >= 2.0:
            seen_far += 1
            assert b["simulated"]["bias"][i] - b["measured"]["bias"][i] == pytest.approx(0.005, abs=2e-6)
            expected = float(np.mean(0.005 / error_scale_m(z[sel], cfg)))   # W1 vs a point mass at 0
            assert b["w1"][i] == pytest.approx(expected, rel=1e-3)
            assert b["term"][i] == pytest.approx(expected, rel=1e-3)
        elif hi <= 2.0:
            seen_near += 1
            assert b["simulated"]["bias"][i] == pytest.approx(0.0, abs=1e-6)
            assert b["term"][i] == 0.0
    assert seen_far >= 4 and seen_near >= 1
    assert r.spatial_term == 0.0


def test_far_bias_is_recovered_under_noise():
    r = compare(frames(far_bias=0.005), EXACT)
    b = r.breakdowns["distance"]
    e = b["edges"]
    db = np.array(b["simulated"]["bias"]) - np.array(b["measured"]["bias"])
    n = np.array(b["measured"]["count"])
    far = np.array([lo >= 2.25 for lo in e[:-1]]) & (n > 500)
    near = np.array([hi <= 1.75 for hi in e[1:]]) & (n > 500)
    assert far.sum() >= 3 and near.sum() >= 1
    # median of n normal samples: std 1.2533 sigma / sqrt(n); difference of two: x sqrt(2); 4 sd
    tol = 4 * 1.2533 * sigma(np.array(b["centres"])) * np.sqrt(2 / np.maximum(n, 1))
    assert (np.abs(db[far] - 0.005) < tol[far]).all()
    assert (np.abs(db[near]) < tol[near]).all() and (tol[near] < 0.001).all()
    top = worst_bins(r, 3)
    assert any(x.feature == "distance" and "too far" in x.description for x in top)


def test_subsampling_is_seeded_and_close_to_exact():
    obs = frames(noise=1.5)
    a = compare(obs, CompareConfig(max_pixels_per_frame=8000, seed=3))
    b = compare(obs, CompareConfig(max_pixels_per_frame=8000, seed=3))
    exact = compare(obs, EXACT)
    assert a.gap == b.gap and a.n_samples == 3 * 8000
    assert a.gap == pytest.approx(exact.gap, rel=0.15)


def _same_data(obs, **sim):
    """Observations sharing the measured/ideal arrays of ``obs`` with new simulated depth."""
    out = []
    for k, o in enumerate(obs):
        simd = sense(o.ideal, np.random.default_rng([500, k]), shadow=_SHADOWS[k], **sim)
        out.append(FrameObservation(o.measured, simd, o.ideal, o.normals, o.material_ids, NAMES, INTR, PROJ,
                                    index=o.index))
    return out


def test_cache_gives_identical_results_and_is_keyed_on_the_data():
    obs = frames(noise=1.5)
    other = _same_data(obs, noise=0.7, hole_rate=0.1)
    for cfg in (CompareConfig(max_pixels_per_frame=4000, seed=3), EXACT):
        cache = CompareCache()
        for o in (obs, other, obs):
            assert compare(o, cfg, cache=cache).to_json() == compare(o, cfg).to_json()
        assert (cache.misses, cache.hits) == (3, 6)
    # a different measured array at the same position is not served from the cache
    cache = CompareCache()
    compare(obs, EXACT, cache=cache)
    changed = [FrameObservation(o.measured.copy(), o.simulated, o.ideal, o.normals, o.material_ids, NAMES, INTR,
                                PROJ, index=o.index) for o in obs]
    changed[1].measured[changed[1].measured > 0] += 0.05
    assert compare(changed, EXACT, cache=cache).to_json() == compare(changed, EXACT).to_json()
    assert cache.misses == 6
    # other sampling settings are other entries; the size is bounded
    small = CompareCache(max_entries=4)
    compare(obs, CompareConfig(max_pixels_per_frame=1000), cache=small)
    compare(obs, CompareConfig(max_pixels_per_frame=2000), cache=small)
    assert len(small) == 4 and small.misses == 6


# ------------------------------------------------------------------------------------------
# Result, maps, worst regions
# ------------------------------------------------------------------------------------------

def test_result_json_round_trip_and_metrics_keys(tmp_path):
    r = compare(frames(bias=0.003), compare_preset("fast"), effects=["noise", "shadow"], label="step 2")
    p = r.save(tmp_path)
    d = json.loads(p.read_text())
    assert set(d) >= {"gap", "breakdowns", "frame_gaps", "config"}
    assert set(d["breakdowns"]) >= {"distance", "incidence", "radial", "material", "edge_distance"}
    assert set(d["breakdowns"]["material"]["labels"]) == {"wall", "plastic"}
    assert len(d["breakdowns"]["distance"]["noise_floor"]) == len(d["breakdowns"]["distance"]["labels"])
    for side in ("measured", "simulated"):
        assert set(d["breakdowns"]["distance"][side]) >= {"bias", "std", "invalid_fraction", "count"}
    r2 = load_result(tmp_path)
    assert r2.to_json() == r.to_json()
    assert r2.gap == r.gap and r2.effects == ["noise", "shadow"]
    assert math.isinf(r2.breakdowns["edge_distance"]["edges"][0])
    assert CompareConfig.from_dict(r2.config).to_dict() == compare_preset("fast").to_dict()
    (tmp_path / "bad.json").write_text("{\"gap\": 1}")
    with pytest.raises(FormatError, match="bad.json"):
        load_result(tmp_path / "bad.json")


def test_error_and_validity_maps_hand_example():
    intr = Intrinsics(3, 1, 1.0, 1.0, 1.0, 0.0)
    o = FrameObservation(np.array([[1.0, 0.0, 2.0]]), np.array([[1.5, 1.0, 0.0]]),
                         np.ones((1, 3)), np.zeros((1, 3, 3)), np.ones((1, 3), np.int32), ["-", "a"], intr)
    em = error_map(o)
    assert em[0, 0] == pytest.approx(-0.5) and np.isnan(em[0, 1:]).all()
    o.simulated[0, 2] = 0
    o.measured[0, 2] = 0
    assert validity_map(o).tolist() == [[0, 2, 3]]
    o.measured[0, 2] = 2.0
    assert validity_map(o).tolist() == [[0, 2, 1]]


def test_worst_block_finds_a_local_defect():
    obs = frames()
    o = obs[1]
    sim = o.simulated.copy()
    sim[64:96, 96:128] = np.where(sim[64:96, 96:128] > 0, sim[64:96, 96:128] + 0.03, 0)  # 3 cm bump
    obs[1] = FrameObservation(o.measured, sim, o.ideal, o.normals, o.material_ids, NAMES, INTR, PROJ, index=7)
    r = compare(obs, EXACT)
    assert int(np.nanargmax(r.frame_gaps)) == 1
    blocks = worst_blocks(obs, EXACT, top=3, block_px=32)
    assert blocks[0].frame == 1 and blocks[0].frame_index == 7 and blocks[0].bbox == (96, 64, 128, 96)
    assert "too far" in blocks[0].description and blocks[0].rank == 1
    regs = worst_regions(r, obs, top_bins=2, top_blocks=2)
    kinds = [x.kind for x in regs]
    assert kinds[:2] == ["bin", "bin"] and kinds[2:] == ["block"]    # only the bump is beyond noise
    assert regs[2].bbox == (96, 64, 128, 96)
    assert all(x.description.endswith(".") for x in regs)


# ------------------------------------------------------------------------------------------
# Report and history
# ------------------------------------------------------------------------------------------

def test_history_append_load_and_continue(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    append_history(a, [], 0.9, timestamp="2025-01-01T00:00:00+00:00")
    h = append_history(a, ["noise"], 0.5)
    assert [e["gap"] for e in h] == [0.9, 0.5] and [e["step"] for e in h] == [0, 1]
    h2 = append_history(b, ["noise", "shadow"], 0.2, "with shadow", compare_against=a)
    assert [e["gap"] for e in h2] == [0.9, 0.5, 0.2] and len(load_history(a)) == 2
    assert step_labels(h2) == ["ideal", "+noise", "with shadow"]
    assert load_history(tmp_path / "missing") == []
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "history.json").write_text('{"entries": [{"gap": 1}]}')
    with pytest.raises(FormatError, match="history.json"):
        load_history(tmp_path / "c")
    with pytest.raises(FormatError):
        append_history(tmp_path / "d", [], 0.1, compare_against=tmp_path / "nowhere")


def test_report_html_references_existing_images(tmp_path):
    """One lab step with run_lab (compare + metrics.json + history + report) after an earlier
    step recorded in another folder; a reduced feature set keeps the plotting fast."""
    cfg = CompareConfig(max_pixels_per_frame=5000, gap_features=("distance", "material", "edge_shadow"),
                        extra_features=())
    prev = tmp_path / "step0"
    append_history(prev, [], 1.0)
    obs = frames(shadow="wrong", noise=1.5)
    out = tmp_path / "step1"
    r = run_lab(obs, out, effects=["noise", "shadow"], config=cfg, compare_against=prev, report_frames=2)
    text = (out / "report.html").read_text()
    srcs = re.findall(r"<img src='([^']+)'", text)
    assert len(srcs) == 1 + 3 + 2                     # history, 3 breakdowns, 2 frames
    for s in srcs:
        assert (out / s).stat().st_size > 5000, s
    assert "figures/history.png" in srcs
    assert [e["gap"] for e in load_history(out)] == [1.0, pytest.approx(r.gap)]
    assert load_result(out).gap == pytest.approx(r.gap)
    regions = json.loads((out / "regions.json").read_text())
    assert {x["kind"] for x in regions} == {"bin", "block"}
    assert "Where the model fails worst" in text and html_escape(regions[0]["description"]) in text


def html_escape(s):
    import html

    return html.escape(s)


# ------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------

def test_bad_input_raises_clear_errors():
    ideal, normals, ids, _ = _SCENES[0]
    with pytest.raises(RealgapError, match="measured.*NaN"):
        FrameObservation(np.full((H, W), np.nan), ideal, ideal, normals, ids, NAMES, INTR)
    with pytest.raises(RealgapError, match="simulated.*shape"):
        FrameObservation(ideal, ideal[:10], ideal, normals, ids, NAMES, INTR)
    with pytest.raises(RealgapError, match="material_ids.*integer"):
        FrameObservation(ideal, ideal, ideal, normals, ids.astype(float), NAMES, INTR)
    with pytest.raises(RealgapError, match="negative"):
        FrameObservation(-ideal, ideal, ideal, normals, ids, NAMES, INTR)
    with pytest.raises(RealgapError, match="no frames"):
        compare([])
    z = np.zeros((H, W), np.float32)
    with pytest.raises(RealgapError, match="no frame has ideal geometry"):
        compare([FrameObservation(ideal, ideal, z, normals, ids, NAMES, INTR)])
    with pytest.raises(ConfigError, match="unknown lab feature"):
        compare(frames()[:1], CompareConfig(gap_features=("distance", "colour")))
    with pytest.raises(ConfigError, match="preset"):
        compare_preset("nope")


def test_features_needing_a_projector_are_skipped_without_one():
    obs = [FrameObservation(o.measured, o.simulated, o.ideal, o.normals, o.material_ids, NAMES, INTR)
           for o in frames(noise=2.0)]
    r = compare(obs, compare_preset("fast"))
    assert "edge_shadow" in r.skipped_features and "edge_shadow" not in r.gap_features
    assert r.gap_features == ["distance", "incidence", "radial", "material", "edge_distance"]
    assert r.gap > 0.3
