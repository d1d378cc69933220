"""recog: loss values on hand-made triplets, the dynamic margin, symmetry detection and
symmetry-aware errors, patch geometry round trips, database save -> load, ICP refinement, a
short 2-object training run that separates the classes, and one-line errors for bad input.

The objects are tiny hand-made meshes (a box, a cylinder, an L-bracket) so the tests need no
shared data and run in seconds; T-LESS numbers are in benchmarks/bench_recog.py.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from app.cli import main  # noqa: E402
from data_tools.camera import Intrinsics  # noqa: E402
from recog.database import DescriptorDB, ExactIndex  # noqa: E402
from recog.loss import dynamic_margin, pair_loss, triplet_loss  # noqa: E402
from recog.patches import PatchConfig, extract_patch, from_ray_frame, ray_rotation, to_ray_frame  # noqa: E402
from recog.symmetry import _rot, detect_symmetry, rotation_error_deg, sym_angles  # noqa: E402

INTR = Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5)


def _mesh(tm, name="m"):
    from data_tools.mesh import TriMesh
    return TriMesh(np.asarray(tm.vertices), np.asarray(tm.faces), name)


def _l_bracket():
    import trimesh
    a = trimesh.creation.box(extents=(0.10, 0.03, 0.02))
    b = trimesh.creation.box(extents=(0.03, 0.06, 0.02))
    b.apply_translation((0.035, 0.045, 0.0))
    c = trimesh.creation.box(extents=(0.03, 0.03, 0.05))
    c.apply_translation((-0.035, 0.0, 0.035))
    return trimesh.util.concatenate([a, b, c])


@pytest.fixture(scope="module")
def model_files(tmp_path_factory):
    import trimesh
    d = tmp_path_factory.mktemp("models")
    trimesh.creation.box(extents=(0.10, 0.06, 0.05)).export(d / "box.ply")
    _l_bracket().export(d / "bracket.ply")
    return d


# ----------------------------------------------------------------------------- loss

def test_triplet_and_pair_loss_by_hand():
    fb = torch.tensor([[0.0, 0.0], [0.0, 0.0]])
    fp = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    fn = torch.tensor([[2.0, 0.0], [1.0, 0.0]])
    m = torch.tensor([0.5, 0.5])
    # d_pos = 1; d_neg = 4 -> 1 - 4 / 1.5 < 0 -> 0; d_neg = 1 -> 1 - 1 / 1.5 = 1/3
    np.testing.assert_allclose(triplet_loss(fb, fp, fn, m).numpy(), [0.0, 1.0 / 3.0], atol=1e-7)
    np.testing.assert_allclose(pair_loss(fb, torch.tensor([[0.0, 2.0], [3.0, 4.0]])).numpy(), [4.0, 25.0])


def test_dynamic_margin_within_and_across_objects():
    same = torch.tensor([True, False, True])
    ang = torch.tensor([0.3, 0.3, math.pi])
    np.testing.assert_allclose(dynamic_margin(same, ang, 4.0).numpy(), [0.3, 4.0, math.pi], rtol=1e-6)
    with pytest.raises(ValueError):
        dynamic_margin(same, ang, 3.0)            # must exceed pi
    # the margin of a same-object negative is 2 arccos(|q_b . q_-|) = the rotation angle between them
    from scipy.spatial.transform import Rotation
    qa, qb = Rotation.random(2, random_state=3).as_quat()
    Ra, Rb = Rotation.from_quat([qa, qb]).as_matrix()
    assert 2 * math.acos(abs(float(qa @ qb))) == pytest.approx(float(sym_angles(Ra, Rb)[0, 0]), abs=1e-7)


# ----------------------------------------------------------------------------- symmetry

def test_detect_symmetry_of_simple_shapes():
    import trimesh
    cyl = detect_symmetry(_mesh(trimesh.creation.cylinder(radius=0.03, height=0.08, sections=64)))
    assert cyl["order"] == 0 and np.allclose(np.abs(cyl["axis"]), [0, 0, 1], atol=1e-6)
    box = detect_symmetry(_mesh(trimesh.creation.box(extents=(0.10, 0.06, 0.04))))
    assert box == {"axis": [0.0, 0.0, 1.0], "order": 2}       # a half turn about the up axis
    assert detect_symmetry(_mesh(_l_bracket()))["axis"] is None


def test_symmetry_aware_errors_against_brute_force():
    from scipy.spatial.transform import Rotation
    A = Rotation.random(4, random_state=1).as_matrix()
    B = Rotation.random(3, random_state=2).as_matrix()
    sym = {"axis": [0.0, 0.0, 1.0], "order": 0}
    spins = np.linspace(0, 2 * np.pi, 2001)
    brute = np.array([[min(np.arccos(np.clip((np.trace((a @ _rot([0, 0, 1], s)).T @ b) - 1) / 2, -1, 1))
                           for s in spins) for b in B] for a in A])
    np.testing.assert_allclose(sym_angles(A, B, sym), brute, atol=2e-3)
    R = A[0]
    half = R @ _rot([0, 0, 1], math.pi)
    assert rotation_error_deg(half, R) == pytest.approx(180.0, abs=1e-6)
    assert rotation_error_deg(half, R, {"axis": [0, 0, 1.0], "order": 2}) == pytest.approx(0.0, abs=1e-6)
    tilt = R @ _rot([1, 0, 0], math.radians(7))
    assert rotation_error_deg(tilt, R, sym) == pytest.approx(7.0, abs=1e-6)


# ----------------------------------------------------------------------------- patches

def test_patch_of_a_wall_and_invalid_pixels():
    depth = np.full((480, 640), 0.8, np.float32)
    depth[230:250, 310:330] = 0.0                   # a hole in the window's centre
    # window centred on the principal point: the virtual camera is the real one, the wall is at z_ref
    p = extract_patch(depth, INTR, (300, 220, 340, 260), PatchConfig(size=32, crop_m=0.2))
    assert p.z_ref_m == pytest.approx(0.8, abs=1e-6) and np.allclose(p.R_ray, np.eye(3))
    assert p.image[15, 15] == 1.0                   # holes read as "far"
    valid = p.image < 1.0
    assert 0.9 < valid.mean() < 1.0 and np.abs(p.image[valid]).max() < 1e-6
    # off-centre: a wall facing the ray through the window's centre is fronto-parallel to the
    # virtual camera: a flat patch at z_ref = its distance along that ray
    u, v = np.meshgrid(np.arange(640), np.arange(480))
    uc, vc = (560 + 599) / 2, (200 + 239) / 2
    n = np.array([(uc - INTR.cx) / INTR.fx, (vc - INTR.cy) / INTR.fy, 1.0])
    n /= np.linalg.norm(n)
    wall = 0.8 / (n[0] * (u - INTR.cx) / INTR.fx + n[1] * (v - INTR.cy) / INTR.fy + n[2])
    q = extract_patch(wall.astype(np.float64), INTR, (560, 200, 600, 240), PatchConfig(size=32, crop_m=0.2))
    assert q.z_ref_m == pytest.approx(0.8, abs=1e-6)
    inside = q.image < 1.0                       # the patch reaches past the image's right edge: +1 there
    assert 0.5 < inside.mean() < 1.0 and np.abs(q.image[inside]).max() < 1e-5


def test_ray_rotation_and_pose_round_trip():
    R = ray_rotation(INTR, 500.0, 100.0)
    ray = np.array([(500.0 - INTR.cx) / INTR.fx, (100.0 - INTR.cy) / INTR.fy, 1.0])
    np.testing.assert_allclose(R @ [0, 0, 1.0], ray / np.linalg.norm(ray), atol=1e-12)
    assert np.allclose(R.T @ R, np.eye(3))
    depth = np.full((480, 640), 0.7, np.float32)
    p = extract_patch(depth, INTR, (480, 80, 520, 120), PatchConfig())
    from scipy.spatial.transform import Rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=5).as_matrix()
    T[:3, 3] = [0.2, -0.1, 0.72]
    R_local, off = to_ray_frame(T, p)
    np.testing.assert_allclose(from_ray_frame(R_local, off, p), T, atol=1e-12)


def test_patches_are_distance_invariant():
    """The same object at two distances gives nearly the same patch (metric crop)."""
    from data_tools.scene_spec import Material, SceneSpec
    from synth.render.ideal import IdealRenderer
    import trimesh
    m = _mesh(_l_bracket(), "obj")
    m.material = "obj"
    r = IdealRenderer(SceneSpec([m], {"obj": Material(0.5, 0.0)}))
    imgs = []
    for z in (0.5, 0.8):
        T = np.eye(4)
        T[:3, 3] = [0, 0, -z]                     # camera looking along +z at the object
        res = r.render(T, INTR, with_rgb=False)
        from recog.patches import bbox_from_mask
        imgs.append(extract_patch(res.depth, INTR, bbox_from_mask(res.hit), PatchConfig(crop_m=0.15)).image)
    assert np.mean(np.abs(imgs[0] - imgs[1]) > 0.2) < 0.05


# ----------------------------------------------------------------------------- database

def test_exact_index_is_exact():
    rng = np.random.default_rng(0)
    x, q = rng.normal(size=(200, 8)), rng.normal(size=(5, 8))
    d, i = ExactIndex(x).search(q, 3)
    brute = ((q[:, None] - x[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(i, np.argsort(brute, 1)[:, :3])
    np.testing.assert_allclose(d, np.sort(brute, 1)[:, :3], rtol=1e-5)


def test_faiss_index_agrees_with_the_exact_one():
    """The ANN index behind the same interface (HNSW from faiss-cpu, the dev extra): on 20 000
    clustered 64-d descriptors its nearest neighbour is the exact one for >= 98 % of 200 queries,
    with the same squared distance; a database with ``index_name="faiss"`` votes as the exact one."""
    pytest.importorskip("faiss", reason="faiss-cpu not installed (pip install -e '.[ann]')")
    from recog.database import FaissIndex, make_index
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(40, 64)).astype(np.float32)
    lab = rng.integers(0, 40, 20000)
    x = (centres[lab] + 0.3 * rng.normal(size=(20000, 64))).astype(np.float32)
    q = (centres[rng.integers(0, 40, 200)] + 0.3 * rng.normal(size=(200, 64))).astype(np.float32)
    ann = make_index("faiss", x)
    assert isinstance(ann, FaissIndex)
    da, ia = ann.search(q, 5)
    de, ie = ExactIndex(x).search(q, 5)
    same = ia[:, 0] == ie[:, 0]
    assert same.mean() >= 0.98, same.mean()
    np.testing.assert_allclose(da[same, 0], de[same, 0], rtol=1e-4, atol=1e-4)
    R, off = np.tile(np.eye(3), (len(x), 1, 1)), np.zeros((len(x), 3))
    votes = [DescriptorDB(x, lab % 3, R, off, np.arange(len(x)), index_name=n).query(q[:50], k=5)
             for n in ("exact", "faiss")]
    agree = np.mean([a.object_index == b.object_index for a, b in zip(*votes)])
    assert agree >= 0.96, agree


def test_database_vote_and_round_trip(tmp_path):
    desc = np.array([[0, 0], [0.1, 0], [5, 5], [5.1, 5]], np.float32)
    db = DescriptorDB(desc, np.array([0, 0, 1, 1]), np.tile(np.eye(3), (4, 1, 1)), np.zeros((4, 3)), np.arange(4))
    m = db.query(np.array([[4.9, 5.0]]), k=3)[0]
    assert m.object_index == 1 and m.nearest == 2
    db.save(tmp_path / "db.npz")
    back = DescriptorDB.load(tmp_path / "db.npz")
    assert [(x.object_index, x.nearest) for x in back.query(desc, 2)] == [(x.object_index, x.nearest)
                                                                         for x in db.query(desc, 2)]


# ----------------------------------------------------------------------------- ICP

def test_icp_reduces_a_perturbed_pose_error(model_files):
    from data_tools.scene_spec import Material, SceneSpec
    from recog.objects import load_objects
    from recog.refine import refine_pose
    from synth.render.ideal import IdealRenderer
    obj = load_objects(str(model_files / "bracket.ply"))[0]
    T_true = np.eye(4)
    T_true[:3, :3] = _rot([1, 0.3, 0.2], 2.3)
    T_true[:3, 3] = [0.03, -0.02, 0.6]
    m = obj.meshes[0].transformed(T_true)
    m.material = "object"
    res = IdealRenderer(SceneSpec([m], obj.materials)).render(np.eye(4), INTR, with_rgb=False)
    from recog.patches import bbox_from_mask
    box = bbox_from_mask(res.hit)
    T0 = T_true.copy()
    T0[:3, :3] = _rot([0.2, 1, 0], math.radians(6)) @ T_true[:3, :3]
    T0[:3, 3] += [0.004, -0.003, 0.005]
    r = refine_pose(obj, T0, res.depth, INTR, box)
    e0 = rotation_error_deg(T0, T_true), np.linalg.norm(T0[:3, 3] - T_true[:3, 3])
    e1 = rotation_error_deg(r.pose, T_true), np.linalg.norm(r.pose[:3, 3] - T_true[:3, 3])
    assert r.accepted and e1[0] < 0.25 * e0[0] and e1[1] < 0.25 * e0[1], (e0, e1)


# ----------------------------------------------------------------------------- training + CLI

@pytest.fixture(scope="module")
def trained(model_files, tmp_path_factory):
    """A 2-object recogniser (box vs bracket) trained briefly on clean views, and a test set."""
    root = tmp_path_factory.mktemp("recog")
    objs = f"{model_files / 'box.ply'},{model_files / 'bracket.ply'}"
    assert main(["recog", "train", "--objects", objs, "--variant", "gaussian", "--out", str(root / "m"),
                 "--subdivisions", "0", "--iterations", "80", "--batch", "16", "--workers", "1",
                 "--no-progress"]) == 0
    assert main(["recog", "testset", "--objects", objs, "--out", str(root / "t"), "--per-object", "4",
                 "--sensor", "kinect_v1", "--effects", "axial_noise", "--no-progress"]) == 0
    return root


def test_short_training_separates_the_classes(trained):
    from recog.model import Recogniser
    m = Recogniser.load(trained / "m")
    assert m.names == ["box", "bracket"]
    assert m.info["self_check"]["same_object"] >= 0.95
    # leave-one-view-out nearest neighbour (the view's own other draw excluded): the same object
    d, o, v = m.db.descriptors, m.db.obj, m.db.view
    dist = np.linalg.norm(d[:, None] - d[None], axis=-1)
    dist[(o[:, None] == o[None]) & (v[:, None] == v[None])] = np.inf
    trained_acc = np.mean(o[np.argmin(dist, 1)] == o)
    assert trained_acc >= 0.9, trained_acc
    steps = m.info["train_log"]
    assert len(steps) >= 2 and steps[-1]["loss"] < steps[0]["loss"], steps
    assert m.objects[0]["symmetry"]["order"] == 2 and m.objects[1]["symmetry"]["axis"] is None


def test_eval_and_predict_cli(trained, capsys):
    out = trained / "e"
    assert main(["recog", "eval", str(trained / "m"), str(trained / "t"), "--out", str(out), "--no-progress"]) == 0
    r = json.loads((out / "eval.json").read_text())
    assert r["header"]["kind"] == "recog.eval" and r["n_scans"] == 8
    assert r["accuracy"] >= 0.75
    assert {"median", "mean", "acc_at_10", "acc_at_20", "acc_at_40"} <= set(r["rot_err_deg"])
    assert set(r["before_icp"]) >= {"rot_err_deg", "rot_err_deg_plain", "trans_err_m"}
    for f in ("figures/cdf_rotation.png", "figures/cdf_translation.png", "figures/confusion.png", "predictions.jsonl"):
        assert (out / f).is_file(), f
    lab = json.loads((trained / "t" / "labels.json").read_text())[0]
    capsys.readouterr()
    assert main(["recog", "predict", str(trained / "m"), str(trained / "t" / lab["file"]), "--bbox",
                 ",".join(map(str, lab["bbox"])), "--json"]) == 0
    pred = json.loads(capsys.readouterr().out)
    assert pred["object"] in ("box", "bracket") and np.asarray(pred["pose"]).shape == (4, 4)


def test_eval_max_frames_is_the_first_n_scans(trained):
    """``--max-frames N`` (the first N, as in every command: tests/test_max_frames.py): the first N scans of
    labels.json, in order."""
    out = trained / "e_first"
    assert main(["recog", "eval", str(trained / "m"), str(trained / "t"), "--out", str(out), "--no-icp",
                 "--max-frames", "3", "--no-progress"]) == 0
    rows = [json.loads(ln) for ln in (out / "predictions.jsonl").read_text().splitlines() if ln.strip()]
    labels = json.loads((trained / "t" / "labels.json").read_text())
    assert [r["file"] for r in rows] == [lab["file"] for lab in labels[:3]]
    assert json.loads((out / "eval.json").read_text())["n_scans"] == 3


def test_eval_json_prints_and_out_writes_the_file(trained, capsys):
    """One dialect: ``--json`` prints eval.json's content on stdout (a switch, as everywhere); the file is
    written by ``--out DIR`` (DIR/eval.json), and a finished DIR is a one-line error without --overwrite.
    ``--json OUT`` (issue #18's spelling) is a one-line usage error naming OUT."""
    out = trained / "eval_dir"
    argv = ["recog", "eval", str(trained / "m"), str(trained / "t"), "--out", str(out), "--json", "--no-progress"]
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    r = json.loads((out / "eval.json").read_text())
    assert r["header"]["kind"] == "recog.eval" and r["n_scans"] == printed["n_scans"] == 8
    assert {"accuracy", "rot_err_deg", "rot_err_deg_plain", "trans_err_m", "before_icp", "confusion"} <= set(r)
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert main(argv + ["--overwrite"]) == 0
    capsys.readouterr()
    assert main(["recog", "eval", str(trained / "m"), str(trained / "t"), "--json", str(trained / "x.json")]) == 1
    err = capsys.readouterr().err
    assert "x.json" in err and len(err.strip().splitlines()) == 1 and not (trained / "x.json").exists()


def test_saved_model_predicts_identically_after_reload(trained):
    from data_tools.sequence import read_depth_png
    from recog.model import Recogniser
    lab = json.loads((trained / "t" / "labels.json").read_text())
    a = Recogniser.load(trained / "m")
    a.save(trained / "copy")
    b = Recogniser.load(trained / "copy")
    for it in lab[:4]:
        depth = read_depth_png(trained / "t" / it["file"], 1000.0)
        pa, pb = a.predict(depth, INTR, it["bbox"], icp=False), b.predict(depth, INTR, it["bbox"], icp=False)
        assert pa.object == pb.object and np.array_equal(pa.pose, pb.pose) and pa.distance == pb.distance


@pytest.mark.parametrize("case, words", [
    ("bbox outside", ["--bbox", "outside"]),
    ("empty crop", ["no depth"]),
    ("unknown object", ["labels.json", "unknown object"]),
    ("other version", ["recogniser.json", "version"]),
])
def test_bad_input_is_one_line(trained, tmp_path, capsys, case, words):
    import shutil
    lab = json.loads((trained / "t" / "labels.json").read_text())
    img = trained / "t" / lab[0]["file"]
    if case == "bbox outside":
        argv = ["recog", "predict", str(trained / "m"), str(img), "--bbox", "700,500,800,600"]
    elif case == "empty crop":
        import cv2
        z = tmp_path / "depth"
        z.mkdir()
        cv2.imwrite(str(z / "zero.png"), np.zeros((480, 640), np.uint16))
        shutil.copy(trained / "t" / "camera.json", tmp_path / "camera.json")
        argv = ["recog", "predict", str(trained / "m"), str(z / "zero.png"), "--bbox", "10,10,50,50"]
    elif case == "unknown object":
        t = tmp_path / "t"
        shutil.copytree(trained / "t", t)
        bad = [dict(lab[0], object="obj_99")] + lab[1:]
        (t / "labels.json").write_text(json.dumps(bad))
        argv = ["recog", "eval", str(trained / "m"), str(t), "--no-progress"]
    else:
        m = tmp_path / "m"
        shutil.copytree(trained / "m", m, ignore=shutil.ignore_patterns("data"))
        meta = json.loads((m / "recogniser.json").read_text())
        meta["version"] = 99
        (m / "recogniser.json").write_text(json.dumps(meta))
        argv = ["recog", "eval", str(m), str(trained / "t"), "--no-progress"]
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("realgap: error:") and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)


def test_physical_randomisation_keeps_far_objects_measured():
    """The physical variant's randomised sensors must still measure an object at the chairs' 3 m: the
    worst corner of the ranges (half projector power, the most ambient light) on a grey wall at
    3 m leaves most pixels valid (with ambient up to 0.2 it left none)."""
    from recog.data import PHYSICAL_RANDOMISATION, sensor_config
    from synth.sensor.simulator import SensorSimulator
    from synth.sensor.testscenes import camera_pose, wall_scene
    worst = {"pattern_projection.power": PHYSICAL_RANDOMISATION["pattern_projection.power"][0],
             "ambient_light.level": PHYSICAL_RANDOMISATION["ambient_light.level"][1]}
    cfg = sensor_config("physical", "kinect_v1", 160, 120).with_params(worst)
    res = SensorSimulator(cfg, None, wall_scene(3.0, albedo=0.5)).simulate(camera_pose(), seed=0)
    assert res.valid_fraction > 0.5


def test_eval_reads_the_synda_mapping(trained, capsys):
    """``recog eval --synda GEN``: the recogniser describes the generator's output instead of the measured patch
    (a generator whose output is constant makes every scan's vote the same), eval.json names the generator; a
    generator trained on other patches is a one-line error."""
    import dataclasses

    import torch

    from recog.model import Recogniser
    from recog.synda.config import AugmentConfig, GeneratorConfig, SyndaConfig, SyndaTrainConfig
    from recog.synda.io import save_generator
    from recog.synda.model import Generator
    m = Recogniser.load(trained / "m")
    g = GeneratorConfig(size=m.patch.size, widths=(2,) * 6, distill_width=2, decoders=("depth",), target="depth",
                        distillation=False)
    cfg = SyndaConfig("depth", g, AugmentConfig(), SyndaTrainConfig()).validate()
    net = Generator(g, "depth")
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
    net.eval()
    gen = trained / "synda.pt"
    save_generator(gen, net, cfg, {"patch": dataclasses.asdict(m.patch)})
    out = trained / "e_synda"
    assert main(["recog", "eval", str(trained / "m"), str(trained / "t"), "--synda", str(gen), "--no-icp",
                 "--out", str(out), "--no-progress"]) == 0
    r = json.loads((out / "eval.json").read_text())
    assert r["synda"] == str(gen) and "synda" in {i["role"] for i in r["header"]["inputs"]}
    rows = [json.loads(line) for line in (out / "predictions.jsonl").read_text().splitlines()]
    assert len({row["descriptor_predicted"] for row in rows}) == 1       # all-zero output: one answer
    from app.viewer.data import RecogSession                             # the viewer shows both patches
    sc = RecogSession(out, trained / "t").scan(0)
    assert sc["patch"].shape == sc["mapped"].shape == (64, 64) and np.all(sc["mapped"] == 0)
    assert sc["patch"].std() > 0
    save_generator(gen, net, cfg, {"patch": {**dataclasses.asdict(m.patch), "crop_m": 9.0}})
    capsys.readouterr()
    assert main(["recog", "eval", str(trained / "m"), str(trained / "t"), "--synda", str(gen), "--no-icp",
                 "--json", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "trained on 64 px patches of 9.0 m" in err


def test_synda_reindex_builds_an_object_only_database(trained, model_files, capsys):
    """``synda reindex``: the same network, a database of the same view grid whose patches are the object alone
    (+1 elsewhere): the recogniser's own training patches with their background set to +1 (made by another path,
    with noise) find their own object and view as nearest; re-running onto a finished folder or onto the model
    itself is a one-line error."""
    import torch

    from recog.data import load_training_data
    from recog.model import Recogniser
    from recog.objects import load_objects
    out = trained / "m_objonly"
    assert main(["synda", "reindex", str(trained / "m"), "--out", str(out), "--no-progress"]) == 0
    m, r = Recogniser.load(trained / "m"), Recogniser.load(out)
    wm, wr = m.net.state_dict(), r.net.state_dict()
    assert all(torch.equal(wm[k], wr[k]) for k in wm)
    assert r.info["reindexed"]["from"] == str(trained / "m") and "synda reindex" in r.info["reindexed"]["command"]
    assert not (out / "views").exists()
    objs = load_objects(f"{model_files / 'box.ply'},{model_files / 'bracket.ply'}")
    td = load_training_data(objs, m.data, trained / "m" / "data")
    q = r.describe(np.where(td.mask, td.patches[:, 0].astype(np.float32), 1.0).astype(np.float32))
    d = ((q[:, None] - r.db.descriptors[None]) ** 2).sum(-1)
    nearest = d.argmin(1)
    same_view = (r.db.obj[nearest] == td.obj) & (r.db.view[nearest] == td.view)
    views = {(o, v) for o, v in zip(td.obj, td.view)}
    assert len(r.db) == len(views) and same_view.mean() > 0.9, (len(r.db), same_view.mean())
    capsys.readouterr()
    for extra in ([], ["--overwrite"]):
        target = out if not extra else trained / "m"
        assert main(["synda", "reindex", str(trained / "m"), "--out", str(target), "--no-progress", *extra]) == 1
        err = capsys.readouterr().err.strip()
        expected = "already holds a finished result" if not extra else "would replace the input"
        assert "\n" not in err and expected in err


def test_synda_augmented_training_data(trained, model_files):
    """``TrainConfig.synda_augment`` (the A-trained baseline of thesis ch. 5): the chunks carry object masks that
    lie on the object's (nearer) pixels; A is deterministic for a seed, keeps shapes and the [-1, 1] range,
    changes the patches and draws anew for another seed; a few training steps with it are deterministic; data
    without masks is a one-line error."""
    import dataclasses

    from data_tools.errors import ConfigError
    from recog.data import load_training_data
    from recog.model import Recogniser
    from recog.objects import load_objects
    from recog.train import TrainConfig, _synda_augmenter, train_network
    m = Recogniser.load(trained / "m")
    objs = load_objects(f"{model_files / 'box.ply'},{model_files / 'bracket.ply'}")
    td = load_training_data(objs, m.data, trained / "m" / "data")
    assert td.mask is not None and td.mask.shape == (len(td), 64, 64) and td.mask.any((1, 2)).all()
    p0 = td.patches[:, 0].astype(np.float32)
    inside = np.array([p0[i][td.mask[i]].mean() for i in range(len(td))])
    outside = np.array([p0[i][~td.mask[i]].mean() for i in range(len(td))])
    assert np.mean(inside < outside) > 0.95
    aug = _synda_augmenter(td, 64)
    rows = np.arange(8)
    x = torch.from_numpy(p0[rows])[:, None]
    y1, y2, y3 = aug(x, rows, 7), aug(x, rows, 7), aug(x, rows, 8)
    assert y1.shape == x.shape and torch.equal(y1, y2) and not torch.equal(y1, y3)
    assert float(y1.min()) >= -1 and float(y1.max()) <= 1 and float((y1 - x).abs().mean()) > 0.01
    half = aug(x, rows, 7, 0.5)                  # a fraction: those patches A'd as before (to float rounding), the rest kept
    same_as_a = [torch.allclose(half[i], y1[i], rtol=0, atol=1e-5) for i in range(8)]   # batched kernels: ~1e-7
    kept = [torch.equal(half[i], x[i]) for i in range(8)]
    assert all(s or k for s, k in zip(same_as_a, kept)) and any(kept) and not all(kept)
    cfg = dataclasses.replace(TrainConfig(), iterations=3, batch=8, synda_augment=1.0)
    syms = [o.get("symmetry") for o in m.objects]
    w1 = train_network(td, syms, cfg, 64, progress=False)[0].state_dict()
    w2 = train_network(td, syms, cfg, 64, progress=False)[0].state_dict()
    w0 = train_network(td, syms, dataclasses.replace(cfg, synda_augment=0.0), 64, progress=False)[0].state_dict()
    assert all(torch.equal(w1[k], w2[k]) for k in w1) and not all(torch.equal(w1[k], w0[k]) for k in w1)
    with pytest.raises(ConfigError, match="object masks"):
        _synda_augmenter(dataclasses.replace(td, mask=None), 64)
