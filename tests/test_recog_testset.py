"""recog testset's changed effects (recog/testset.py, ``--effect-override`` / ``--effect-preset``): the
preset is generated from the training randomisation and lies outside it, the overrides give the same sensor
model as a hand-edited sensor_config.json, they change the scans and are recorded, and bad names or values
are one-line errors that write nothing."""
from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from data_tools.errors import ConfigError
from recog.data import PHYSICAL_RANDOMISATION
import recog.testset as ts
from synth.sensor.config import SensorConfig
from tests.test_bad_input import check_one_line_error


def test_beyond_training_is_outside_every_training_range_by_hand():
    p = ts.beyond_training()
    assert set(p) == set(PHYSICAL_RANDOMISATION)
    assert p["ir_capture.read_noise_e"] == 17.0            # 12 + 0.5 (12 - 2)
    assert p["pattern_projection.power"] == 4.0            # log range 0.5-2: 2 * (2 / 0.5) ** 0.5
    assert ts.beyond_training(1.0)["ir_capture.speckle_contrast"] == pytest.approx(0.75)
    for k, (lo, hi, _kind) in PHYSICAL_RANDOMISATION.items():
        assert p[k] > hi, k
    s = ts.testset_sensor(ts.TestsetConfig(sensor="kinect_v1", effect_preset="beyond_training",
                                     effect_overrides={"ir_capture.read_noise_e": 30.0})).fittable()
    assert s["ir_capture.psf_sigma_px"][0] == 1.15 and s["ir_capture.read_noise_e"][0] == 30.0   # the override wins


def test_overrides_equal_a_hand_edited_sensor_json(tmp_path):
    ov = ts.parse_effect_overrides(["pattern_projection.dot_sigma_px=0.9,ir_capture.read_noise_e=20",
                                 " ir_capture.psf_sigma_px = 1.2 "])
    assert ov == {"pattern_projection.dot_sigma_px": 0.9, "ir_capture.read_noise_e": 20.0,
                  "ir_capture.psf_sigma_px": 1.2}
    d = SensorConfig.from_spec("kinect_v1", "physical").to_json()
    for e in d["effects"]:
        if e["name"] == "ir_capture":
            e["params"].update(read_noise_e=20.0, psf_sigma_px=1.2)
        if e["name"] == "pattern_projection":
            e["params"]["dot_sigma_px"] = 0.9
    (tmp_path / "s.json").write_text(json.dumps(d))
    by_file = SensorConfig.load(tmp_path / "s.json").to_json()
    assert ts.testset_sensor(ts.TestsetConfig(sensor="kinect_v1", effect_overrides=ov)).to_json() == by_file
    assert ts.testset_sensor(ts.TestsetConfig(sensor="kinect_v1")).to_json() != by_file


@pytest.mark.parametrize("items, words", [(["ir_capture.read_noise_e"], "EFFECT.PARAM=VALUE"),
                                          (["read_noise_e=3"], "EFFECT.PARAM=VALUE"),
                                          (["ir_capture.read_noise_e=lots"], "not a number")])
def test_malformed_overrides(items, words):
    with pytest.raises(ConfigError, match=words):
        ts.parse_effect_overrides(items)


def _box(tmp_path):
    import trimesh
    trimesh.creation.box(extents=(0.10, 0.06, 0.05)).export(tmp_path / "box.ply")
    return str(tmp_path / "box.ply")


def test_overrides_change_the_scans_and_are_recorded(tmp_path, monkeypatch):
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    obj = _box(tmp_path)
    base = ["recog", "testset", "--objects", obj, "--per-object", "1", "--sensor", "kinect_v1",
            "--effects", "axial_noise", "--seed", "3"]
    from data_tools.sequence import read_depth_png
    depth = {}
    for name, extra in (("plain", []), ("a", ["--effect-override", "axial_noise.sigma0_m=0.02"]),
                        ("b", ["--effect-override", "axial_noise.sigma0_m=0.02"])):
        assert main(base + ["--out", str(tmp_path / name)] + extra) == 0
        depth[name] = read_depth_png(tmp_path / name / "depth" / "000000.png", 5000.0)
    cfg = json.loads((tmp_path / "a" / "testset_config.json").read_text())
    assert cfg["effect_overrides"] == {"axial_noise.sigma0_m": 0.02} and cfg["effect_preset"] == ""
    np.testing.assert_array_equal(depth["a"], depth["b"])
    both = (depth["a"] > 0) & (depth["plain"] > 0)
    # a 2 cm axial noise floor against the preset's: the same pixels differ by centimetres
    assert np.abs(depth["a"][both] - depth["plain"][both]).mean() > 0.01


@pytest.mark.parametrize("extra, words", [
    (["--effect-override", "ir_capture.nope=1"], ["nope", "not a fittable parameter"]),
    (["--effect-override", "nope.x=1"], ["'nope'", "not in this sensor model"]),
    (["--effect-override", "ir_capture.read_noise_e=-5"], ["read_noise_e", "outside its bounds"]),
    (["--effect-override", "ir_capture=5"], ["EFFECT.PARAM=VALUE"]),
    (["--effect-preset", "worst"], ["unknown effect preset 'worst'", "beyond_training"])])
def test_bad_effect_names_are_one_line_and_write_nothing(extra, words, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("REALGAP_NO_PROGRESS", "1")
    obj = _box(tmp_path)
    check_one_line_error(tmp_path, ["recog", "testset", "--objects", obj, "--per-object", "1",
                                    "--sensor", "kinect_v1", "--out", "{S}"] + extra, words, capsys, exact=True)
