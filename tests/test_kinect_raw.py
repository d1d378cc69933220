"""``data convert-kinect-raw``: hand-made raw captures (16-bit PGMs of known disparity) and a
Herrera-style OpenCV-YAML calibration with known numbers; the depth follows z = 1 / (c0 + c1 d)
exactly, the distortion correction d + beta exp(a0 - a1 d) only with --undistort-disparity, and
bad files are one-line errors."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import main
from data_tools.kinect_raw import disparity_to_depth, read_kinect_calibration
from data_tools.sequence import SequenceReader

W, H = 64, 48
C0, C1 = 3.3309, -0.0030711          # Herrera et al.'s typical Kinect v1 values: z(600) ~ 0.68 m
A0, A1 = 1.0, 0.005


def _calib(path: Path, beta: np.ndarray | None = None, **override) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    vals = {"dK": np.array([[75.0, 0, 31.5], [0, 75.0, 23.5], [0, 0, 1]]),
            "dkc": np.array([[0.01, -0.02, 0.0, 0.0, 0.0]]), "dc": np.array([[C0, C1]]),
            "dc_alpha": np.array([[A0, A1]])}
    vals.update(override)
    for k, v in vals.items():
        if v is not None:
            fs.write(k, v)
    if beta is not None:
        fs.write("dc_beta", beta)
    fs.release()
    return path


@pytest.fixture
def capture(tmp_path, request):
    colour_all = getattr(request, "param", True)
    src = tmp_path / "raw"
    src.mkdir()
    rng = np.random.default_rng(0)
    for n in (3, 4, 7):
        d = np.full((H, W), 600 + n, np.uint16)
        d[:5, :5] = 2047                                  # no measurement
        cv2.imwrite(str(src / f"{n:04d}-d.pgm"), d)
        if n != 7 or colour_all:
            cv2.imwrite(str(src / f"{n:04d}-c.ppm"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    beta = np.tile(np.linspace(-2.0, 2.0, W), (H, 1))       # a disparity distortion ramp, disparity units
    return src, _calib(tmp_path / "calib.yml", beta), beta


def test_depth_from_disparity_by_hand(capture):
    _, calib_path, beta = capture
    c = read_kinect_calibration(calib_path)
    assert np.allclose(c.K[0], [75, 0, 31.5]) and c.dc == (C0, C1) and c.beta.shape == (H, W)
    raw = np.array([[600, 2047], [800, 0]], np.uint16)
    c.beta = np.array([[1.0, 1.0], [2.0, 0.0]])
    z = disparity_to_depth(raw, c)
    assert z[0, 0] == pytest.approx(1 / (C0 + C1 * 600), rel=1e-6) and z[0, 1] == 0.0
    assert z[1, 0] == pytest.approx(1 / (C0 + C1 * 800), rel=1e-6)
    zu = disparity_to_depth(raw, c, undistort=True)
    d_u = 600 + 1.0 * np.exp(A0 - A1 * 600)
    assert zu[0, 0] == pytest.approx(1 / (C0 + C1 * d_u), rel=1e-6)


def test_convert_writes_tum_layout_and_resumes(capture, tmp_path, capsys):
    src, calib, beta = capture
    out = tmp_path / "seq"
    assert main(["data", "convert-kinect-raw", str(src), "--out", str(out), "--calib", str(calib),
                 "--no-progress"]) == 0
    seq = SequenceReader(out)
    assert len(seq) == 3 and not seq.has_groundtruth
    np.testing.assert_allclose(seq.timestamps, [3 / 30, 4 / 30, 7 / 30], atol=1e-6)
    cam = json.loads((out / "camera.json").read_text())
    assert cam["fx"] == 75.0 and cam["depth_scale"] == 5000.0 and cam["sensor"]["model"] == "kinect_v1"
    assert cam["distortion"][:2] == [0.01, -0.02] and cam["sensor"]["raw_disparity"]["undistorted"] is False
    f = seq[1]
    expect = 1 / (C0 + C1 * 604)
    assert np.abs(f.depth[10:, 10:] - expect).max() < 1e-4          # 0.2 mm quantisation
    assert (f.depth[:5, :5] == 0).all()
    assert f.rgb is not None and f.rgb.shape == (H, W, 3)
    # undistorted: depth follows the corrected disparity, which varies along u
    out2 = tmp_path / "seq_u"
    assert main(["data", "convert-kinect-raw", str(src), "--out", str(out2), "--calib", str(calib),
                 "--undistort-disparity", "--no-progress"]) == 0
    du = SequenceReader(out2)[1].depth
    d_u = 604 + beta[20] * np.exp(A0 - A1 * 604)
    np.testing.assert_allclose(du[20], 1 / (C0 + C1 * d_u), atol=1e-4)
    # a finished conversion is an error without --overwrite; an unfinished one continues
    capsys.readouterr()
    assert main(["data", "convert-kinect-raw", str(src), "--out", str(out), "--calib", str(calib)]) == 1
    assert "--overwrite" in capsys.readouterr().err
    (out / "convert.json").unlink()
    lines = (out / "depth.txt").read_text().splitlines()
    (out / "depth.txt").write_text("\n".join(lines[:-1]) + "\n")   # as if killed before the last frame
    assert main(["data", "convert-kinect-raw", str(src), "--out", str(out), "--calib", str(calib),
                 "--no-progress"]) == 0
    assert len(SequenceReader(out)) == 3 and "resumed after 2" in capsys.readouterr().out


@pytest.mark.parametrize("case, words", [
    ("depth in mm", ["values up to", "11-bit"]),
    ("8-bit", ["16-bit"]),
    ("no dc", ["'dc'"]),
    ("beta size", ["dc_beta"]),
    ("not yaml", ["calib.yml"]),
    ("no frames", ["NNNN-d.pgm"]),
])
def test_bad_input_is_one_line(capture, tmp_path, capsys, case, words):
    src, calib, beta = capture
    if case == "depth in mm":
        cv2.imwrite(str(src / "0004-d.pgm"), np.full((H, W), 3000, np.uint16))
    elif case == "8-bit":
        cv2.imwrite(str(src / "0003-d.pgm"), np.full((H, W), 100, np.uint8))
    elif case == "no dc":
        calib = _calib(tmp_path / "calib.yml", beta, dc=None)
    elif case == "beta size":
        calib = _calib(tmp_path / "calib.yml", beta[:10])
    elif case == "not yaml":
        calib.write_text("this is not yaml: [")
    else:
        for f in src.iterdir():
            f.unlink()
    capsys.readouterr()
    assert main(["data", "convert-kinect-raw", str(src), "--out", str(tmp_path / "o"), "--calib", str(calib),
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("realgap: error:") and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)


@pytest.mark.parametrize("capture", [False], indirect=True)
def test_partial_colour_is_left_out_with_a_warning(capture, tmp_path, capsys):
    src, calib, _ = capture                      # frame 7 has no colour image
    assert main(["data", "convert-kinect-raw", str(src), "--out", str(tmp_path / "s"), "--calib", str(calib),
                 "--no-progress"]) == 0
    assert "1 of 3 frames have no colour" in capsys.readouterr().err
    seq = SequenceReader(tmp_path / "s")
    assert len(seq) == 3 and seq[0].rgb is None


def test_destination_positional_or_out(capture, tmp_path, capsys):
    # the form `convert-kinect-raw SRC DST --calib C` and the --out form write the same
    src, calib, _ = capture
    assert main(["data", "convert-kinect-raw", str(src), str(tmp_path / "a"), "--calib", str(calib),
                 "--no-progress"]) == 0
    assert main(["data", "convert-kinect-raw", str(src), "--out", str(tmp_path / "b"), "--calib", str(calib),
                 "--no-progress"]) == 0
    for name in ("depth.txt", "camera.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    capsys.readouterr()
    assert main(["data", "convert-kinect-raw", str(src), str(tmp_path / "c"), "--out", str(tmp_path / "d"),
                 "--calib", str(calib)]) == 1
    err = capsys.readouterr().err
    assert "two destinations" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists() and not (tmp_path / "d").exists()
    assert main(["data", "convert-kinect-raw", str(src), "--calib", str(calib)]) == 1
    assert "no destination" in capsys.readouterr().err
