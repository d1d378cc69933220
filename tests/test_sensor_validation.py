"""Flat-wall validation of the physical Kinect v1 pipeline against the published noise models."""
from __future__ import annotations

import json

import numpy as np
import pytest

from synth.sensor.validation import (FlatWallConfig, flat_wall_experiment, khoshelham_sigma_m, nguyen_sigma_m,
                              projector_shadow_side, quantization_step_m)


def test_published_models_hand_values():
    assert khoshelham_sigma_m(1.0) == pytest.approx(0.001425)
    assert khoshelham_sigma_m(3.0) == pytest.approx(0.012825)
    assert nguyen_sigma_m(0.4) == pytest.approx(0.0012)
    assert quantization_step_m(1.0, 580 * 0.075) == pytest.approx(0.125 / 43.5)


def _check(res, full: bool):
    d = np.asarray(res.distances_m)
    s = np.asarray(res.std_m)
    sel = (d >= 0.8) & (d <= 4.0)
    lo = np.minimum(khoshelham_sigma_m(d[sel]), nguyen_sigma_m(d[sel]))
    hi = np.maximum(khoshelham_sigma_m(d[sel]), nguyen_sigma_m(d[sel]))
    assert np.all(s[sel] >= 0.65 * lo) and np.all(s[sel] <= 1.35 * hi), list(zip(d[sel], s[sel] / hi))
    assert res.band_ok
    # noise grows ~ z^2 (not linearly): the 4 m std is > 8x the 1 m one
    i1, i4 = int(np.argmin(abs(d - 1))), int(np.argmin(abs(d - 4)))
    assert s[i4] / s[i1] > 8
    # tilt: nearly everything valid up to 60 deg, most pixels lost beyond ~75-80 deg
    t = np.asarray(res.tilts_deg)
    v = np.asarray(res.tilt_valid_fraction)
    assert v[t == 60][0] > 0.8 * v[0]
    assert v[t == 85][0] < 0.2
    assert 72 <= res.dropout_angle_deg <= 82
    assert res.shadow_side == "left"
    # the staircase has the quantisation step of the device
    m = np.asarray(res.staircase_measured_m)
    levels = np.unique(np.round(m, 5))
    gaps = np.diff(levels)
    zmid = np.mean(res.staircase_true_m)
    assert np.median(gaps) == pytest.approx(quantization_step_m(zmid, res.fb_px_m), rel=0.15)


@pytest.mark.parametrize("effects", ["physical", "direct"])
def test_flat_wall_reduced(tmp_path, effects):
    """Physical pipeline (noise emerging from IR capture + matching) and the direct model
    (analytic effects from ideal depth) both reproduce the published behaviour."""
    cfg = FlatWallConfig(effects=effects, crop=(160, 120), frames=2, distances_m=(0.8, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0),
                         tilts_deg=(0, 60, 70, 75, 78, 80, 85), staircase_m=(2.0, 2.06, 0.003))
    res = flat_wall_experiment(cfg)
    _check(res, full=False)
    out = res.save(tmp_path, figure=True)
    d = json.loads((out / "flat_wall.json").read_text())
    assert d["summary"]["band_ok"] is True and (out / "flat_wall.png").stat().st_size > 10000


def test_shadow_side_follows_projector():
    from synth.sensor import get_preset
    pre = get_preset("kinect_v1").cropped(160, 120)
    assert projector_shadow_side(pre) == "left"
    assert projector_shadow_side(pre.replace(projector_offset_m=(-0.075, 0.0, 0.0))) == "right"
    assert projector_shadow_side(pre, "direct") == "left"


@pytest.mark.slow
def test_flat_wall_full_resolution(tmp_path):
    res = flat_wall_experiment(FlatWallConfig())
    _check(res, full=True)
    res.save(tmp_path)
