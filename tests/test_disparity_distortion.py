"""The learned per-pixel disparity distortion (``disparity_distortion``, issue #17 part 3).

Hand-computed effect values; the closed-form map estimate on exact samples; the map file travels
with the model (saved beside it, loaded from anywhere); and the acceptance on planar captures made
by an independent generator (``tests/hidden_effects.generate_plane_capture``: Herrera et al.'s
raw-code model, no ``synth.sensor`` code): diagnose ranks the effect first, the fitted map
correlates > 0.9 with the true one, and on frames held out from the fit the gap falls by >= 50 %
and the simulated plane noise moves closer to the measured one at every distance.
"""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest

from tests import hidden_effects as he
from app.cli import main
from data_tools.errors import ConfigError, FormatError
from synth.sensor import SensorConfig
from synth.sensor.effects.disparity_distortion import estimate_map, load_map, save_map, upsample

ALPHA = (2.22, 0.003)                   # exp(a0 - a1 k) = 1 at 1 m
FB = he.FOCAL * he.BASELINE              # 21.75 px m
CODES_PER_PX = 1.0 / (FB * he.HERRERA_C1)


def test_effect_values_by_hand(tmp_path):
    """A constant map of 0.5 px with no decay: z' = fb / (fb / z + 0.5); with decay 0.1 / px the
    error at 2 m is 0.5 exp(-0.1 (fb/1 - fb/2))."""
    from synth.sensor.effects.disparity_distortion import DisparityDistortion
    from synth.sensor.presets import get_preset
    path = save_map(np.full((3, 4), 0.5, np.float32), tmp_path)
    pre = get_preset("kinect_v1").cropped(32, 24)
    fb = pre.fb

    class S:   # the slice of SensorState the effect reads and writes
        preset, shape = pre, (24, 32)
        depth = np.full((24, 32), 2.0, np.float32)
        valid = np.ones((24, 32), bool)

    s = S()
    s.depth[0, 0], s.valid[0, 0] = 0.0, False
    DisparityDistortion({"beta_map": str(path)}).apply(s, None)
    assert s.depth[0, 0] == 0 and not s.valid[0, 0]                 # holes stay holes
    np.testing.assert_allclose(s.depth[5, 5], fb / (fb / 2.0 + 0.5), rtol=1e-6)
    s.depth = np.full((24, 32), 2.0, np.float32)
    DisparityDistortion({"beta_map": str(path), "decay_per_px": 0.1}).apply(s, None)
    e = 0.5 * np.exp(-0.1 * (fb / 1.0 - fb / 2.0))
    np.testing.assert_allclose(s.depth[5, 5], fb / (fb / 2.0 + e), rtol=1e-6)


def test_map_estimate_is_exact_on_exact_samples():
    """Noise-free residuals of a constant map with decay 0.05 / px: the estimate returns the map
    and the decay (on its grid) exactly; a bowl is recovered with correlation > 0.99."""
    H, W = 96, 128
    vv, uu = np.mgrid[0:H, 0:W]
    for true in (np.full((H, W), 0.3), 0.4 * (((uu - 63.5) / 64) ** 2 + ((vv - 47.5) / 48) ** 2)):
        samples = []
        for z in (0.8, 1.2, 1.9, 2.7):
            d = np.full(vv.shape, FB / z)
            r = true * np.exp(-0.05 * (FB - d))
            samples.append((uu.ravel(), vv.ravel(), r.ravel(), d.ravel()))
        grid, decay, info = estimate_map(samples, FB, (H, W), 1.0)
        assert decay == pytest.approx(0.05) and info["cells_observed"] == info["cells"] == 192
        full = upsample(grid, (H, W))
        if np.ptp(true) == 0:
            np.testing.assert_allclose(full, true, atol=0.3 * 0.02)      # only the ridge shrinks it (< 2 %)
        else:
            assert np.corrcoef(full.ravel(), true.ravel())[0, 1] > 0.99


def test_unobserved_cells_are_filled_smoothly():
    """Samples only in the left half: the right half is filled from its neighbours (no zeros, no
    jump at the border)."""
    H, W = 32, 64
    vv, uu = np.mgrid[0:H, 0:W // 2]
    r = np.full(vv.shape, 0.2)
    grid, _, info = estimate_map([(uu.ravel(), vv.ravel(), r.ravel(), np.full(r.size, FB))], FB, (H, W), 1.0,
                                 decays=[0.0])
    assert info["cells_observed"] == info["cells"] // 2
    np.testing.assert_allclose(grid, 0.2, atol=0.01)


def test_map_file_travels_with_the_model(tmp_path, monkeypatch):
    """save() copies the map beside the JSON and references it by name; the folder can move and
    be loaded from another working directory; a missing or bad map is one line naming it."""
    grid = np.linspace(-0.2, 0.2, 12, dtype=np.float32).reshape(3, 4)
    src = save_map(grid, tmp_path / "scratch")
    cfg = SensorConfig.build("kinect_v1", ["axial_noise", {"name": "disparity_distortion",
                                                           "params": {"beta_map": str(src)}}])
    path = cfg.save(tmp_path / "a" / "model.json")
    ref = json.loads(path.read_text())["effects"][1]["params"]["beta_map"]
    assert ref == src.name and (path.parent / ref).is_file()
    (tmp_path / "a").rename(tmp_path / "b")
    monkeypatch.chdir(tmp_path / "scratch")
    back = SensorConfig.load(tmp_path / "b" / "model.json")
    np.testing.assert_array_equal(load_map(back.effect("disparity_distortion").params.beta_map), grid)
    assert back.save(tmp_path / "b" / "model.json") and len(list((tmp_path / "b").glob("*.npy"))) == 1
    (tmp_path / "b" / ref).unlink()
    with pytest.raises(FormatError) as e:
        SensorConfig.load(tmp_path / "b" / "model.json")
    assert ref in str(e.value) and "not found" in str(e.value) and "\n" not in str(e.value)
    np.save(tmp_path / "b" / ref, np.zeros((2, 2, 2)))
    with pytest.raises(FormatError, match="expected a 2-D float map"):
        SensorConfig.load(tmp_path / "b" / "model.json")
    bad = tmp_path / "nan.npy"
    np.save(bad, np.array([[np.nan, 0.0]]))
    with pytest.raises(ConfigError, match="NaN"):
        SensorConfig.build("kinect_v1", [{"name": "disparity_distortion", "params": {"beta_map": str(bad)}}])


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """A fit capture (8 frames, 0.7-2.6 m) and a held-out one (6 frames at other distances and
    tilts), both with the same Herrera-like bowl + stripes."""
    root = tmp_path_factory.mktemp("dd")
    beta = he.herrera_beta()
    he.generate_plane_capture(root / "fit", np.linspace(0.7, 2.6, 8), beta, ALPHA, seed=1)
    he.generate_plane_capture(root / "held_out", np.linspace(0.8, 2.5, 6), beta, ALPHA, seed=2)
    return root, beta


def test_diagnose_finds_the_pattern_and_the_fit_holds_on_held_out_frames(captures):
    from synth.lab.calibration import plane_noise_table
    from synth.lab.diagnose import diagnose
    from synth.lab.fit import Objective
    from synth.lab.compare import CompareConfig
    from synth.lab.measured import MeasuredSequence
    root, beta = captures
    ms = MeasuredSequence.load(root / "fit")
    base = ms.default_config(["axial_noise", "range_limits"])
    diag = diagnose(ms, base)
    ranking = [c.effect for c in diag.ranking]
    assert ranking[0] == "disparity_distortion", [(c.effect, round(c.gain, 3)) for c in diag.ranking]
    assert diag.ranking[0].gain > 0.5
    assert "depth_bias" in ranking                         # the parametric alternative is reported too
    fitted = diag.ranking[0].config
    e = fitted.effect("disparity_distortion")
    true_px = he.herrera_beta_px_at(beta, 1.0, ALPHA, FB)
    est = e.params.strength * e.map_for(true_px.shape)
    assert np.corrcoef(est.ravel(), true_px.ravel())[0, 1] > 0.9
    assert e.params.decay_per_px == pytest.approx(ALPHA[1] * abs(CODES_PER_PX), rel=0.25)

    held = MeasuredSequence.load(root / "held_out")
    without = dataclasses.replace(fitted, effects=[x for x in fitted.effects if x.name != "disparity_distortion"])
    ob = Objective(held, range(len(held)), CompareConfig(), 0)
    g0, g1 = ob(without), ob(fitted)
    assert g1 <= 0.5 * g0, (g0, g1)
    # per held-out frame, the simulated error correlates with the true distortion at that depth
    sims_with = held.simulate(fitted)
    sims_without = held.simulate(without)
    for k, (sw, so) in enumerate(zip(sims_with, sims_without)):
        z = held.render(k).depth
        ok = (z > 0) & (sw > 0) & (so > 0)
        d_err = FB / sw[ok] - FB / so[ok]                 # what the effect adds, px (same noise draw)
        zc = float(np.median(z[ok]))
        true_k = he.herrera_beta_px_at(beta, zc, ALPHA, FB)[ok]
        assert np.corrcoef(d_err, true_k)[0, 1] > 0.9
    # plane noise (spread about the reference) closer to the measured one at every distance
    t_with = plane_noise_table(held.observations(sims_with))
    t_without = plane_noise_table(held.observations(sims_without))
    for a, b in zip(t_with, t_without):
        assert abs(a["simulated_mm"] - a["measured_mm"]) < abs(b["simulated_mm"] - b["measured_mm"]), (a, b)


def test_cli_fit_on_half_compare_on_the_other_half(captures, tmp_path, monkeypatch, capsys):
    root, _ = captures
    cap = root / "fit"
    model = tmp_path / "m" / "model.json"
    assert main(["sensor", "fit", str(cap), "--effects", "axial_noise,range_limits,disparity_distortion",
                 "--frame-slice", "0::2", "--out", str(model), "--no-progress"]) == 0
    maps = list(model.parent.glob("*.npy"))
    assert len(maps) == 1
    assert json.loads(model.read_text())["effects"][-1]["params"]["beta_map"] == maps[0].name
    monkeypatch.chdir(tmp_path)
    os.makedirs("elsewhere")
    monkeypatch.chdir("elsewhere")
    lab = tmp_path / "lab"
    assert main(["sensor", "compare", str(cap), "--model", str(model), "--frame-slice", "1::2", "--out", str(lab),
                 "--no-progress"]) == 0
    base = tmp_path / "lab_base"
    assert main(["sensor", "compare", str(cap), "--effects", "axial_noise,range_limits", "--frame-slice", "1::2",
                 "--out", str(base), "--no-progress"]) == 0
    g_fit = json.loads((lab / "metrics.json").read_text())["gap"]
    g_base = json.loads((base / "metrics.json").read_text())["gap"]
    assert g_fit < 0.5 * g_base
    cfg = json.loads((lab / "lab_config.json").read_text())
    assert cfg["frame_slice"] == "1::2" and cfg["measured"]["frames"] == 4
    assert len(list(lab.glob("*.npy"))) == 1                                  # the effective model is complete
    capsys.readouterr()
    assert main(["sensor", "compare", str(cap), "--effects", "axial_noise", "--frame-slice", "0:x", "--out",
                 str(tmp_path / "bad")]) == 1
    err = capsys.readouterr().err.strip()
    assert "--frame-slice" in err and "\n" not in err
    assert main(["sensor", "compare", str(cap), "--effects", "axial_noise", "--frame-slice", "50:60", "--out",
                 str(tmp_path / "bad")]) == 1
    assert "selects none" in capsys.readouterr().err
