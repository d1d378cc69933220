"""Per-effect tests: each proves its effect on a tiny analytic scene (160x120 crop of the
Kinect v1 geometry, same focal length and baseline)."""
from __future__ import annotations

import numpy as np
import pytest

from synth.sensor import MotionLimits, SensorConfig, SensorSimulator, get_preset, make_effect
from synth.sensor.matching import MatchSetup
from synth.sensor.testscenes import box_before_wall_scene, camera_pose, corner_scene, wall_scene

K1 = get_preset("kinect_v1")
SMALL = K1.cropped(160, 120)
FB = K1.fb
T = camera_pose()


@pytest.fixture(scope="module")
def box_scene():
    # box front face at 1.4 m (left edge at u = 38.1 in the crop), wall at 2 m
    return box_before_wall_scene(2.0, 1.5, 0.2)


NO_MOTION_LIMIT = MotionLimits(0.0, 0.0)   # the motion tests use large motions to make effects measurable


def run(effects, scene, preset=SMALL, seed=0, motion=None, **kw):
    cfg = SensorConfig.build(preset, effects, motion=motion)
    return SensorSimulator(cfg, None, scene).simulate(T, seed=seed, **kw)


def apply_one(name, scene, params=None, preset=SMALL, seed=0, prepare=None):
    """Apply one effect to the ideal state by hand; returns the state."""
    sim = SensorSimulator(preset, [], scene)
    st, _, _ = sim.make_state(T)
    if prepare:
        prepare(st)
    e = make_effect({"name": name, "params": params or {}}, preset.effect_params.get(name))
    e.apply(st, e.sample(e.rng(seed), st))
    return st


# ---------------------------------------------------------------- projector shadow
@pytest.mark.parametrize("model", ["physical", "direct"])
@pytest.mark.parametrize("side", [+1, -1])
def test_projector_shadow_side(box_scene, model, side):
    """Projector at +x: light comes from the image's right, the box shadows the wall on its
    LEFT (-u) side, in a band f b (1/z_box - 1/z_wall) = 9.3 px wide; at -x, mirrored."""
    pre = SMALL.replace(projector_offset_m=(side * 0.075, 0.0, 0.0))
    effects = ["projector_shadow"] if model == "direct" else None
    res = run(effects, box_scene, pre)
    rows = slice(45, 75)
    width = FB * (1 / 1.4 - 1 / 2.0)
    left_band = (~res.valid[rows, 38 - 14:38]).sum(1).mean()      # wall just left of the box
    right_band = (~res.valid[rows, 121:121 + 14]).sum(1).mean()   # wall just right of it
    shadow, lit = (left_band, right_band) if side > 0 else (right_band, left_band)
    assert abs(shadow - width) < 2.0, (shadow, width)
    assert lit < 1.0


def test_projector_shadow_cast_by_geometry_only(box_scene):
    st = apply_one("projector_shadow", box_scene)
    hidden = ~st.valid & st.ideal.hit
    cols = np.nonzero(hidden[60])[0]
    u_shadow_start = 79.5 + 580 * (0.075 - 0.125 * 2.0) / 2.0     # ray through the box's front-left corner
    u_box = 79.5 - 580 * 0.1 / 1.4                              # box's left edge, 38.07
    assert cols.min() == pytest.approx(u_shadow_start, abs=1.0)
    assert cols.max() == int(np.floor(u_box)) and st.ideal.depth[60, int(np.ceil(u_box))] == pytest.approx(1.4)


def _shadow_masks(scene, preset=SMALL):
    """{method: (unlit-by-shadow mask, stats)} of pattern_projection on ``scene``."""
    import dataclasses
    from synth.sensor.effects.pattern_projection import blurred_pattern, compute_radiance
    sim = SensorSimulator(preset, None, scene)
    st = sim.make_state(T)[0]
    pp = sim.effect("pattern_projection")
    pb = blurred_pattern(st.pattern, pp.params.dot_sigma_px, {})
    out = {}
    for m in ("raycast", "hybrid", "scanline"):
        prm = dataclasses.replace(pp.params, shadow_method=m)
        rad, stats = compute_radiance(st.view, (0, 0, 0), st.preset, pb, prm, sim.renderer, st.ray_dirs_cam)
        out[m] = (rad, stats)
    return out


def _plank_scenes():
    from data_tools.scene_spec import Material, SceneSpec
    from synth.sensor.testscenes import box_mesh, quad_mesh
    wall = quad_mesh([0.0, 0.0, 2.0], [10.0, 0, 0], [0, 10.0, 0], "wall", "wall")
    m = {"wall": Material(0.8, 0.0), "obj": Material(0.8, 0.0)}
    # beside the rig, outside the camera's view (right edge at x = 0.138 z) but in the projector's
    outside = box_mesh([0.13, 0.0, 0.3], [0.14, 2.0, 0.1], "outside", "obj")
    # a 1.5 cm rod 1 m in front of the wall: narrower than its shadow offset, so the ordering
    # test alone marks wall pixels whose projector ray passes beside it
    rod = box_mesh([0.0, 0.0, 1.0], [0.015, 2.0, 0.015], "rod", "obj")
    return {"outside": SceneSpec([wall, outside], m), "rod": SceneSpec([wall, rod], m)}


@pytest.mark.parametrize("which", ["box", "outside", "rod"])
def test_hybrid_shadow_matches_one_ray_per_pixel(box_scene, which):
    """The default 'hybrid' projector visibility gives the shadows of one exact shadow ray per
    pixel, also for an occluder outside the camera's view and for a thin rod (where the
    ordering test alone is wrong), with far fewer rays."""
    scene = box_scene if which == "box" else _plank_scenes()[which]
    out = _shadow_masks(scene)
    exact, hybrid, scan = (out[m][0] > 0 for m in ("raycast", "hybrid", "scanline"))
    n_shadow = out["raycast"][1]["shadowed_px"]
    assert n_shadow > 200
    assert np.count_nonzero(exact != hybrid) <= 2, np.count_nonzero(exact != hybrid)
    np.testing.assert_array_equal(out["hybrid"][0][hybrid & exact], out["raycast"][0][hybrid & exact])
    if which != "outside":  # (an occluder 25 cm from the projector needs the out-of-view rays)
        assert out["hybrid"][1]["shadow_rays"] < 0.5 * out["hybrid"][1]["lit_px"]
    if which != "box":      # where the ordering test alone fails
        assert np.count_nonzero(exact != scan) > 100


# ---------------------------------------------------------------- quantisation
def test_disparity_quantization_levels():
    scene = wall_scene(2.5, 40.0)
    st = apply_one("disparity_quantization", scene)
    z = st.depth[st.valid]
    setup = MatchSetup.for_preset(SMALL)
    k = (FB * (1 / z - 1 / setup.z0)) / setup.step
    assert np.allclose(k, np.round(k), atol=2e-3), "every depth is on a 1/8 px disparity level"
    levels = np.unique(np.round(k).astype(int))
    assert len(levels) > 20
    zl = 1 / (1 / setup.z0 + levels * setup.step / FB)
    gaps = -np.diff(zl)
    mid = (zl[1:] + zl[:-1]) / 2
    np.testing.assert_allclose(gaps, mid ** 2 * 0.125 / FB, rtol=0.02)   # dz = z^2 / (8 f b)
    # depth error bounded by half a step
    err = np.abs(st.depth - st.ideal.depth)[st.valid]
    assert np.all(err <= 0.5 * st.ideal.depth[st.valid] ** 2 * 0.125 / FB * 1.01 + 1e-5)


def test_physical_pipeline_quantises_to_eighth_pixel(box_scene):
    res = run(None, box_scene, seed=1)
    d = res.disparity[res.valid]
    assert np.allclose(d * 8, np.round(d * 8), atol=1e-4)
    q = run(None, box_scene, seed=1)
    st_d = apply_one("disparity_quantization", box_scene, prepare=lambda s: (setattr(s, "depth", res.depth.copy()),
                                                                             setattr(s, "valid", res.valid.copy())))
    np.testing.assert_allclose(st_d.depth, q.depth, atol=2e-6)  # idempotent after block matching


# ---------------------------------------------------------------- dropouts
def test_incidence_dropout_grows_with_tilt():
    fr = [run(["incidence_dropout"], wall_scene(1.5, a)).valid_fraction for a in (0, 60, 75, 80, 85)]
    assert fr[0] > 0.99 and fr[1] > 0.99
    assert fr[1] > fr[2] > fr[3] > fr[4]
    assert fr[3] < 0.6 and fr[4] < 0.3


def test_low_reflectance_drops_dark_surfaces():
    white = run(["low_reflectance"], wall_scene(3.0, albedo=0.8)).valid_fraction
    black = run(["low_reflectance"], wall_scene(3.0, albedo=0.03)).valid_fraction
    assert white > 0.99 and black < 0.7
    pw = run(None, wall_scene(3.0, albedo=0.8)).valid_fraction
    pb = run(None, wall_scene(3.0, albedo=0.03)).valid_fraction
    assert pb < pw - 0.1, "the physical pipeline loses dark surfaces through shot noise"


def test_specular_dropout():
    metal = wall_scene(1.5, 30, albedo=0.1, specular=0.9)
    matte = wall_scene(1.5, 30, albedo=0.1, specular=0.0)
    assert run(["specular_dropout"], metal).valid_fraction < 0.1
    assert run(["specular_dropout"], matte).valid_fraction == 1.0
    assert run(None, metal).valid_fraction < run(None, matte).valid_fraction - 0.05


def test_specular_highlight_saturates_physically():
    """A mirror-like wall facing the rig reflects the projector into the camera: saturation."""
    res = run(None, wall_scene(1.0, 0.0, albedo=0.2, specular=0.8))
    assert res.log["ir_capture"]["saturated_px"] > 100


@pytest.mark.parametrize("model", ["physical", "direct"])
def test_ambient_light_reduces_valid_pixels(model):
    eff = None if model == "physical" else ["ambient_light"]
    frac = []
    for lvl in (0.0, 0.05, 2.0):
        sim = SensorSimulator(SMALL, eff, wall_scene(2.0))
        sim.effect("ambient_light").params.level = lvl
        frac.append(sim.simulate(T, seed=0).valid_fraction)
    assert frac[0] >= frac[1] > frac[2]
    assert frac[2] < 0.5


# ---------------------------------------------------------------- noise, bias, fattening
def test_axial_noise_std_follows_model():
    st = apply_one("axial_noise", wall_scene(2.0), {"sigma0_m": 0.0, "sigma2_per_m": 0.0014})
    e = (st.depth - st.ideal.depth)[st.valid]
    assert abs(e.std() - 0.0014 * 4) < 0.05 * 0.0056
    assert abs(e.mean()) < 0.0056 * 4 / np.sqrt(e.size)


def test_depth_bias_disparity_offset():
    st = apply_one("depth_bias", wall_scene(2.0), {"disparity_offset_px": 0.5})
    z = st.ideal.depth[st.valid]
    np.testing.assert_allclose(st.depth[st.valid], 1 / (1 / z + 0.5 / FB), rtol=1e-5)


def test_edge_fattening_direct(box_scene):
    st = apply_one("edge_fattening", box_scene, {"radius_px": 3})
    box_ideal = (np.abs(st.ideal.depth - 1.4) < 0.01)[60]
    box_now = (np.abs(st.depth - 1.4) < 0.01)[60]
    assert box_now.sum() == box_ideal.sum() + 6      # 3 px on each side
    assert np.all(box_now[box_ideal])


def test_physical_edges_differ_from_ideal(box_scene):
    """The matching window changes depth edges (fattening / holes) within half a window."""
    res = run(None, box_scene)
    wrong = res.valid & (np.abs(res.depth - res.ideal_depth) > 0.1)
    cols = np.nonzero(wrong[40:80].any(0))[0]
    assert np.all((np.abs(cols - 38) <= 5) | (np.abs(cols - 121) <= 5))


# ---------------------------------------------------------------- geometry / optics
def test_range_limits():
    assert run(["range_limits"], wall_scene(9.0)).valid_fraction == 0.0
    assert run(["range_limits"], wall_scene(0.3)).valid_fraction == 0.0
    assert run(["range_limits"], wall_scene(3.0)).valid_fraction == 1.0


def test_hole_filling_small_holes_only():
    def punch(st):
        st.valid[50:52, 50:52] = False          # 4 px hole
        st.valid[20:40, 100:130] = False        # 600 px hole
        st.depth[~st.valid] = 0
    st = apply_one("hole_filling", wall_scene(2.0), {"max_hole_px": 30}, prepare=punch)
    assert st.valid[50:52, 50:52].all() and np.allclose(st.depth[50:52, 50:52], 2.0, atol=1e-4)
    assert not st.valid[25:35, 105:125].any()


def test_lens_distortion_direct_casts_distorted_rays():
    """Direct model: pixel (u, v) of the distorted image casts the pinhole ray of its undistorted
    (sub-pixel) position, so on a wall tilted 30 deg about y its depth is the analytic
    z = 2 / (1 - x tan 30) of that ray to 1e-4 m, where nearest-pixel resampling is off by up to
    half a pixel of the depth gradient; projecting the ray through OpenCV lands back on (u, v)."""
    import cv2
    from synth.sensor.effects.lens_distortion import undistort_pixels
    coeffs = (-0.25, 0.08, 0.001, -0.002, 0.0)
    st = apply_one("lens_distortion", wall_scene(2.0, tilt_deg=30.0), {"coefficients": coeffs})
    K = SMALL.intrinsics.K
    tan = np.tan(np.radians(30.0))
    worst_nearest = 0.0
    for (u, v) in [(10, 10), (150, 100), (80, 60), (30, 110), (3, 57), (121, 7)]:
        und = undistort_pixels(np.array([[[u, v]]], np.float64), K, coeffs)[0, 0]
        x = (und[0] - K[0, 2]) / K[0, 0]
        assert st.depth[v, u] == pytest.approx(2.0 / (1.0 - x * tan), abs=1e-4)
        assert st.valid[v, u] and st.view.hit[v, u]
        xn = (np.rint(und[0]) - K[0, 2]) / K[0, 0]           # what the nearest ideal pixel would give
        worst_nearest = max(worst_nearest, abs(2.0 / (1.0 - xn * tan) - 2.0 / (1.0 - x * tan)))
        ray = np.array([[x, (und[1] - K[1, 2]) / K[1, 1], 1.0]])
        back = cv2.projectPoints(ray, np.zeros(3), np.zeros(3), K, np.array(coeffs))[0][0, 0]
        assert np.allclose(back, (u, v), atol=1e-3)
    assert worst_nearest > 5e-4          # the test would catch nearest-pixel resampling
    zero = apply_one("lens_distortion", wall_scene(2.0), {"coefficients": (0, 0, 0, 0, 0)})
    assert zero.log["lens_distortion"]["active"] is False


def test_lens_distortion_without_renderer_resamples_nearest():
    """Without a scene renderer the direct model falls back to resampling the ideal depth at the
    nearest undistorted pixel (OpenCV's model)."""
    from synth.sensor.effects.lens_distortion import undistort_pixels
    coeffs = (-0.25, 0.08, 0.001, -0.002, 0.0)

    def ramp(st):
        st.renderer = None
        st.depth = (1.0 + np.arange(160, dtype=np.float32)[None, :] * 0.01
                    + np.arange(120, dtype=np.float32)[:, None] * 1e-4)
    st = apply_one("lens_distortion", wall_scene(2.0), {"coefficients": coeffs}, prepare=ramp)
    K = SMALL.intrinsics.K
    for (u, v) in [(10, 10), (150, 100), (80, 60), (30, 110)]:
        und = undistort_pixels(np.array([[[u, v]]], np.float64), K, coeffs)[0, 0]
        if 0 <= und[0] < 159.5 and 0 <= und[1] < 119.5:
            uu, vv = int(np.rint(und[0])), int(np.rint(und[1]))
            assert st.depth[v, u] == pytest.approx(1.0 + uu * 0.01 + vv * 1e-4, abs=1e-5)


def test_rolling_shutter_shears_moving_edges(box_scene):
    prev = T.copy()
    prev[0, 3] = -0.3                    # camera moves +x by 0.3 m per frame period
    still = run(["rolling_shutter"], box_scene)
    static = run(["rolling_shutter"], box_scene, prev_pose=T)
    np.testing.assert_array_equal(static.depth, still.depth)   # no motion -> no effect
    moving = run(["rolling_shutter"], box_scene, prev_pose=prev, motion=NO_MOTION_LIMIT)

    def left_edge(res, row):
        return int(np.nonzero(np.abs(res.depth[row] - 1.4) < 0.01)[0].min())
    r1, r2 = 45, 75
    s = (np.array([r1, r2]) / 119 - 0.5) * 0.03 * 30          # row times in frame periods
    x_cam = 0.3 * s                                            # camera x at those rows
    expected = 580 * (x_cam[0] - x_cam[1]) / 1.4               # the edge moves opposite to the camera
    got = left_edge(moving, r2) - left_edge(moving, r1)
    assert expected < -20 and got == pytest.approx(expected, abs=1.5)
    assert left_edge(still, r2) == left_edge(still, r1)


def test_motion_blur_pattern_moves_with_the_rig():
    """Translating parallel to a flat wall: the dots move with the rig, the IR image is as
    sharp as when static (same draws); an edge sweeping by is blurred."""
    prev = T.copy()
    prev[0, 3] = -0.2
    wall = wall_scene(2.0)
    a = run(None, wall, seed=4)
    b = run(None, wall, seed=4, prev_pose=prev, motion=NO_MOTION_LIMIT)
    assert b.log["motion_blur"]["active"] and not b.warnings
    assert np.abs(a.ir.astype(int) - b.ir.astype(int)).max() <= 1
    box = box_before_wall_scene(2.0, 1.5, 0.2)
    c = run(["motion_blur"], box, prev_pose=prev, motion=NO_MOTION_LIMIT)
    d = run(["motion_blur"], box)
    assert c.valid.sum() < d.valid.sum() and d.valid.all()


def test_implausible_motion_is_a_cut(box_scene):
    """A previous pose implying more than the motion limits is treated as a cut: the frame is
    the static one (same seed), the motion effects are inactive and a warning says why."""
    effects = ["rolling_shutter", "motion_blur"]
    static = run(effects, box_scene, seed=2)
    jump = T.copy()
    jump[0, 3] = -1.0                                   # 1 m in one frame period = 30 m/s
    cut = run(effects, box_scene, seed=2, prev_pose=jump)
    np.testing.assert_array_equal(cut.depth, static.depth)
    assert cut.log["rolling_shutter"]["active"] is False and cut.log["motion_blur"]["active"] is False
    assert len(cut.warnings) == 1 and "max_speed_m_s" in cut.warnings[0] and "30 m/s" in cut.warnings[0]
    assert cut.log["motion"]["cut"] is True
    turn = T.copy()                                     # 10 deg in one frame period = 5.2 rad/s
    a = np.radians(10.0)
    turn[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    cut = run(effects, box_scene, seed=2, prev_pose=turn)
    assert "max_angular_speed_rad_s" in cut.warnings[0]
    np.testing.assert_array_equal(cut.depth, static.depth)
    # a plausible hand-held motion (3 cm per frame = 0.9 m/s) keeps the motion effects
    walk = T.copy()
    walk[0, 3] = -0.03
    ok = run(effects, box_scene, seed=2, prev_pose=walk)
    assert not ok.warnings and ok.log["rolling_shutter"]["active"] is True
    assert not np.array_equal(ok.depth, static.depth)
    # the limits are part of the model: raising them lets the same jump through
    loose = run(effects, box_scene, seed=2, prev_pose=jump, motion=MotionLimits(50.0, 10.0))
    assert not loose.warnings and loose.log["rolling_shutter"]["active"] is True


def test_motion_limits_round_trip_and_bad_values():
    from data_tools.errors import ConfigError
    cfg = SensorConfig.build("kinect_v1", "direct", motion=MotionLimits(1.5, 2.0))
    back = SensorConfig.from_json(cfg.to_json())
    assert back.motion == MotionLimits(1.5, 2.0)
    assert back.with_params({"axial_noise.sigma2_per_m": 0.002}).motion == MotionLimits(1.5, 2.0)
    old = cfg.to_json()
    del old["motion"]                                   # configs saved before the limits existed
    assert SensorConfig.from_json(old).motion == MotionLimits()
    with pytest.raises(ConfigError, match="max_speed_m_s"):
        MotionLimits(-1.0, 2.0)
    with pytest.raises(ConfigError, match="unknown key"):
        SensorConfig.from_json({**cfg.to_json(), "motion": {"max_speed": 2}})


# ---------------------------------------------------------------- capture physics
def test_radiance_falls_with_distance_squared():
    def mean_rad(z):
        st = SensorSimulator(SMALL, ["pattern_projection"], wall_scene(z)).make_state(T)[0]
        e = st.model["pattern_projection"]
        e.apply(st, None)
        return st.radiance.mean()
    assert mean_rad(1.0) / mean_rad(2.0) == pytest.approx(4.0, rel=0.03)


def test_ir_capture_saturates_near_and_dims_far():
    near = run(None, wall_scene(0.5))
    far = run(None, wall_scene(2.0))
    assert near.log["ir_capture"]["saturated_px"] > 0 and far.log["ir_capture"]["saturated_px"] == 0
    assert near.ir.max() == 1023


# ---------------------------------------------------------------- ToF
TOF = get_preset("kinect_v2").cropped(128, 106)


def test_multipath_biases_concave_corners_only():
    flat = apply_one("multipath", wall_scene(2.0), preset=TOF)
    assert np.abs(flat.depth - flat.ideal.depth)[flat.valid].max() < 1e-6
    corner = apply_one("multipath", corner_scene(2.0), preset=TOF)
    err = (corner.depth - corner.ideal.depth)[corner.valid]
    assert err.mean() > 0.002, "indirect light lengthens the measured path in a concave corner"
    assert err.min() > -1e-3


def test_wiggling_formula():
    st = apply_one("wiggling", wall_scene(2.0), {"amplitude_m": 0.004, "period_m": 0.5}, preset=TOF)
    c = st.ray_dirs_cam[..., 2]
    r = st.ideal.depth / c
    np.testing.assert_allclose(st.depth, st.ideal.depth + 0.004 * np.sin(2 * np.pi * r / 0.5) * c, atol=1e-6)


def test_flying_pixels_lie_between_surfaces(box_scene):
    st = apply_one("flying_pixels", box_scene, {"probability": 1.0}, preset=TOF)
    changed = np.abs(st.depth - st.ideal.depth) > 1e-6
    assert changed.sum() > 50
    z = st.depth[changed]
    assert np.all((z > 1.4 - 1e-4) & (z < 2.0 + 1e-4))
    import cv2
    k = np.ones((3, 3), np.uint8)
    span = cv2.dilate(st.ideal.depth, k) - cv2.erode(st.ideal.depth, k)
    assert np.all(span[changed] > 0.1), "only pixels on a depth edge fly"


def test_scanline_shadow_mirrors_for_a_projector_on_the_left():
    """A pixel without a surface blocks nothing, on either side (it used to become -inf after
    the mirror's sign flip and shadow every pixel before it with the projector at -x)."""
    from synth.sensor.effects.pattern_projection import scanline_shadow
    up = np.array([[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]], np.float32)   # a flat row: nothing occludes
    valid = np.array([[False, True, True, True, True, True]])
    for side in (1.0, -1.0):
        assert not scanline_shadow(up, valid, side).any()
    # an occluder: with the projector on the left, a pixel left of a point that maps to a
    # projector column >= its own is blocked (mirror of the right-hand case)
    up2 = np.array([[0.0, 3.0, 1.0, 2.0]], np.float32)
    ok = np.ones((1, 4), bool)
    assert scanline_shadow(up2, ok, 1.0).tolist() == [[False, True, False, False]]
    assert scanline_shadow(-up2[:, ::-1], ok, -1.0).tolist() == [[False, False, True, False]]


def test_warped_sub_exposure_view_is_exact_on_a_tilted_wall():
    """``motion_blur``'s sub-frame reuse: the view warped to other row poses equals the rendered
    one on a planar surface (every pixel's ray meets the tangent plane of its source pixel)."""
    from synth.render import IdealRenderer
    from synth.sensor.effects.motion_blur import warp_view
    from synth.sensor.state import cast_view
    pre = get_preset("kinect_v1").cropped(160, 120)
    intr = pre.intrinsics
    r = IdealRenderer(wall_scene(1.8, tilt_deg=35.0))
    dirs = r.ray_dirs_cam(intr)
    H = intr.height
    rows0 = np.broadcast_to(np.eye(4), (H, 4, 4)).copy()
    rows1 = rows0.copy()
    rows1[:, 0, 3] = np.linspace(0.01, 0.03, H)             # a rolling-shutter-like sideways motion
    rows1[:, 1, 3] = 0.005
    v0 = cast_view(r, dirs, rows0)
    exact = cast_view(r, dirs, rows1)
    warped, src = warp_view(v0, rows1, intr, ray_dirs_cam=dirs)
    both = exact.hit & warped.hit
    assert both.mean() > 0.97 and (src[warped.hit] >= 0).all()
    np.testing.assert_allclose(warped.points_cam[both], exact.points_cam[both], atol=2e-5)
    np.testing.assert_allclose(warped.normals_cam[both], exact.normals_cam[both], atol=1e-5)
    lean, _ = warp_view(v0, rows1, intr, full=False, ray_dirs_cam=dirs)
    np.testing.assert_array_equal(lean.points_cam[..., 2], warped.points_cam[..., 2])


def test_motion_blur_warp_agrees_with_render_far_below_the_noise():
    """The default ``warp`` and the exact ``render`` sub-exposures on a moving camera in the room:
    their depth differs far less than two noise seeds of the same method do."""
    from synth.scenes import build_scene
    from synth.sequence import SequenceConfig, make_sequence_trajectory
    scene = build_scene("room", seed=0)
    P = make_sequence_trajectory(SequenceConfig(frames=20).with_resolution(320, 240), scene).poses
    pre = get_preset("kinect_v1").cropped(320, 240)
    out = {}
    for m in ("render", "warp"):
        cfg = SensorConfig.build(pre, ["rolling_shutter", "pattern_projection", "ambient_light",
                                       {"name": "motion_blur", "params": {"method": m}}, "ir_capture",
                                       "block_matching"])
        sim = SensorSimulator(cfg, None, scene)
        out[m] = [sim.simulate(P[i + 1], seed=i, prev_pose=P[i]) for i in (8, 12)]
        if m == "warp":
            other = [sim.simulate(P[i + 1], seed=i + 100, prev_pose=P[i]) for i in (8, 12)]
    for a, b, c in zip(out["render"], out["warp"], other):
        assert b.log["motion_blur"]["method"] == "warp" and a.log["motion_blur"]["method"] == "render"
        ab = a.valid & b.valid
        bc = b.valid & c.valid
        d_method = np.mean(np.abs(a.depth[ab] - b.depth[ab]) > 0.01)
        d_seed = np.mean(np.abs(b.depth[bc] - c.depth[bc]) > 0.01)
        assert (a.valid != b.valid).mean() < 0.5 * (b.valid != c.valid).mean()
        assert d_method < 0.2 * d_seed, (d_method, d_seed)


def test_warped_pattern_at_the_frame_pose_is_the_frame_radiance():
    """``warp_pattern``'s sub-exposure at the frame's own row poses: the identity warp, so the
    published shading times the re-sampled pattern must give back the frame's radiance (on a
    box before a wall, matte and shiny, and a tilted wall: fall-off, incidence, Phong lobe,
    projector shadow), and the shading must be positive on every unshadowed pixel, whatever the
    pattern there (the dots of a sub-exposure move)."""
    from data_tools.scene_spec import Material, SceneSpec
    from synth.sensor.effects.motion_blur import add_warped_pattern
    from synth.sensor.effects.pattern_projection import blurred_pattern, compute_radiance
    base = box_before_wall_scene(2.0, 1.5, 0.2)
    shiny = SceneSpec(base.meshes, {k: Material(m.albedo, 0.3) for k, m in base.materials.items()})
    for scene in (base, shiny, wall_scene(1.8, tilt_deg=35.0)):
        sim = SensorSimulator(SMALL, None, scene)
        st = sim.make_state(T)[0]
        pp = sim.effect("pattern_projection")
        pb = blurred_pattern(st.pattern, pp.params.dot_sigma_px, {})
        out = {"shading": None}
        E, _ = compute_radiance(st.view, (0, 0, 0), st.preset, pb, pp.params, sim.renderer, st.ray_dirs_cam, out=out)
        G = out["shading"]
        acc = np.zeros(st.shape, np.float32)
        add_warped_pattern(acc, st.view, st.view.row_c2w, st.intr, st.ray_dirs_cam, st.preset, pb, G)
        np.testing.assert_allclose(acc, E, rtol=1e-4, atol=1e-6 * E.max())
        shadow = out["shadow"] if out["shadow"] is not None else np.zeros(st.shape, bool)
        assert (G[st.view.hit & ~shadow] > 0).all() and (G[shadow] == 0).all()   # the dots play no part


def test_motion_blur_warp_pattern_agrees_with_warp_far_below_the_noise():
    """The default ``warp_pattern`` (shading frozen, dots re-projected) against ``warp`` (the
    radiance of the warped view computed again) on a moving camera in the room: integrated
    radiance within 1e-3, and depth differences far below those of two noise seeds."""
    from synth.scenes import build_scene
    from synth.sequence import SequenceConfig, make_sequence_trajectory
    scene = build_scene("room", seed=0)
    P = make_sequence_trajectory(SequenceConfig(frames=20).with_resolution(320, 240), scene).poses
    pre = get_preset("kinect_v1").cropped(320, 240)
    res, rad = {}, {}
    for m in ("warp", "warp_pattern"):
        cfg = SensorConfig.build(pre, ["rolling_shutter", "pattern_projection", "ambient_light",
                                       {"name": "motion_blur", "params": {"method": m}}, "ir_capture",
                                       "block_matching"])
        sim = SensorSimulator(cfg, None, scene)
        res[m] = [sim.simulate(P[i + 1], seed=i, prev_pose=P[i]) for i in (8, 12)]
        rad[m] = []
        for i in (8, 12):
            st = sim.make_state(P[i + 1], P[i])[0]
            for e in st.model.values():
                if e.name == "ir_capture":
                    break
                e.apply(st, e.sample(e.rng(i), st))
            assert st.log["motion_blur"]["method"] == m
            rad[m].append(st.radiance)
        if m == "warp_pattern":
            other = [sim.simulate(P[i + 1], seed=i + 100, prev_pose=P[i]) for i in (8, 12)]
    for a, b in zip(rad["warp"], rad["warp_pattern"]):
        assert np.abs(a - b).sum() < 1e-3 * np.abs(a).sum()
    for a, b, c in zip(res["warp"], res["warp_pattern"], other):
        ab, bc = a.valid & b.valid, b.valid & c.valid
        d_method = np.mean(np.abs(a.depth[ab] - b.depth[ab]) > 0.01)
        d_seed = np.mean(np.abs(b.depth[bc] - c.depth[bc]) > 0.01)
        assert (a.valid != b.valid).mean() < 0.1 * (b.valid != c.valid).mean()
        assert d_method < 0.05 * d_seed, (d_method, d_seed)
