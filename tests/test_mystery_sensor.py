"""The mystery sensor (:mod:`synth.lab.mystery`): deterministic per seed, its geometry agrees with the
lab's own renderer of the scene.json it writes (two independent ray casters), its noise follows the
disparity model it declares, and the answer file names the hidden effect."""
from __future__ import annotations

import json

import numpy as np
import pytest

from synth.lab.mystery import MYSTERY_EFFECTS, make_mystery_sequence


def _depth(seq, k=0):
    from data_tools.sequence import SequenceReader
    return SequenceReader(seq).read_depth(k)


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    a = make_mystery_sequence(tmp_path / "a", seed=3, frames=2, effect="depth_bias")
    b = make_mystery_sequence(tmp_path / "b", seed=3, frames=2, effect="depth_bias")
    c = make_mystery_sequence(tmp_path / "c", seed=4, frames=2, effect="depth_bias")
    assert a == b and a != c
    for name in ("depth/00000.png", "depth/00001.png", "scene.json", "camera.json", "groundtruth.txt"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert (tmp_path / "a" / "depth/00000.png").read_bytes() != (tmp_path / "c" / "depth/00000.png").read_bytes()


def test_answer_names_the_effect_and_the_conversion_is_consistent(tmp_path):
    ans = make_mystery_sequence(tmp_path / "s", seed=1, frames=1, effect="disparity_quantization")
    saved = json.loads((tmp_path / "s_answer.json").read_text())
    assert saved["effect"] == "disparity_quantization" == ans["effect"]
    assert 0.1 <= saved["parameters"]["step_px"] <= 0.25
    r, cam = saved["raw_disparity"], saved["camera"]
    # z = 1 / (c0 + c1 d) with d in 1/8 px: d = d_inf - 8 f b / z round-trips for any z
    z = np.array([0.5, 1.0, 2.5, 4.0])
    d = r["d_inf"] - 8 * cam["fx"] * cam["baseline_m"] / z
    np.testing.assert_allclose(1.0 / (r["c0"] + r["c1"] * d), z, rtol=1e-12)
    with pytest.raises(ValueError, match="unknown mystery effect"):
        make_mystery_sequence(tmp_path / "x", seed=1, frames=1, effect="wobble")


def test_geometry_agrees_with_the_labs_renderer(tmp_path):
    """Where both have depth, the mystery depth (no bias hidden) and the lab's ideal render of the
    written scene.json agree to within the noise: poses, intrinsics and meshes mean the same."""
    from synth.lab.measured import MeasuredSequence
    make_mystery_sequence(tmp_path / "s", seed=2, frames=1, effect="projector_shadow")
    m = MeasuredSequence.load(tmp_path / "s")
    ideal = m.render(0)
    ideal = ideal.depth if hasattr(ideal, "depth") else ideal
    meas = m.measured_depth(0)
    both = (ideal > 0) & (meas > 0)
    assert both.mean() > 0.9
    diff = (meas - ideal)[both]
    assert abs(np.median(diff)) < 0.002                  # metres: no offset between the two casters
    assert np.median(np.abs(diff)) < 0.02                # noise, not misplaced geometry


def test_noise_grows_as_the_declared_disparity_noise(tmp_path):
    """Static camera: the per-pixel spread over frames is noise_px z^2 / (f b) (the disparity model)."""
    for seed in range(40):
        ans = make_mystery_sequence(tmp_path / f"s{seed}", seed=seed, frames=1, effect="incidence_dropout")
        if not ans["moving_camera"]:
            break
    else:
        pytest.fail("no static-camera seed among 40")
    ans = make_mystery_sequence(tmp_path / "static", seed=seed, frames=12, effect="incidence_dropout")
    Z = np.stack([_depth(tmp_path / "static", k) for k in range(12)])
    ok = (Z > 0).all(axis=0)
    zbar = Z.mean(axis=0)[ok]
    ratio = Z.std(axis=0, ddof=1)[ok] / (ans["raw_disparity"]["noise_px"] * zbar ** 2
                                        / (ans["camera"]["fx"] * ans["camera"]["baseline_m"]))
    far = zbar > 1.5                                    # far enough that the 0.2 mm PNG step is negligible
    assert far.sum() > 1000
    assert np.median(ratio[far]) == pytest.approx(1.0, abs=0.08)


def test_every_effect_writes_a_readable_sequence(tmp_path):
    from data_tools.sequence import SequenceReader
    for i, e in enumerate(MYSTERY_EFFECTS):
        make_mystery_sequence(tmp_path / e, seed=i, frames=1, effect=e)
        r = SequenceReader(tmp_path / e)
        assert len(r) == 1 and (r.read_depth(0) > 0).mean() > 0.5
