"""SynDA's colour test sets (recog/synda/colour_testset.py, app/colour_render.py) and ``recog eval --synda`` with an
rgb generator."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from data_tools.errors import RealgapError
from data_tools.mesh import TriMesh
from data_tools.scene_spec import Material
from recog.objects import RecogObject
from recog.synda.colour_testset import ColourScene, ColourTestsetConfig, compose, draw_scene, image_files

pv = pytest.importorskip("pyvista")


def _quad(z: float, half: float) -> RecogObject:
    """A square of side 2 ``half`` facing the camera at depth ``z`` (object frame = camera frame)."""
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], float)
    m = TriMesh(v, np.array([[0, 1, 2], [0, 2, 3]]), "quad", "m")
    obj = RecogObject("quad", [m], {"m": Material(0.5, 0.0)})
    return obj


def _scene(z: float, texture: int = 0, occluders=()) -> ColourScene:
    pose = np.eye(4)
    pose[2, 3] = z
    light = {"position": np.array([0.0, 0.0, 0.0]), "colour": np.ones(3), "intensity": 1.0}
    mat = {"pbr": False, "metallic": 0.0, "roughness": 0.5, "ambient": 0.3, "diffuse": 0.7, "specular": 0.0,
           "specular_power": 10.0}
    return ColourScene(0, pose, [light], mat, texture, "plane", list(occluders))


@pytest.fixture(scope="module")
def halves(tmp_path_factory):
    """A texture folder with one image: red left half, blue right half."""
    import cv2
    d = tmp_path_factory.mktemp("tex")
    im = np.zeros((64, 64, 3), np.uint8)
    im[:, :32] = (0, 0, 255)          # BGR: red
    im[:, 32:] = (255, 0, 0)          # blue
    cv2.imwrite(str(d / "halves.png"), im)
    return d


def test_render_textures_come_from_the_image_and_depth_is_metric(halves):
    """A square facing the camera with the red|blue image as texture: the rendered object is red on one side and blue
    on the other (the colour comes from the image, not from a procedural field as in A), its depth is its distance
    (1.5 m, within 1 mm), alpha marks exactly the drawn pixels, a sphere in front hides part of it (visible mask),
    and the same scene renders bit-identically twice."""
    from app.colour_render import PyVistaRenderer
    cfg = ColourTestsetConfig(width=160, height=120, focal_px=120.0, textures=str(halves))
    r = PyVistaRenderer(cfg, image_files(cfg.textures))
    obj = _quad(0.0, 0.4)
    rgba, depth, vis = r(_scene(1.5), obj)
    drawn = depth > 0
    assert rgba.shape == (120, 160, 4) and depth.shape == (120, 160)
    alpha = rgba[..., 3] > 0
    assert not (drawn & ~alpha).any() and (alpha & ~drawn).sum() <= 4 * 64      # at most a one-pixel fringe
    assert np.allclose(depth[drawn], 1.5, atol=1e-3)
    # the square spans +-0.4 m at 1.5 m: 2 * 0.4 / 1.5 * 120 = 64 px wide
    cols = np.nonzero(drawn.any(0))[0]
    assert abs((cols[-1] - cols[0] + 1) - 64) <= 2
    red = (rgba[..., 0].astype(int) - rgba[..., 2] > 40) & drawn
    blue = (rgba[..., 2].astype(int) - rgba[..., 0] > 40) & drawn
    assert red.sum() > 0.3 * drawn.sum() and blue.sum() > 0.3 * drawn.sum()
    xr, xb = np.nonzero(red)[1].mean(), np.nonzero(blue)[1].mean()
    assert abs(xr - xb) > 20                                            # two halves, side by side
    assert vis.sum() == drawn.sum()
    occ = {"shape": "sphere", "centre": np.array([0.0, 0.0, 1.2]), "size": 0.3, "rotation": np.eye(3),
           "colour": np.array([0.1, 0.9, 0.1]), "texture": -1}
    rgba2, depth2, vis2 = r(_scene(1.5, occluders=[occ]), obj)
    assert 0 < vis2.sum() < vis.sum() and depth2[60, 80] < 1.4
    again = r(_scene(1.5, occluders=[occ]), obj)
    assert np.array_equal(again[0], rgba2) and np.array_equal(again[1], depth2)


def test_scene_draws_are_seeded_and_compose_blends_by_alpha():
    """draw_scene is a function of (seed, object, scan); another seed or scan draws another scene; occluders are
    sorted nearest first and dropping one removes the nearest; compose puts the background where alpha is 0."""
    obj = _quad(0.0, 0.2)
    obj.meshes[0].vertices[:, 2] += np.array([0.0, 0.0, 0.05, 0.05])   # give it some height
    cfg = ColourTestsetConfig(occluders=(3, 3))
    a, b = draw_scene(obj, 0, 1, cfg, 5, 7), draw_scene(obj, 0, 1, cfg, 5, 7)
    assert np.array_equal(a.pose, b.pose) and a.texture == b.texture and a.background == b.background
    assert all(np.array_equal(x["centre"], y["centre"]) for x, y in zip(a.occluders, b.occluders))
    c = draw_scene(obj, 0, 2, cfg, 5, 7)
    d = draw_scene(obj, 0, 1, dataclasses.replace(cfg, seed=cfg.seed + 1), 5, 7)
    assert not np.allclose(a.pose, c.pose) and not np.allclose(a.pose, d.pose)
    zs = [o["centre"][2] for o in a.occluders]
    assert len(zs) == 3 and zs == sorted(zs)
    z_near = (obj.vertices @ a.pose[:3, :3].T + a.pose[:3, 3])[:, 2].min()
    assert all(z <= z_near + 1e-9 for z in zs)                          # in front of the object
    dropped = draw_scene(obj, 0, 1, cfg, 5, 7, drop=1)
    assert [o["centre"][2] for o in dropped.occluders] == zs[1:]
    from data_tools.geometry import is_rigid
    assert is_rigid(a.pose, 1e-9)
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[0, 0] = (10, 20, 30, 255)
    bg = np.full((2, 2, 3), 200, np.uint8)
    out = compose(rgba, bg)
    assert out[0, 0].tolist() == [10, 20, 30] and out[1, 1].tolist() == [200, 200, 200]


def _tiny_generator(path, domain: str, patch, target: str = "depth"):
    import torch

    from recog.synda.config import AugmentConfig, GeneratorConfig, SyndaConfig, SyndaTrainConfig
    from recog.synda.io import save_generator
    from recog.synda.model import Generator
    g = GeneratorConfig(size=patch.size, widths=(2,) * 6, distill_width=2, decoders=(target,), target=target,
                        distillation=False)
    cfg = SyndaConfig(domain, g, AugmentConfig(), SyndaTrainConfig()).validate()
    torch.manual_seed(0)
    net = Generator(g, domain).eval()
    save_generator(path, net, cfg, {"patch": dataclasses.asdict(patch)})
    return net


def test_colour_testset_is_read_by_recog_eval(tmp_path, capsys):
    """``synda testset`` writes a test set that ``recog eval --synda RGB_GEN`` reads (every scan recognised from
    the generator's mapping of its colour patch; the colour patch is pixel-aligned with the depth patch); the same
    command twice writes identical files; an rgb generator on scans without colour, and a generator whose output
    is not depth, are one-line errors."""
    from app.cli import main
    from recog.model import Recogniser
    ts = tmp_path / "ts"
    args = ["synda", "testset", "--objects", "chairs", "--per-object", "1", "--out", str(ts), "--no-progress"]
    assert main(args) == 0
    labels = json.loads((ts / "labels.json").read_text())
    assert len(labels) == 3 and all((ts / lab["rgb"]).is_file() for lab in labels)
    assert json.loads((ts / "testset_config.json").read_text())["domain"] == "rgb"
    first = (ts / "rgb" / "000000.png").read_bytes()
    assert main(args + ["--overwrite"]) == 0 and (ts / "rgb" / "000000.png").read_bytes() == first
    model = Recogniser.load("recog/weights/chairs")
    gen = tmp_path / "rgb.pt"
    _tiny_generator(gen, "rgb", model.patch)
    out = tmp_path / "e"
    assert main(["recog", "eval", "recog/weights/chairs", str(ts), "--synda", str(gen), "--no-icp", "--out", str(out),
                 "--no-progress"]) == 0
    r = json.loads((out / "eval.json").read_text())
    assert r["n_scans"] == 3 and r["synda"] == str(gen)
    # the colour patch lies on the depth patch's pixels: the object's colour differs from the background there
    from data_tools.sequence import read_depth_png, read_rgb_image
    from recog.patches import extract_patch
    from recog.synda.colour_testset import colour_patch
    from recog.testset import read_testset
    cam, scans = read_testset(ts)
    sc = scans[0]
    p = extract_patch(read_depth_png(ts / sc.file, cam.depth_scale), cam.intrinsics, sc.bbox, model.patch)
    c = colour_patch(read_rgb_image(ts / sc.rgb), cam.intrinsics, p, model.patch)
    assert c.shape == (3, model.patch.size, model.patch.size) and c.min() >= -1 and c.max() <= 1
    # the viewer's recognition mode shows the colour patch the generator read and its depth mapping
    from app.viewer.data import RecogSession
    view = RecogSession(out, ts).scan(0)
    S = model.patch.size
    assert view["patch"].shape == (S, S, 3) and view["patch"].dtype == np.uint8 and view["mapped"].shape == (S, S)
    assert np.array_equal(view["patch"], np.clip((c.transpose(1, 2, 0) + 1) * 127.5, 0, 255).astype(np.uint8))
    # bad inputs: scans without colour; a generator with normals as output
    lab = [{k: v for k, v in x.items() if k != "rgb"} for x in labels]
    (ts / "labels.json").write_text(json.dumps(lab))
    capsys.readouterr()
    assert main(["recog", "eval", "recog/weights/chairs", str(ts), "--synda", str(gen), "--no-icp", "--json",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "reads colour images, these scans have none" in err
    bad = tmp_path / "normals.pt"
    _tiny_generator(bad, "rgb", model.patch, target="normals")
    assert main(["recog", "eval", "recog/weights/chairs", str(ts), "--synda", str(bad), "--no-icp", "--json",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "final output is normals" in err


def test_colour_patch_and_image_errors(tmp_path):
    """colour_patch takes (H, W, 3) only; an empty image folder is a one-line error naming it; 16-bit PNGs (depth
    frames beside colour ones) are not taken as backgrounds."""
    import cv2

    from recog.synda.colour_testset import colour_patch
    with pytest.raises(RealgapError, match=r"must be \(H, W, 3\)"):
        colour_patch(np.zeros((4, 4)), None, None, None)
    with pytest.raises(RealgapError, match="no images"):
        image_files(str(tmp_path))
    cv2.imwrite(str(tmp_path / "a.depth.png"), np.zeros((4, 4), np.uint16))
    cv2.imwrite(str(tmp_path / "a.color.png"), np.zeros((4, 4, 3), np.uint8))
    assert [f.name for f in image_files(str(tmp_path))] == ["a.color.png"]


def test_train_target_flag():
    """``synda train --target depth`` makes an rgb generator whose final output is depth (the depth recogniser's
    input); without it the rgb preset keeps the thesis' normals."""
    from app.cli import build_parser
    from app.commands.synda import synda_configs
    base = ["synda", "train", "--objects", "chairs", "--domain", "rgb", "--out", "g.pt"]
    cfg, _ = synda_configs(build_parser().parse_args(base + ["--target", "depth"]))
    assert cfg.domain == "rgb" and cfg.generator.target == "depth"
    cfg, _ = synda_configs(build_parser().parse_args(base))
    assert cfg.generator.target == "normals"


def test_train_flags_generated_from_config(capsys):
    """Every SynDA field has a ``synda train`` flag that overrides the preset: optimiser numbers by their name,
    the architecture's ablation switches as ``--no-generator.NAME``, A's ranges as ``LO,HI``; a range of the wrong
    length is one usage line before any work, and an unset flag keeps the preset's value."""
    import dataclasses

    from app.cli import build_parser, main
    from app.commands.synda import synda_configs
    from recog.synda.config import synda_preset
    base = ["synda", "train", "--objects", "chairs", "--domain", "depth", "--out", "g.pt", "--seed", "3"]
    cfg, _ = synda_configs(build_parser().parse_args(base))
    preset = synda_preset("cpu", "depth")
    assert cfg == dataclasses.replace(preset, train=dataclasses.replace(preset.train, seed=3))
    cfg, _ = synda_configs(build_parser().parse_args(base + [
        "--iterations", "7", "--lr", "1e-3", "--no-generator.skips", "--generator.widths", "8,16,16,16,16,16",
        "--augment.blur-sigma", "0.5,0.9", "--augment.blurs", "none,median"]))
    assert cfg.train.iterations == 7 and cfg.train.lr == 1e-3 and cfg.train.seed == 3
    assert cfg.generator.skips is False and cfg.generator.widths == (8, 16, 16, 16, 16, 16)
    assert cfg.augment.blur_sigma == (0.5, 0.9) and cfg.augment.blurs == ("none", "median")
    assert cfg.generator.decoders == preset.generator.decoders            # untouched fields keep the preset's
    assert main(base + ["--augment.blur-sigma", "0.5"]) != 0
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--augment.blur-sigma" in err and "expected 2 comma-separated values" in err
