"""diagnose(): applicability rules, output format, errors, determinism, config pass-through, and
evidence sentences computed from measured data (sequences of the independent generator,
tests/hidden_effects.py, 160x120)."""
from __future__ import annotations

import dataclasses
import importlib
import json
import re
import time

import numpy as np
import pytest

from data_tools.errors import ConfigError
from synth.lab import DiagnoseConfig, FitConfig, MeasuredSequence, diagnose, fit_model
from synth.lab.diagnose import _applicability
from synth.lab.evidence import EvidenceContext, evidence_for, has_evidence
from synth.sensor.registry import effect_class, effect_names
from synth.sensor.config import MotionLimits, SensorConfig

from tests import hidden_effects as he

fit_mod = importlib.import_module("synth.lab.fit")
descent_mod = importlib.import_module("synth.lab.descent")
diagnose_mod = importlib.import_module("synth.lab.diagnose")   # (synth.lab.diagnose is also the function)

CHEAP_FIT = FitConfig(max_frames=2, max_pixels_per_frame=2000, eval_pixels_per_frame=3000)
CHEAP = DiagnoseConfig(refit_model=False, candidate_evaluations=6, refine_top=0, evaluate=False)


@pytest.fixture(scope="module")
def seqs(tmp_path_factory):
    root = tmp_path_factory.mktemp("lab_diag")
    out = {}
    for e in (*he.HIDDEN_EFFECTS, None):
        p = he.generate(root / str(e), e, seed=21, n_frames=3, width=160, height=120)
        out[e] = (root / str(e), p)
    return out


def _truth_config(ms, params, effects=("axial_noise", "range_limits")):
    """The base model with the generator's true noise level (so tests of evidence/format do not
    depend on the model refit)."""
    s2 = params["sigma_d_px"] / (ms.preset.fx * ms.preset.baseline_m)
    return ms.default_config(list(effects)).with_params({"axial_noise.sigma2_per_m": s2})


def test_applicability_rules():
    direct = SensorConfig.build("kinect_v1", ["axial_noise"])
    assert "physical pipeline" in _applicability(direct, "block_matching")
    assert "tof" in _applicability(direct, "multipath")
    assert _applicability(direct, "projector_shadow") is None
    tof = SensorConfig.build("kinect_v2", ["axial_noise"])
    assert "structured_light" in _applicability(tof, "projector_shadow")
    assert _applicability(tof, "multipath") is None


def test_diagnosis_format_ranking_and_skips(seqs, tmp_path):
    path, params = seqs["projector_shadow"]
    ms = MeasuredSequence.load(path)
    cfg = _truth_config(ms, params)
    d = diagnose(ms, cfg, candidates=["specular_dropout", "projector_shadow", "multipath", "depth_bias"],
                 fit_config=CHEAP_FIT, diagnose_config=CHEAP)
    # no specular material in the scene: the probe finds specular dropout changes nothing
    assert "unchanged" in d.skipped["specular_dropout"] and "tof" in d.skipped["multipath"]
    assert [c.effect for c in d.ranking][0] == "projector_shadow"
    gains = [c.gain for c in d.ranking]
    assert gains == sorted(gains, reverse=True)
    for c in d.ranking:
        assert c.gain == pytest.approx((d.gap - c.gap_after) / d.gap)
    j = d.to_json()
    assert set(j) >= {"gap", "ranking", "skipped", "model"}
    assert set(j["ranking"][0]) >= {"effect", "gap_after", "gain", "params", "evidence"}
    p = d.save(tmp_path / "out")
    assert p.name == "diagnosis.json" and json.loads(p.read_text())["ranking"][0]["effect"] == "projector_shadow"


def test_bad_candidates_raise(seqs):
    ms = MeasuredSequence.load(seqs[None][0])
    cfg = ms.default_config(["axial_noise", "range_limits"])
    with pytest.raises(ConfigError, match="no_such"):
        diagnose(ms, cfg, candidates=["no_such"], fit_config=CHEAP_FIT, diagnose_config=CHEAP)
    with pytest.raises(ConfigError, match="already in the model"):
        diagnose(ms, cfg, candidates=["axial_noise"], fit_config=CHEAP_FIT, diagnose_config=CHEAP)


def _ctx(seqs, effect):
    path, params = seqs[effect]
    ms = MeasuredSequence.load(path)
    cfg = _truth_config(ms, params)
    obs = ms.observations(ms.simulate(cfg))
    albedo = {k + 1: ms.scene.material_of(m).albedo for k, m in enumerate(ms.scene.meshes)}
    return EvidenceContext(obs, ms.preset, albedo), params


def _percents(s):
    return [float(x) for x in re.findall(r"(\d+) %", s)]


def _claims(s):
    """Phrases that assert a signature (must only appear when the numbers support them)."""
    return [p for p in ("grows with the image radius", "loses more pixels than", "rises at grazing",
                        "systematically off", "lie on a lattice", "carry the foreground", "more than brighter",
                        "against")
            if p in s]


_MM = r"([\d.]+) mm"


@pytest.mark.parametrize("effect", he.HIDDEN_EFFECTS)
def test_evidence_states_the_signature_when_the_data_show_it(seqs, effect):
    ctx, p = _ctx(seqs, effect)
    params = {"lens_distortion": {"lens_distortion.k1": p.get("k1")},
              "disparity_quantization": {"disparity_quantization.step_px": p.get("step_px")}}.get(effect, {})
    s = evidence_for(effect, ctx, params, gain=0.4)
    assert "weak" not in s and _claims(s), s
    pc = _percents(s)
    if effect == "projector_shadow":
        shadow_rate, lit_rate, model_rate, share = pc[:4]
        assert shadow_rate > 5 * max(lit_rate, 1) and model_rate < 5 and share > 60, s
    elif effect == "low_reflectance":
        dark, bright = pc[:2]
        assert dark > 50 and bright < 5 and "black_fabric" in s, s
    elif effect == "lens_distortion":
        centre, outer = (float(x) for x in re.findall(_MM, s)[:2])
        ratio = float(re.search(r"\(x([\d.]+);", s).group(1))
        assert "grows with the image radius" in s and outer > 1.5 * centre and ratio > 1.5, s
    elif effect == "edge_fattening":
        assert pc[0] > 20 and pc[2] < 5, s
    elif effect == "incidence_dropout":
        assert "rises at grazing incidence" in s and pc[0] < 5 and max(pc[2:-1]) > 50, s
    elif effect == "depth_bias":
        assert "systematically off" in s, s
    elif effect == "disparity_quantization":
        # the lattice is found in the measurement alone, within 3 % of the generator's step
        step = float(re.search(r"lattice of ([\d.]+) px", s).group(1))
        assert abs(step - p["step_px"]) / p["step_px"] < 0.03, s
    # a signature the fitted effect does not explain is reported as such
    s0 = evidence_for(effect, ctx, params, gain=0.0)
    assert s0.startswith(s[:-1]) and s0.endswith("; yet adding the fitted effect does not lower the gap."), s0


@pytest.mark.parametrize("effect", [n for n in effect_names() if has_evidence(n)])
def test_evidence_says_weak_when_the_data_lack_the_signature(seqs, effect):
    """Base-only data: every evidence function reports the numbers without claiming a signature,
    and the lead clause follows the sign of the gain."""
    ctx, _ = _ctx(seqs, None)
    s = evidence_for(effect, ctx, {}, gain=0.12)
    assert s.startswith("Adding it lowers the gap by 12 %, but the ") and "is weak in the measured data" in s, s
    assert not _claims(s), s
    s0 = evidence_for(effect, ctx, {}, gain=0.0)
    assert s0.startswith("Adding it does not lower the gap, and the ") and "weak" in s0, s0


def test_lens_evidence_follows_the_sign_of_the_radial_change(seqs):
    """The reported case: outer-ring error below the centre's must not read 'grows'."""
    ctx, _ = _ctx(seqs, None)
    s = evidence_for("lens_distortion", ctx, {})
    centre, outer = (float(x) for x in re.findall(_MM, s)[:2])
    assert outer < centre and "grows" not in s and "radial signature is weak" in s, s


def test_shadow_evidence_is_weak_when_holes_are_everywhere(seqs):
    """The reported case: shadow-side holes drowned in holes everywhere must not be presented as
    a shadow signature, and no non-zero share is printed as '0 %'."""
    ctx, _ = _ctx(seqs, "projector_shadow")
    rng = np.random.default_rng(0)
    obs = []
    for o in ctx.observations:
        m = o.measured.copy()
        m[rng.random(m.shape) < 0.6] = 0.0
        obs.append(dataclasses.replace(o, measured=m))
    s = evidence_for("projector_shadow", EvidenceContext(obs, ctx.preset, ctx.albedo), {}, gain=0.05)
    shadow_rate, lit_rate = _percents(s)[1:3]
    assert "projector-shadow signature is weak" in s and shadow_rate < 1.5 * lit_rate, s
    assert "holes are" not in s, s


def test_percentages_never_round_a_nonzero_rate_to_zero():
    from synth.lab.evidence import EvidenceContext
    _pct = EvidenceContext.pct
    assert _pct(0.004) == "<1 %" and _pct(0.0) == "0 %" and _pct(0.996) == ">99 %" and _pct(1.0) == "100 %"


# ------------------------------------------------------------------------------------------
# Determinism and config pass-through
# ------------------------------------------------------------------------------------------

class _JumpingClock:
    """A stand-in for the time module whose wall clock jumps an hour per reading: any
    wall-clock budget would stop every search at its first check."""

    def __init__(self):
        self.t = time.perf_counter()

    def perf_counter(self):
        self.t += 3600.0
        return self.t

    def process_time(self):
        return time.process_time()


def _untimed(d):
    """diagnosis.json content without its timing fields."""
    if isinstance(d, dict):
        return {k: _untimed(v) for k, v in d.items() if k != "seconds"}
    if isinstance(d, list):
        return [_untimed(v) for v in d]
    return d


DET_FIT = FitConfig(max_frames=2, max_pixels_per_frame=2000, eval_pixels_per_frame=3000)
DET = DiagnoseConfig(model_evaluations=8, candidate_evaluations=6, refine_top=1, refine_evaluations=6)
DET_CANDS = ["projector_shadow", "depth_bias", "edge_fattening"]


def test_diagnose_is_deterministic_and_ignores_the_wall_clock(seqs, monkeypatch):
    path, _ = seqs["projector_shadow"]
    ms = MeasuredSequence.load(path)
    cfg = ms.default_config(["axial_noise", "range_limits"])
    a = diagnose(ms, cfg, candidates=DET_CANDS, fit_config=DET_FIT, diagnose_config=DET)
    assert a.ranking[0].refined and not a.time_capped
    monkeypatch.setattr(fit_mod, "time", _JumpingClock())
    monkeypatch.setattr(descent_mod, "time", _JumpingClock())
    monkeypatch.setattr(diagnose_mod, "time", _JumpingClock())
    # a fresh sequence (cold caches) under a clock that runs wild: the same diagnosis
    b = diagnose(MeasuredSequence.load(path), cfg, candidates=DET_CANDS, fit_config=DET_FIT, diagnose_config=DET)
    assert _untimed(b.to_json()) == _untimed(a.to_json())
    assert [c.params for c in b.ranking] == [c.params for c in a.ranking]
    # the optional safety guard is the only wall-clock limit, and the result says when it acted
    guarded = dataclasses.replace(DET_FIT, max_seconds=60.0)
    c = diagnose(ms, cfg, candidates=DET_CANDS, fit_config=guarded, diagnose_config=DET)
    assert c.time_capped and c.to_json()["time_capped"] is True
    r = fit_model(ms, cfg, fit_config=dataclasses.replace(guarded, max_evaluations=6))
    assert r.time_capped and r.to_json()["time_capped"] is True


def test_fit_and_diagnose_keep_every_config_field(seqs):
    """A custom motion limit (any SensorConfig field besides preset/effects) survives the refit,
    the candidates, the joint refinement and fit_model."""
    path, _ = seqs["lens_distortion"]
    ms = MeasuredSequence.load(path)
    motion = MotionLimits(max_speed_m_s=1.25, max_angular_speed_rad_s=0.5)
    cfg = dataclasses.replace(ms.default_config(["axial_noise", "range_limits"]), motion=motion)
    d = diagnose(ms, cfg, candidates=["lens_distortion", "disparity_quantization"], fit_config=DET_FIT,
                 diagnose_config=DET)
    assert d.model_config.motion == motion
    assert all(c.config.motion == motion for c in d.ranking)
    res = fit_model(ms, cfg, fit_config=dataclasses.replace(DET_FIT, max_evaluations=6))
    assert res.config.motion == motion


def test_effects_declare_the_sensor_types_they_model():
    assert effect_class("multipath").sensor_types == ("tof",)
    assert effect_class("projector_shadow").sensor_types == ("structured_light", "active_stereo")
    assert effect_class("axial_noise").sensor_types is None          # every type
    declared = {n: effect_class(n).sensor_types for n in effect_names()}
    assert {n for n, t in declared.items() if t == ("tof",)} == {"multipath", "wiggling", "flying_pixels"}
