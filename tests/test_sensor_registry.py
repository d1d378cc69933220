"""Effect registry, sensor configs (JSON round trip), presets and bad input."""
from __future__ import annotations

import dataclasses
import json

import pytest

from data_tools.config import field_docs
from data_tools.errors import ConfigError, FormatError, RealgapError
from synth.sensor import (PRESETS, SensorConfig, SensorPreset, effect_class, effect_names, get_preset,
                          make_effect)
from synth.sensor.registry import Effect, register_effect

REQUIRED = ["axial_noise", "edge_fattening", "projector_shadow", "incidence_dropout", "low_reflectance",
            "specular_dropout", "disparity_quantization", "lens_distortion", "depth_bias", "range_limits",
            "ambient_light", "motion_blur", "rolling_shutter", "hole_filling", "pattern_projection",
            "ir_capture", "block_matching", "multipath", "wiggling", "flying_pixels"]


def test_required_effects_are_registered():
    names = effect_names()
    for n in REQUIRED:
        assert n in names


@pytest.mark.parametrize("name", REQUIRED)
def test_effect_class_is_documented_typed_and_fittable(name):
    cls = effect_class(name)
    assert cls.name == name
    assert cls.__doc__, "each effect explains its physics"
    assert dataclasses.is_dataclass(cls.Params)
    fields = {f.name for f in dataclasses.fields(cls.Params)}
    undocumented = fields - set(field_docs(cls.Params))
    assert not undocumented, f"{name}: parameters without a docstring: {sorted(undocumented)}"
    assert set(cls.FITTABLE) <= fields
    for k, (lo, hi) in cls.FITTABLE.items():
        assert lo < hi
    e = cls()  # defaults are valid
    assert e.enabled


@pytest.mark.parametrize("name", effect_names())
def test_every_parameter_declares_unit_and_plausible_range(name):
    """Each effect file declares, per parameter, a unit and bounds (or choices); defaults, every
    preset's value and the fit range lie inside; a value outside is a one-line ConfigError
    naming effect, parameter and range."""
    cls = effect_class(name)
    for key, cp in cls.CONFIG_PARAMETERS.items():
        assert cp.unit is not None and cp.low < cp.high, f"{name}.{key}: config parameter without unit or range"
    for spec in cls.param_specs():
        where = f"{name}.{spec.name}"
        assert spec.unit is not None, f"{where}: no unit (declare it with registry.param)"
        assert spec.doc, f"{where}: no docstring"
        if spec.type in ("int", "float"):
            assert spec.bounds is not None, f"{where}: no plausible range"
            lo, hi = spec.bounds
            assert lo <= spec.default <= hi, f"{where}: default {spec.default} outside [{lo}, {hi}]"
            if spec.fit_range is not None:
                assert lo <= spec.fit_range[0] < spec.fit_range[1] <= hi, f"{where}: fit range outside bounds"
            for preset in PRESETS.values():
                v = preset.effect_params.get(name, {}).get(spec.name)
                if v is not None:
                    assert lo <= v <= hi, f"{where}: preset {preset.name} sets {v}, outside [{lo}, {hi}]"
            bad = hi + (abs(hi) + 1.0)
            with pytest.raises(ConfigError) as ei:
                make_effect({"name": name, "params": {spec.name: int(bad) if spec.type == "int" else bad}})
            msg = str(ei.value)
            assert name in msg and spec.name in msg and "bounds" in msg and "\n" not in msg
        elif spec.type == "str" and spec.name in effect_class(name).FILE_PARAMS:
            with pytest.raises(ConfigError) as ei:       # a data file that is not there
                make_effect({"name": name, "params": {spec.name: "/nonexistent/map.npy"}})
            msg = str(ei.value)
            assert name in msg and "/nonexistent/map.npy" in msg and "not found" in msg and "\n" not in msg
        elif spec.type == "str":
            assert spec.choices and spec.default in spec.choices, f"{where}: declare its choices"
            with pytest.raises(ConfigError, match=f"{spec.name}='nope' is not one of"):
                make_effect({"name": name, "params": {spec.name: "nope"}})


def test_unknown_effect_lists_known_names():
    with pytest.raises(ConfigError) as ei:
        effect_class("gaussian_blurr")
    msg = str(ei.value)
    assert "gaussian_blurr" in msg and "axial_noise" in msg and "block_matching" in msg
    assert "\n" not in msg
    with pytest.raises(ConfigError):
        SensorConfig.build("kinect_v1", ["axial_noise", "nope"])


def test_bad_params_are_config_errors():
    with pytest.raises(ConfigError, match="unknown parameter"):
        make_effect({"name": "axial_noise", "params": {"sigma": 1}})
    with pytest.raises(ConfigError, match="outside its bounds"):
        make_effect({"name": "incidence_dropout", "params": {"angle50_deg": 120}})
    with pytest.raises(ConfigError, match=r"hole_filling.*max_hole_px: expected an integer"):
        make_effect({"name": "hole_filling", "params": {"max_hole_px": "many"}})
    with pytest.raises(ConfigError, match=r"axial_noise.*expected a finite number"):
        make_effect({"name": "axial_noise", "params": {"sigma2_per_m": float("nan")}})
    with pytest.raises(ConfigError, match="twice"):
        SensorConfig.build("kinect_v1", ["axial_noise", "axial_noise"])


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("model", ["physical", "direct"])
def test_config_json_round_trip(preset, model, tmp_path):
    cfg = SensorConfig.build(preset, model)
    cfg.effects[0].enabled = False
    d = cfg.to_json()
    text = json.dumps(d)  # plain JSON data
    back = SensorConfig.from_json(json.loads(text))
    assert back.to_json() == d
    assert back.preset == cfg.preset
    p = cfg.save(tmp_path / "sensor_config.json")
    assert SensorConfig.load(p).to_json() == d


def test_preset_defaults_reach_effect_params():
    cfg = SensorConfig.build("kinect_v1")
    assert cfg.effect("ir_capture").params.gain_e == PRESETS["kinect_v1"].effect_params["ir_capture"]["gain_e"]
    # explicit params win over preset defaults
    cfg2 = SensorConfig.build("kinect_v1", [{"name": "ir_capture", "params": {"read_noise_e": 7.0}}])
    p = cfg2.effect("ir_capture").params
    assert p.read_noise_e == 7.0 and p.gain_e == 30000.0


def test_fittable_and_with_params():
    cfg = SensorConfig.build("kinect_v1", "direct")
    fit = cfg.fittable()
    assert "axial_noise.sigma2_per_m" in fit and "incidence_dropout.angle50_deg" in fit
    v, lo, hi = fit["axial_noise.sigma2_per_m"]
    c2 = cfg.with_params({"axial_noise.sigma2_per_m": 0.003})
    assert c2.effect("axial_noise").params.sigma2_per_m == 0.003
    assert cfg.effect("axial_noise").params.sigma2_per_m == v  # original untouched
    with pytest.raises(ConfigError):
        cfg.with_params({"axial_noise.sigma2_per_m": hi * 10})
    with pytest.raises(ConfigError):
        cfg.with_params({"axial_noise.not_a_param": 1.0})


@pytest.fixture
def clean_registry():
    from synth.sensor import registry
    before = dict(registry._REGISTRY)
    yield
    registry._REGISTRY.clear()
    registry._REGISTRY.update(before)


def test_register_a_new_effect_by_class(clean_registry):
    @dataclasses.dataclass
    class P:
        value_m: float = 0.01
        """Offset, metres."""

    @register_effect
    class _TestOffset(Effect):
        """Adds a constant (test-only effect registered at run time to prove the extension
        point works without touching any other file of the package). It has no physics at all,
        but it is a complete effect: typed params, fittable bounds, sample/apply split."""
        name = "_test_offset"
        Params = P
        FITTABLE = {"value_m": (0.0, 1.0)}

        def apply(self, state, draw):
            state.depth = state.depth + self.params.value_m

    assert "_test_offset" in effect_names()
    e = make_effect({"name": "_test_offset", "params": {"value_m": 0.5}})
    assert e.params.value_m == 0.5
    with pytest.raises(TypeError):
        @register_effect
        class _Dup(Effect):  # same name, other class
            name = "_test_offset"
            Params = P

            def apply(self, state, draw):
                pass


def test_presets_have_published_specs():
    k = get_preset("kinect_v1")
    assert (k.width, k.height, k.fx, k.baseline_m, k.block_size, k.subpixel_step_px) == (640, 480, 580.0, 0.075, 9, 0.125)
    d = get_preset("realsense_d435")
    assert (d.width, d.height, d.baseline_m, d.type, d.matcher) == (848, 480, 0.05, "active_stereo", "sgbm")
    v2 = get_preset("kinect_v2")
    assert (v2.width, v2.height, v2.type) == (512, 424, "tof")
    for name in ("multipath", "wiggling", "flying_pixels"):
        assert name in v2.physical_effects
    for p in PRESETS.values():
        assert p.source and p.description
        for n in p.physical_effects + p.direct_effects + tuple(p.effect_params):
            effect_class(n)  # every name a preset uses exists


def test_bad_presets():
    k = get_preset("kinect_v1")
    with pytest.raises(ConfigError, match="baseline"):
        k.replace(baseline_m=-0.075)
    with pytest.raises(ConfigError, match="x axis"):
        k.replace(projector_offset_m=(0.0, 0.075, 0.0))
    with pytest.raises(ConfigError, match="unknown sensor preset"):
        get_preset("kinect_v3")
    with pytest.raises(ConfigError):
        SensorPreset.from_json({**k.to_json(), "colour": "red"})
    assert SensorPreset.from_json(k.to_json()) == k


def test_bad_config_file(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(FormatError, match="bad.json"):
        SensorConfig.load(p)
    p.write_text(json.dumps({"preset": "kinect_v1", "effects": [{"name": "warp_drive"}]}))
    with pytest.raises(FormatError, match="warp_drive"):
        SensorConfig.load(p)
    assert issubclass(FormatError, RealgapError)


def test_sensor_effects_and_presets_commands_come_from_the_registry(capsys):
    from app.cli import main
    assert main(["sensor", "effects", "--json"]) == 0
    listed = {e["name"]: e for e in json.loads(capsys.readouterr().out)}
    assert sorted(listed) == effect_names()
    for name, e in listed.items():
        specs = {s.name: s for s in effect_class(name).param_specs()}
        for p in e["parameters"]:
            if p["name"] in specs:
                s = specs[p["name"]]
                assert p["unit"] == s.unit and p["bounds"] == (list(s.bounds) if s.bounds else None)
                assert p["fit_range"] == (list(s.fit_range) if s.fit_range else None)
    sigma2 = next(p for p in listed["axial_noise"]["parameters"] if p["name"] == "sigma2_per_m")
    assert sigma2["presets"]["kinect_v1"] == PRESETS["kinect_v1"].effect_params["axial_noise"]["sigma2_per_m"]
    assert "kinect_v1" in listed["disparity_quantization"]["used_by"]

    assert main(["sensor", "effects", "incidence_dropout"]) == 0
    text = capsys.readouterr().out
    assert "angle50_deg" in text and "deg" in text and "(30, 90)" in text

    assert main(["sensor", "presets", "kinect_v1", "--json"]) == 0
    (k1,) = json.loads(capsys.readouterr().out)
    fields = {f["name"]: f["value"] for f in k1["fields"]}
    assert fields["fx"] == PRESETS["kinect_v1"].fx and k1["physical_effects"] == list(PRESETS["kinect_v1"].physical_effects)
    assert main(["sensor", "presets"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert len(rows) == 2 + len(PRESETS) and len({len(r.rstrip()) <= len(rows[1]) for r in rows}) == 1
    assert main(["sensor", "presets", "kinect_v9"]) == 1
    assert "kinect_v9" in capsys.readouterr().err
