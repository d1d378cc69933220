"""The story demo (``realgap demo``, :mod:`app.demo`): its configuration, its page and its summary
from hand-made facts (fast), and the whole story on the ``quick`` preset (slow)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from app.demo.config import DEMO_PRESETS, DemoConfig
from data_tools.errors import ConfigError


def _png(path: Path) -> str:
    """A stand-in output file (the page only links or embeds it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"x")
    return str(path)


def _facts(root: Path, found: str = "depth_bias") -> dict:
    lab = {"hidden_effect": "depth_bias", "hidden_parameters": {"offset_px": -0.6}, "found_effect": found,
           "found_gain": 0.8, "evidence": "the residual grows with 1/z", "fitted_parameters": {"offset_px": -0.58},
           "gap_ideal": 2.0, "gap_base": 1.0, "gap_fitted": 0.2,
           "history": [{"label": "ideal depth", "gap": 2.0}, {"label": "base model (fitted)", "gap": 1.0},
                       {"label": "+ depth_bias (fitted)", "gap": 0.2}],
           "report": _png(root / "lab" / "report.html"), "diagnosis": _png(root / "lab" / "diagnosis.html")}
    explore = {"frames": 150, "report": _png(root / "explore" / "index.html"),
               "comparison_plot": _png(root / "explore" / "comparison.png"),
               "backends": {"icp": {"ok": True, "ate_rmse_m": 0.01, "ape_median_m": 0.008, "frames_per_second": 6.0},
                            "neural": {"ok": False, "error": "lost"}},
               "views": {"figure": _png(root / "explore" / "views.png")}, "screenshot": None,
               "screenshot_note": "viewer screenshot skipped: no EGL"}
    recog = {"scans": 12, "accuracy": 0.75, "accuracy_descriptor": 0.5, "rot_err_deg_median": 1.5,
             "rot_err_deg_median_before_icp": None, "trans_err_m_median": 0.002,
             "eval": _png(root / "recog" / "eval.json"), "figures": [_png(root / "recog" / "cdf_rotation.png")],
             "overlay": _png(root / "recog" / "overlay.png")}
    return {"lab": lab, "explore": explore, "recog": recog, "seconds": 123.4}


def test_config_validation_names_the_option():
    DemoConfig().validate()
    for preset in DEMO_PRESETS.values():
        preset.validate()
    with pytest.raises(ConfigError, match="novel_frame"):
        DemoConfig(room_frames=60, novel_frame=60).validate()
    with pytest.raises(ConfigError, match="mystery_frames"):
        DemoConfig(mystery_frames=1).validate()


def test_page_shows_every_part_and_links_resolve(tmp_path):
    from app.demo.page import write_index
    (tmp_path / "demo_config.json").write_text("{}")
    (tmp_path / "summary.json").write_text("{}")
    page = write_index(tmp_path, _facts(tmp_path)).read_text()
    for heading in ("1. The sensor lab", "2. Exploration", "3. Recognition"):
        assert heading in page
    assert "2.000" in page and "0.200" in page and "the lab found it" in page
    assert "failed" in page and "no EGL" in page          # a failed backend and a missing screenshot are said
    assert "- / 1.5 deg" in page                          # a missing number is a dash, not 'None'
    targets = re.findall(r"(?:src|href)='([^']+)'", page)
    assert len(targets) >= 10
    assert all((tmp_path / t).exists() for t in targets), [t for t in targets if not (tmp_path / t).exists()]


def test_page_says_when_the_lab_named_another_effect(tmp_path):
    from app.demo.page import write_index
    page = write_index(tmp_path, _facts(tmp_path, found="lens_distortion")).read_text()
    assert "named another effect" in page


def test_summary_is_five_to_ten_lines_naming_the_page(tmp_path):
    from app.demo.run import summary_lines
    lines = summary_lines(tmp_path, _facts(tmp_path))
    assert 5 <= len(lines) <= 10
    assert lines[-1].endswith("index.html for the whole story")
    assert "depth_bias (right)" in lines[1] and "2.000 -> 1.000 -> 0.200" in lines[1]
    assert "neural  failed: lost" in "\n".join(lines)


def test_turned_pose_turns_about_the_camera_down_axis():
    from app.demo.explore import turned_pose
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    R = turned_pose(T, 90.0)
    assert np.allclose(R[:3, 3], [1, 2, 3])
    assert np.allclose(R[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-12)    # forward turns to the right (+x)
    assert np.allclose(R[:3, :3] @ [0, 1, 0], [0, 1, 0])                 # down stays down


@pytest.mark.slow
def test_quick_demo_end_to_end_and_resume(tmp_path):
    """The whole story on the quick preset; a second run reuses every finished part."""
    import time
    from app.demo.run import run_demo
    out = tmp_path / "demo"
    facts = run_demo(out, DEMO_PRESETS["quick"], log=lambda s: None, progress=False)
    assert (out / "index.html").is_file() and (out / "summary.json").is_file()
    assert facts["lab"]["gap_fitted"] < facts["lab"]["gap_base"] < facts["lab"]["gap_ideal"]
    assert facts["explore"]["backends"]["icp"]["ok"]
    assert 0.0 <= facts["recog"]["accuracy"] <= 1.0
    assert json.loads((out / "summary.json").read_text())["header"]["kind"] == "demo"
    t = time.perf_counter()
    run_demo(out, DEMO_PRESETS["quick"], log=lambda s: None, progress=False)
    assert time.perf_counter() - t < 30
