"""``realgap synth views`` through the real entry point: files, labels, limit/resume, bad input."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from data_tools.sequence import read_depth_png

REPO = Path(__file__).resolve().parents[1]
CROP = ["--width", "160", "--height", "120"]   # centred crop of the Kinect v1 image: same optics, fast


def _run(*args):
    return subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=300)


@pytest.fixture(scope="module")
def box_ply(tmp_path_factory):
    import trimesh
    p = tmp_path_factory.mktemp("mesh") / "box.ply"
    trimesh.creation.box(extents=(0.12, 0.08, 0.10)).export(p)
    return p


def test_views_cli_writes_labels_and_resumes(box_ply, tmp_path):
    out = tmp_path / "views"
    args = ["synth", "views", "--model", str(box_ply), "--sensor", "kinect_v1", "--out", str(out),
            "--subdivisions", "0", "--roll-angles=0,30", "--distance", "0.8", "--clutter", "2", "--seed", "3", *CROP]
    r = _run(*args, "--limit", "3")
    assert r.returncode == 0, r.stderr
    assert "first 3 of 8" in r.stdout
    recs = [json.loads(line) for line in (out / "views.jsonl").read_text().splitlines()]
    assert [x["index"] for x in recs] == [0, 1, 2]
    cfg = json.loads((out / "views_config.json").read_text())
    assert cfg["inplane_deg"] == [0.0, 30.0] and cfg["clutter"] == 2 and cfg["distance_m"] == 0.8
    assert cfg["model_path"] == str(box_ply.resolve()) and cfg["model_scale"] == 1.0
    assert json.loads((out / "sensor_config.json").read_text())["preset"]["width"] == 160
    # resume without the limit adds the rest; the first views are kept, not re-rendered
    first = (out / "depth" / "000000.png").stat().st_mtime_ns
    assert main(args + ["--resume"]) == 0
    labels = json.loads((out / "labels.json").read_text())
    assert labels["object"] == "box" and [v["index"] for v in labels["views"]] == list(range(8))
    assert (out / "depth" / "000000.png").stat().st_mtime_ns == first
    # labels: the object-to-camera pose puts the box centre on the optical axis at 0.8 m, and the
    # ideal depth under the object mask lies on the box surface
    import cv2
    intr = None
    from data_tools.camera import read_camera_json
    from data_tools.geometry import unproject
    intr = read_camera_json(out / "camera.json").intrinsics
    for v in labels["views"][:4]:
        T = np.asarray(v["pose_obj_to_cam"])
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        ideal = read_depth_png(out / v["ideal_depth"], 5000.0)
        mask = cv2.imread(str(out / v["mask"]), cv2.IMREAD_UNCHANGED) > 0
        pts = unproject(ideal, intr)[mask]
        obj = (pts - T[:3, 3]) @ T[:3, :3]
        assert np.all(np.abs(obj) <= np.array([0.06, 0.04, 0.05]) + 2e-3)
        measured = read_depth_png(out / v["depth"], 5000.0)
        assert (measured[mask] > 0).mean() > 0.5, "the sensor sees most of the object"
    # resuming with other settings would mix two data sets
    r = main(args[:-len(CROP)] + ["--resume", "--clutter", "0"] + CROP)
    assert r == 1


def test_views_cli_tless_model_in_millimetres(tmp_path, capsys):
    from conftest import shared_path
    ply = shared_path("tless_cad", "obj_01.ply")
    out = tmp_path / "tless"
    assert main(["synth", "views", "--model", str(ply), "--out", str(out), "--limit", "1", *CROP]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "78.7 m across" in err[0] and "--scale 0.001" in err[0] and str(ply) in err[0]
    assert main(["synth", "views", "--model", str(ply), "--scale", "0.001", "--out", str(out), "--limit", "2",
                 "--effects", "direct", *CROP]) == 0
    recs = json.loads((out / "labels.json").read_text())["views"]
    assert len(recs) == 2 and recs[0]["object"] == "obj_01" and recs[0]["visible_px"] > 200


def test_views_cli_bad_input_one_line(box_ply, tmp_path, capsys):
    r = _run("synth", "views", "--model", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "o"))
    assert r.returncode == 1 and "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "missing.ply" in lines[0] and "not found" in lines[0]

    def one_line_error(*args):
        rc = main(["synth", "views", *args])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 1 and len(err) == 1, err
        return err[0]

    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
    msg = one_line_error("--model", str(empty), "--out", str(tmp_path / "e"))
    assert "empty.ply" in msg
    msg = one_line_error("--model", str(box_ply), "--sensor", "kinect_v9", "--out", str(tmp_path / "s"))
    assert "kinect_v9" in msg and "kinect_v1" in msg
    msg = one_line_error("--model", str(box_ply), "--effects", "blurr", "--out", str(tmp_path / "s"))
    assert "blurr" in msg and "axial_noise" in msg
    msg = one_line_error("--model", str(box_ply), "--scale", "0.001", "--out", str(tmp_path / "s"))
    assert "too small" in msg and "0.175 mm" in msg and "already in metres" in msg
    msg = one_line_error("--model", str(box_ply), "--distance", "0.3", "--out", str(tmp_path / "s"))
    assert "minimum depth" in msg


def test_views_sensor_crop_keeps_the_json_motion_limits(tmp_path):
    """A sensor_config.json with --width/--height is cropped, every other field kept."""
    import argparse
    import dataclasses

    from app.commands.synth import _views_sensor
    from synth.sensor.config import MotionLimits, SensorConfig
    motion = MotionLimits(max_speed_m_s=0.7, max_angular_speed_rad_s=0.3)
    path = tmp_path / "sensor_config.json"
    dataclasses.replace(SensorConfig.build("kinect_v1", ["axial_noise"]), motion=motion).save(path)
    cfg = _views_sensor(argparse.Namespace(sensor=str(path), effects=None, width=320, height=240))
    assert cfg.motion == motion and cfg.preset.width == 320 and cfg.names() == ["axial_noise"]
