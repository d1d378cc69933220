"""``realgap view``: off-screen screenshots (exist, not blank, the trajectories in their colours),
scripted interaction (frames, the virtual camera, a lab effect switched off) updating the panes,
a movie, and one-line errors. Rendering is off-screen (EGL), as on a machine without a display.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from app.cli import main  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def offscreen_ok():
    from app.viewer.window import check_offscreen
    from data_tools.errors import RealgapError
    try:
        check_offscreen()
    except RealgapError as e:
        pytest.skip(str(e))


@pytest.fixture(scope="module")
def seq_and_run(tmp_path_factory):
    """A 24-frame simulated Kinect v1 sequence (the sensor's 640x480; the ideal one in seq/ideal) and an icp
    run on it."""
    root = tmp_path_factory.mktemp("view")
    assert main(["synth", "sequence", "--preset", "small", "--frames", "24", "--sensor", "kinect_v1",
                 "--out", str(root / "seq"), "--no-progress"]) == 0
    assert main(["slam", "run", str(root / "seq"), "--out", str(root / "icp"), "--no-progress"]) == 0
    return root


def _count_colour(img: np.ndarray, rgb, tol: int = 40) -> int:
    return int((np.abs(img[..., :3].astype(int) - np.asarray(rgb)).max(-1) < tol).sum())


def test_sequence_data_without_plotting(seq_and_run):
    from app.viewer.data import load_session
    s = load_session([str(seq_and_run / "icp")])                     # the run names its sequence
    assert len(s) == 24 and [r.name for r in s.runs] == ["icp"]
    r = s.runs[0]
    assert r.ape_m is not None and np.nanmax(r.ape_m) < 0.05          # a simulated room: cm-level drift
    assert np.allclose(r.aligned_positions[0], s.gt.positions[0], atol=1e-6)    # origin-aligned
    st = s.frame_state(3)["icp"]
    assert st["registered"] and not st["failed"] and st["ape_m"] is not None
    views = s.novel_views(s.pose(5))
    assert views["neural"] == "no neural run" and views["icp"].coverage > 0.5


def test_screenshot_shows_trajectories_and_panes(seq_and_run, offscreen_ok, tmp_path):
    out = tmp_path / "shot.png"
    r = subprocess.run([sys.executable, "-m", "app", "view", str(seq_and_run / "seq"), str(seq_and_run / "icp"),
                        "--screenshot", str(out), "--frame", "12", "--size", "1200x700"],
                       capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr
    import cv2
    img = cv2.imread(str(out))[..., ::-1]
    assert img.shape == (700, 1200, 3)
    assert img.std() > 20                                              # not blank
    from app.viewer.data import TRACK_COLOURS
    icp = tuple(int(255 * c) for c in TRACK_COLOURS["icp"])
    virtual = tuple(int(255 * c) for c in TRACK_COLOURS["virtual camera"])
    left = img[:, :600]                                                # the 3D pane
    assert _count_colour(left, icp) > 30, "icp trajectory/legend colour missing"
    assert _count_colour(left, virtual) > 10, "virtual camera frustum missing"
    for name, (y0, x0) in {"rgb": (0, 600), "depth": (0, 900), "novel view": (350, 600)}.items():
        pane = img[y0 + 40:y0 + 330, x0 + 10:x0 + 290]
        assert pane.std() > 10, f"{name} pane is blank"
    assert img[360:690, 910:1190].std() < 25                          # the neural pane holds only its message


def test_scripted_interaction_updates_panes(seq_and_run, offscreen_ok):
    from app.viewer.data import load_session
    from app.viewer.window import Viewer
    v = Viewer(load_session([str(seq_and_run / "seq"), str(seq_and_run / "icp")]), off_screen=True,
               window_size=(800, 450))
    rgb0, depth0 = v.pane_images["rgb"].copy(), v.pane_images["depth"].copy()
    v.set_frame(10)
    assert v.frame == 10
    grown = len(v._cloud_frames)
    assert grown >= 2 and v._cloud_frames == list(range(0, 11, v._cloud_stride))     # the map grew
    v.set_frame(2)
    assert v._cloud_frames == list(range(0, 3, v._cloud_stride))                      # and shrinks going back
    v.set_frame(10)
    assert not np.array_equal(v.pane_images["rgb"], rgb0)
    assert not np.array_equal(np.nan_to_num(v.pane_images["depth"]), np.nan_to_num(depth0))
    novel0 = v.pane_images["novel_0"].copy()
    v.set_virtual_camera(v.s.pose(20))
    assert not np.array_equal(v.pane_images["novel_0"], novel0)
    assert v.pane_images["novel_1"] is None                           # "no neural run"
    before = v.s.virtual_pose.copy()
    v.move_virtual(forward=1)
    assert np.linalg.norm(v.s.virtual_pose[:3, 3] - before[:3, 3]) == pytest.approx(0.1)
    target = v.s.pose(12)[:3, 3] + v.s.pose(12)[:3, 2]          # a point 1 m in front of frame 12's camera
    v.look_at_point(target)                                          # what a right-click on the 3D pane does
    T = v.s.virtual_pose
    assert np.linalg.norm(T[:3, 3] - target) == pytest.approx(1.5)
    assert np.allclose(T[:3, 2], (target - T[:3, 3]) / 1.5, atol=1e-9)
    v.toggle_help()
    img = v.p.screenshot(return_img=True)
    assert _count_colour(img, (255, 221, 102), 30) > 20              # the help overlay is drawn
    v.p.close()


def test_a_second_sequence_is_shown_as_the_simulation(seq_and_run, offscreen_ok, tmp_path, capsys):
    """``realgap view SEQ SIMSEQ``: the second sequence's depth at the same timestamp and the
    residual (mm) beside the measured depth; a second sequence of other frames is a one-line error."""
    from app.viewer.data import load_session
    from app.viewer.window import Viewer
    seq, sim = seq_and_run / "seq" / "ideal", seq_and_run / "seq"
    v = Viewer(load_session([str(seq), str(sim)]), off_screen=True, window_size=(900, 450))
    v.set_frame(7)
    meas, simd, res = v.pane_images["depth"], v.pane_images["simulated"], v.pane_images["residual"]
    from data_tools.sequence import SequenceReader
    expect = SequenceReader(sim).read_depth(7)
    np.testing.assert_array_equal(np.nan_to_num(simd), expect)
    both = np.isfinite(meas) & np.isfinite(simd)
    np.testing.assert_allclose(res[both], (meas[both] - simd[both]) * 1000.0, rtol=1e-5, atol=1e-3)  # as report.html
    assert 0 < np.nanmedian(np.abs(res)) < 50                       # sensor noise: millimetres
    v.p.close()
    other = tmp_path / "other"
    assert main(["synth", "sequence", "--frames", "3", "--fps", "7", "--out", str(other),
                 "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["view", str(seq), str(other), "--screenshot", str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err.strip()
    assert "shares no timestamp" in err and "\n" not in err and not (tmp_path / "x.png").exists()


def test_lab_mode_effect_toggle_resimulates(seq_and_run, offscreen_ok, tmp_path):
    lab = tmp_path / "lab"
    assert main(["sensor", "compare", str(seq_and_run / "seq"), "--effects", "axial_noise,projector_shadow",
                 "--out", str(lab), "--compare-preset", "fast", "--spread-frames", "3", "--report-frames", "1",
                 "--no-progress"]) == 0
    from app.viewer.data import load_session
    from app.viewer.window import Viewer
    v = Viewer(load_session([], lab=str(lab)), off_screen=True, window_size=(900, 500))
    sim0 = np.nan_to_num(v.pane_images["simulated"]).copy()
    k = v.s.effects.index("projector_shadow")
    v.toggle_effect(k)
    assert v.s.enabled["projector_shadow"] is False
    sim1 = np.nan_to_num(v.pane_images["simulated"])
    assert (sim1 > 0).sum() > (sim0 > 0).sum()                       # shadows switched off: fewer holes
    assert np.isfinite(v.pane_images["residual"]).any()
    v.p.close()


@pytest.mark.slow  # ~60 s of off-screen rendering; the screenshot path is in the default run
def test_movie(seq_and_run, offscreen_ok, tmp_path):
    gif = tmp_path / "fly.gif"
    assert main(["view", str(seq_and_run / "icp"), "--movie", str(gif), "--size", "400x250"]) == 0
    from PIL import Image
    im = Image.open(gif)
    assert im.n_frames >= 10


def test_bad_input(seq_and_run, offscreen_ok, tmp_path, capsys):
    gif = tmp_path / "fly.gif"
    gif.write_bytes(b"GIF89a")       # an existing output
    # one-line errors, nothing written
    for argv, words in ((["view", str(seq_and_run / "icp"), "--screenshot", str(gif)], ["exists", "--overwrite"]),
                        (["view", str(tmp_path), "--screenshot", str(tmp_path / "x.png")], ["neither a sequence"]),
                        (["view", str(seq_and_run / "icp"), "--screenshot", str(tmp_path / "y.png"), "--frame", "99"],
                         ["--frame"]),
                        (["view", "--lab", str(seq_and_run / "seq"), "--screenshot", str(tmp_path / "z.png")],
                         ["lab_config.json"])):
        capsys.readouterr()
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "Traceback" not in err, err
        for w in words:
            assert w in err, (w, err)
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "y.png").exists()
    run = tmp_path / "norun"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"sequence": str(seq_and_run / "seq"), "config": {}}))
    (run / "stats.json").write_text("{}")
    capsys.readouterr()
    assert main(["view", str(run), "--screenshot", str(tmp_path / "w.png")]) == 1
    assert "trajectory.txt" in capsys.readouterr().err


def test_off_screen_run_is_quiet_and_counts_frames_as_the_flag_does(seq_and_run, offscreen_ok, tmp_path, capfd):
    """No VTK "bad X server connection" line on an off-screen run; ``--frame 3`` is shown as frame 3."""
    png = tmp_path / "s.png"
    assert main(["view", str(seq_and_run / "icp"), "--screenshot", str(png), "--frame", "3", "--size", "400x250"]) == 0
    err = capfd.readouterr().err
    assert "X server" not in err and "WARN" not in err, err
    from app.viewer.data import load_session
    from app.viewer.window import Viewer
    v = Viewer(load_session([str(seq_and_run / "icp")]), off_screen=True, window_size=(400, 250))
    v.set_frame(3)
    assert v._status().startswith(f"frame 3 (0-{len(v.s) - 1})")
    v.p.close()
