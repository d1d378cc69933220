"""Edge fattening's disparity threshold and gate, the lens's border holes and noise-aware edges
(issue #43 item 6: the misses of the independent generators)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from data_tools.camera import Intrinsics
from tests import hidden_effects as he


def test_stump_splits_in_the_middle_of_the_gap():
    from synth.sensor.effects.edge_fattening import _stump
    j = np.array([0.5, 1.0, 1.5, 2.5, 3.0])
    assert _stump(j, np.array([0, 0, 0, 1, 1], bool)) == pytest.approx(np.sqrt(1.5 * 2.5))
    assert _stump(j, np.ones(5, bool)) is None and _stump(j, np.zeros(5, bool)) is None


def test_disparity_threshold_wins_where_no_relative_one_separates():
    # foreground / background pairs, fb = 10 px m: fattened iff the disparity jump exceeds 2 px.
    # The relative jumps of the fattened (20, 23, 14 %) and the others (33, 37.5, 9 %) interleave:
    # no relative threshold separates them, a disparity one does (between 1.82 and 2.31 px)
    from synth.sensor.effects.edge_fattening import _jump_threshold
    pairs = [(0.8, 1.0), (2.0, 3.0), (1.0, 1.3), (2.5, 4.0), (0.5, 0.55), (0.6, 0.7)]
    z = np.ones((60, 20 * len(pairs)), np.float32)
    m = z.copy()
    for k, (zf, zb) in enumerate(pairs):
        c0 = 20 * k
        z[:, c0:c0 + 20] = m[:, c0:c0 + 20] = zb
        z[:, c0 + 8:c0 + 12] = m[:, c0 + 8:c0 + 12] = zf
        if 10.0 / zf - 10.0 / zb > 2.0:
            m[:, c0 + 7] = m[:, c0 + 12] = zf
    ok = np.ones(z.shape, bool)
    for k in range(len(pairs)):                  # not the seams between two backgrounds
        ok[:, 20 * k:20 * k + 3] = ok[:, 20 * k + 17:20 * k + 20] = False
    form, t = _jump_threshold([(m, z, ok)], 0.06, fb=10.0)
    assert form == "px" and 1.82 < t <= 2.31, (form, t)
    assert _jump_threshold([(m, z, ok)], 0.06) is None            # the relative form alone finds none


def _fake_measured(depths, hit):
    """A measured-sequence stand-in for the closed-form starts: measured depths, an ideal view that
    hits wherever ``hit``."""
    r = SimpleNamespace(hit=hit, depth=np.where(hit, 2.0, 0.0).astype(np.float32))
    return SimpleNamespace(measured_depth=lambda k: depths[k], render=lambda k: r, mask=lambda k: None,
                           __len__=lambda: len(depths))


def test_border_holes_give_the_barrel_k1_that_cuts_them():
    from synth.sensor.effects.lens_distortion import LensDistortion, distortion_maps
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    mx, my = distortion_maps(intr, (-0.2, 0.0, 0.0, 0.0, 0.0))
    cut = (mx < -0.5) | (mx > 159.5) | (my < -0.5) | (my > 119.5)
    assert 0.005 < cut.mean() < 0.3                          # the corners
    hit = np.ones(cut.shape, bool)
    depths = [np.where(cut, 0.0, 2.0).astype(np.float32) for _ in range(3)]
    depths[1][40:50, 60:70] = 0.0                            # a scene hole in one frame only: ignored
    ms = _fake_measured(depths, hit)
    k1 = LensDistortion._border_holes(ms, range(3), intr, [0.0] * 5)
    assert k1 == pytest.approx(-0.2, abs=0.021)
    full = _fake_measured([np.full(cut.shape, 2.0, np.float32)] * 3, hit)
    assert LensDistortion._border_holes(full, range(3), intr, [0.0] * 5) is None    # a lens that sees its corners


@pytest.mark.parametrize("seed,k1,outside", [(25, 0.1969, None), (26, -0.1857, "hole")])
def test_lens_start_on_the_independent_generator_at_160_px(tmp_path, seed, k1, outside):
    """The hidden generator's lens at 160x120 (2 % depth noise at 3 m between neighbours): the
    chamfer start's edges stay above the noise, and a barrel lens resampled from a pinhole image
    (corners without a source pixel) is started with outside = hole."""
    from synth.lab import MeasuredSequence
    from synth.sensor.effects.lens_distortion import LensDistortion
    t = he.generate(tmp_path / "seq", "lens_distortion", seed=seed, n_frames=4, width=160, height=120)
    assert t["k1"] == pytest.approx(k1, abs=1e-4)
    ms = MeasuredSequence.load(tmp_path / "seq")
    st = LensDistortion.fit_start(ms, ms.default_config(["axial_noise", "range_limits", "lens_distortion"]), None)
    assert st["lens_distortion.k1"] == pytest.approx(k1, abs=0.02), st
    assert st.get("lens_distortion.outside") == outside


def test_edge_fattening_of_the_independent_generator_fattens_slopes_too(tmp_path):
    """The hidden generator fattens wherever its disk holds a surface nearer by 4 %, steep floor
    and walls included: the start says gate = none, and the model with it reproduces the
    generator's fattened pixels (the tangent-plane gate left half of them out)."""
    from synth.lab import MeasuredSequence
    from synth.lab.params import set_params
    from synth.sensor.effects.edge_fattening import EdgeFattening
    t = he.generate(tmp_path / "seq", "edge_fattening", seed=25, n_frames=4, width=160, height=120)
    ms = MeasuredSequence.load(tmp_path / "seq")
    cfg = ms.default_config(["edge_fattening"])
    st = EdgeFattening.fit_start(ms, cfg, None)
    assert st["edge_fattening.gate"] == "none" and st["edge_fattening.radius_px"] == t["radius_px"], st
    counts = {}
    for gate in ("edges", "none"):
        c = set_params(cfg, {"edge_fattening.radius_px": t["radius_px"], "edge_fattening.min_jump_rel": 0.04})
        c = c.with_params({"edge_fattening.window": "disk", "edge_fattening.gate": gate})
        sim = ms.simulator(c)
        res = sim.simulate(ms.poses[0], seed=0, render=ms.render(0))
        counts[gate] = res.log["edge_fattening"]["fattened_px"]
    r = ms.render(0)
    far = np.where(r.hit, r.depth, np.inf)
    from scipy import ndimage
    zmin = ndimage.minimum_filter(far, footprint=he._disk(t["radius_px"]), mode="nearest")
    truth = int(np.count_nonzero(np.isfinite(zmin) & (zmin < far * 0.96)))
    assert counts["none"] == pytest.approx(truth, rel=0.02) and counts["edges"] < 0.8 * truth, (counts, truth)


def _floor_with_a_box():
    """A state stand-in: a floor plane at 1.5-2.5 m (50 deg tilt, exact tangent planes) seen by a
    160x120 camera (f b = 10.9 px m), a box 30 % nearer in rows 40-60, columns 60-100; no noise."""
    from data_tools.geometry import pixel_rays
    intr = Intrinsics(160, 120, 145.0, 145.0, 79.5, 59.5)
    rays = pixel_rays(intr, unit=False).astype(np.float32)
    n = np.array([0.0, -np.cos(np.radians(50)), -np.sin(np.radians(50))], np.float32)
    z = (-1.4 / (rays @ n)).astype(np.float32)
    normals = np.broadcast_to(n, rays.shape).copy()
    box = np.zeros(z.shape, bool)
    box[40:60, 60:100] = True
    z[box] *= np.float32(0.7)
    normals[box] = (0.0, 0.0, -1.0)
    view = SimpleNamespace(depth=z, hit=np.ones(z.shape, bool), normals_cam=normals)
    return SimpleNamespace(depth=z.copy(), valid=np.ones(z.shape, bool), view=view, ray_dirs_cam=rays,
                           preset=SimpleNamespace(fb=145.0 * 0.075, block_size=9), log={}), box


def test_disparity_gate_leaves_a_steep_floor_alone():
    """With the jump threshold in disparity only (min_jump_rel 0, min_jump_px 0.05: a 4-row window on
    this floor spans ~0.09 px), fattening happens beside the box's edges (the gate: the window of an
    edge pixel, and a window around that) and nowhere else: the
    edges gate tests the same disparity jump against each pixel's tangent plane (``gate_rel``),
    where a test at 0 took every pixel of the floor for an edge and fattened all of it."""
    from synth.sensor.effects.edge_fattening import EdgeFattening
    state, box = _floor_with_a_box()
    before = state.depth.copy()
    EdgeFattening({"radius_px": 4, "min_jump_rel": 0.0, "min_jump_px": 0.05, "gate": "edges"}).apply(state, None)
    changed = state.depth != before
    near_box = np.zeros_like(box)
    near_box[32:68, 52:108] = True                   # within two windows of the box (the gate's reach)
    assert changed[near_box & ~box].sum() > 100      # the box spreads over the floor beside it
    assert changed[~near_box].sum() == 0             # the floor's own slope is not an edge
