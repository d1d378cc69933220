"""Object-centred views for recognition: viewpoints, labels (poses), files, resume."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.errors import ConfigError, RealgapError
from data_tools.geometry import unproject
from data_tools.sequence import read_depth_png
from synth.sensor import get_preset
from synth.sensor.testscenes import box_mesh
from synth.sensor.views import hemisphere_viewpoints, icosphere_vertices, read_views, render_views

SMALL = get_preset("kinect_v1").cropped(200, 160)


def test_icosphere_counts_and_hemisphere():
    assert [len(icosphere_vertices(k)) for k in range(3)] == [12, 42, 162]
    v = hemisphere_viewpoints(2, min_elevation_deg=5)
    assert np.allclose(np.linalg.norm(v, axis=1), 1)
    assert np.all(v[:, 2] >= np.sin(np.radians(5)) - 1e-9)
    assert 60 < len(v) < 90
    assert len(np.unique(np.round(v, 6), axis=0)) == len(v)


@pytest.fixture(scope="module")
def views_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("views")
    model = box_mesh([0.3, -0.2, 1.0], [0.12, 0.08, 0.1], "cuboid")   # deliberately off-centre in its frame
    res = render_views(model, SMALL, out, subdivisions=0, inplane_deg=(0.0, 30.0), clutter=2, background=True,
                       progress=False, distance_m=0.9)
    return out, model, res


def test_views_files_and_labels(views_dir):
    out, model, res = views_dir
    recs = read_views(out)
    assert res.n_written == len(recs) == res.n_views == 2 * len(hemisphere_viewpoints(0))
    for name in ("camera.json", "sensor_config.json", "views_config.json", "labels.json"):
        assert (out / name).exists()
    import json
    assert json.loads((out / "labels.json").read_text())["views"] == recs
    r = recs[0]
    assert r["object"] == "cuboid" and np.asarray(r["pose_obj_to_cam"]).shape == (4, 4)
    depth = read_depth_png(out / r["depth"], 5000.0)
    assert depth.shape == (160, 200) and (depth > 0).any()


def test_view_poses_are_object_to_camera(views_dir):
    """Unprojected ideal depth of the object mask, moved to the object frame by the inverse of
    the label pose, lies on the model's box surface; the box centre projects to the image
    centre (the camera looks at it)."""
    import cv2
    out, model, _ = views_dir
    intr = SMALL.intrinsics
    lo, hi = model.bounds
    for r in read_views(out)[:6]:
        T = np.asarray(r["pose_obj_to_cam"])
        ideal = read_depth_png(out / r["ideal_depth"], 5000.0)
        mask = cv2.imread(str(out / r["mask"]), cv2.IMREAD_UNCHANGED) > 0
        assert mask.sum() > 100
        pts = unproject(ideal, intr)[mask]
        obj = (pts - T[:3, 3]) @ T[:3, :3]          # camera -> object frame
        assert np.all(obj >= lo - 2e-3) and np.all(obj <= hi + 2e-3)
        on_face = np.min(np.minimum(np.abs(obj - lo), np.abs(obj - hi)), axis=1)
        assert np.percentile(on_face, 99) < 2e-3
        c = T[:3, :3] @ ((lo + hi) / 2) + T[:3, 3]
        assert abs(intr.fx * c[0] / c[2] + intr.cx - intr.cx) < 1.0 and abs(intr.fy * c[1] / c[2]) < 1.0
        assert np.linalg.norm(c) == pytest.approx(0.9, abs=1e-6)


def test_inplane_rotation(views_dir):
    out, _, _ = views_dir
    recs = read_views(out)
    a, b = recs[0], recs[1]                # same viewpoint, in-plane 0 and 30 degrees
    assert a["viewpoint"] == b["viewpoint"] and (a["inplane_deg"], b["inplane_deg"]) == (0.0, 30.0)
    Ra, Rb = np.asarray(a["pose_obj_to_cam"])[:3, :3], np.asarray(b["pose_obj_to_cam"])[:3, :3]
    Rrel = Rb @ Ra.T                       # rotation about the optical axis by -30 deg
    assert np.allclose(Rrel[2], [0, 0, 1], atol=1e-9)
    assert np.degrees(np.arctan2(Rrel[1, 0], Rrel[0, 0])) == pytest.approx(-30.0)


def test_resume_and_bad_options(views_dir, tmp_path):
    out, model, res = views_dir
    again = render_views(model, SMALL, out, subdivisions=0, inplane_deg=(0.0, 30.0), clutter=2, background=True,
                         progress=False, distance_m=0.9, resume=True)
    assert again.n_written == 0
    with pytest.raises(RealgapError, match="already holds views"):
        render_views(model, SMALL, out, subdivisions=0, progress=False)
    with pytest.raises(ConfigError, match="unknown option"):
        render_views(model, SMALL, tmp_path / "x", spin=3)
    with pytest.raises(ConfigError, match="minimum depth"):
        render_views(model, SMALL, tmp_path / "y", distance_m=0.3, progress=False)
