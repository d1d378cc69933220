"""Adding an effect touches one file: a new effect written outside the package (a folder named in
``$REALGAP_EFFECT_PATH``) gets the contract suite, the parameter checks, the CLI, a fit and a
diagnosis (with its own signature figure and evidence sentence) without any other change."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

STEP_BIAS = '''
"""A toy effect for tests: depth beyond a distance is offset (a step in the bias)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from synth.sensor.registry import STAGE_DEPTH, Effect, Signature, param, register_effect


@dataclass
class StepBiasParams:
    offset_m: float = param(0.0, "m")
    """Depth offset of pixels beyond ``start_m``, metres."""
    start_m: float = param(1.25, "m", 0.0, 20.0)
    """Depth at which the offset starts, metres."""


@register_effect
class StepBias(Effect):
    """z' = z + offset for z > start (a test effect: a calibration step at one range)."""

    name = "step_bias"
    SIGNATURE = Signature("a step in the bias at one distance",
                          "The median error jumps at one distance and stays there.",
                          panels=(("distance", "bias"),))
    IDENTITY_PARAMS = {"offset_m": 0.0}
    Params = StepBiasParams
    FITTABLE = {"offset_m": (-0.1, 0.1)}
    stage = STAGE_DEPTH + 2

    def apply(self, state, draw) -> None:
        far = state.valid & (state.depth > self.params.start_m)
        state.depth = np.where(far, state.depth + self.params.offset_m, state.depth).astype(np.float32)

    @classmethod
    def evidence(cls, ctx, params, gain=None):
        z, m = ctx.ideal, ctx.measured
        v = m > 0
        far, near = v & (z > 1.25), v & (z <= 1.25)
        if far.sum() < 50 or near.sum() < 50:
            return ctx.weak("step signature", gain, "too few pixels on one side of 1.25 m")
        step = float(np.median(m[far] - z[far]) - np.median(m[near] - z[near]))
        return f"the median error steps by {ctx.mm(step)} at 1.25 m (step_bias evidence)."
'''


def test_an_effect_in_one_outside_file_gets_everything(tmp_path):
    effects = tmp_path / "my_effects"
    effects.mkdir()
    (effects / "step_bias.py").write_text(STEP_BIAS)
    env = {**os.environ, "REALGAP_EFFECT_PATH": str(effects)}

    # 1. the contract suite and the parameter declaration checks run on it as on every built-in effect
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", "step_bias",
                        "tests/test_effect_contract.py", "tests/test_sensor_registry.py"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:]
    n_passed = int(r.stdout.strip().splitlines()[-1].split(" passed")[0].split()[-1])
    assert n_passed >= 8, r.stdout[-500:]

    # 2. `realgap sensor effects` lists it with its parameters (generated from the registry)
    r = subprocess.run([sys.executable, "-m", "app", "sensor", "effects", "step_bias", "--json"], cwd=REPO, env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    (entry,) = json.loads(r.stdout)
    offset = next(p for p in entry["parameters"] if p["name"] == "offset_m")
    assert offset["unit"] == "m" and offset["fit_range"] == [-0.1, 0.1] and entry["signature"].startswith("a step")

    # 3. a measured sequence with a 3 cm step: the fit finds it, the diagnosis ranks it first with its
    # own signature figure and evidence sentence
    script = textwrap.dedent(f"""
        import json, sys
        sys.path.insert(0, {str(REPO / 'tests')!r})
        from test_sensor_cli import TRUE_EFFECTS, make_measured_sequence
        from app.cli import main
        from pathlib import Path
        root = Path({str(tmp_path)!r})
        seq = make_measured_sequence(root, effects=[*TRUE_EFFECTS,
                                     {{"name": "step_bias", "params": {{"offset_m": 0.03}}}}])
        base = ",".join(TRUE_EFFECTS)
        fo = ["--fit-option", "max_frames=2", "--fit-option", "max_pixels_per_frame=3000",
              "--fit-option", "max_evaluations=12"]
        assert main(["sensor", "fit", str(seq), "--effects", base + ",step_bias", "--only", "step_bias",
                     "--out", str(root / "model.json"), *fo]) == 0
        assert main(["sensor", "diagnose", str(seq), "--effects", base, "--candidates",
                     "step_bias,incidence_dropout", "--out", str(root / "diag"), "--top", "2",
                     "--report-frames", "1", *fo]) == 0
    """)
    r = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    model = json.loads((tmp_path / "model.json").read_text())
    step = next(e for e in model["effects"] if e["name"] == "step_bias")
    assert step["params"]["offset_m"] == pytest.approx(0.03, abs=0.006)
    assert model["fit"]["gap"] < model["fit"]["gap_before"]
    diag = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    best = diag["ranking"][0]
    assert best["effect"] == "step_bias" and "step_bias evidence" in best["evidence"]
    page = (tmp_path / "diag" / "diagnosis.html").read_text()
    assert "a step in the bias at one distance" in page


def test_a_broken_effect_file_is_a_one_line_error(tmp_path):
    (tmp_path / "broken.py").write_text("import numpy as np\nraise ValueError('no')\n")
    env = {**os.environ, "REALGAP_EFFECT_PATH": str(tmp_path)}
    (tmp_path / "seq").mkdir()       # an output is never inside its input: SEQ and --out side by side
    r = subprocess.run([sys.executable, "-m", "app", "sensor", "compare", str(tmp_path / "seq"), "--effects",
                        "axial_noise", "--out", str(tmp_path / "out")], cwd=REPO, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 1
    err = r.stderr.strip()
    assert "\n" not in err and "broken.py" in err and "ValueError" in err, err
