"""diagnose(): applicability rules, output format, errors, and evidence sentences computed from
measured data (sequences of the independent generator, tests/hidden_effects.py, 160x120)."""
from __future__ import annotations

import json
import re

import pytest

from data_tools.errors import ConfigError
from synth.lab import DiagnoseConfig, FitConfig, MeasuredSequence, diagnose
from synth.lab.diagnose import _applicability
from synth.lab.evidence import EvidenceContext, evidence_for
from synth.sensor.simulator import SensorConfig

from tests import hidden_effects as he

CHEAP_FIT = FitConfig(max_frames=2, max_pixels_per_frame=2000, eval_pixels_per_frame=3000)
CHEAP = DiagnoseConfig(refit_model=False, candidate_evaluations=6, refine_top=0, evaluate=False)


@pytest.fixture(scope="module")
def seqs(tmp_path_factory):
    root = tmp_path_factory.mktemp("lab_diag")
    out = {}
    for e in ("projector_shadow", "low_reflectance", "lens_distortion", "edge_fattening", None):
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


def test_evidence_sentences_come_from_the_data(seqs):
    ctx, _ = _ctx(seqs, "projector_shadow")
    s = evidence_for("projector_shadow", ctx, {})
    share, shadow_rate, lit_rate, model_rate = _percents(s)[:4]
    assert share > 60 and shadow_rate > 5 * max(lit_rate, 1) and model_rate < 5, s
    # the same sentence on data without shadows says so
    ctx0, _ = _ctx(seqs, None)
    assert _percents(evidence_for("projector_shadow", ctx0, {}))[1] < 5

    ctx, p = _ctx(seqs, "low_reflectance")
    s = evidence_for("low_reflectance", ctx, {})
    dark, bright = _percents(s)[:2]
    assert dark > 50 and bright < 5 and "black_fabric" in s, s

    ctx, p = _ctx(seqs, "lens_distortion")
    s = evidence_for("lens_distortion", ctx, {"lens_distortion.k1": p["k1"]})
    ratio = float(re.search(r"\(x([\d.]+)\)", s).group(1))
    assert ratio > 2, s

    ctx, p = _ctx(seqs, "edge_fattening")
    s = evidence_for("edge_fattening", ctx, {})
    assert _percents(s)[0] > 20 and _percents(s)[2] < 5, s
