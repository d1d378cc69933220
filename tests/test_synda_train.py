"""SynDA training (recog/synda/train.py, data.py, run.py) and its commands (app/commands/synda.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from data_tools.errors import RealgapError
from recog.synda.augment import Augmenter
from recog.synda.config import AugmentConfig, GeneratorConfig, SyndaConfig, SyndaTrainConfig
from recog.synda.data import SyndaData, normals_from_depth
from recog.synda.io import load_generator, save_generator
from recog.synda.train import evaluate_batch_loss, make_batch, train_generator

S = 16
TINY = GeneratorConfig(size=S, widths=(4, 8, 8, 8), distill_width=4, decoders=("normals", "depth", "mask"),
                       target="depth")


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def boxes(n: int = 12, k: int = 2, seed: int = 0) -> SyndaData:
    """n views of a box of random size and depth on a tilted plane; k noisy draws each (noise + holes)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:S, 0:S]
    clean, mask = np.zeros((n, S, S), np.float32), np.zeros((n, S, S), bool)
    for i in range(n):
        a, b = rng.integers(2, 7, 2)
        c = rng.integers(5, 11, 2)
        m = (abs(yy - c[0]) <= a) & (abs(xx - c[1]) <= b)
        clean[i] = np.where(m, rng.uniform(-0.5, 0.1), 0.3 + 0.02 * (yy - S / 2))
        mask[i] = m
    noisy = clean[:, None] + rng.normal(0, 0.05, (n, k, S, S))
    noisy[rng.random((n, k, S, S)) < 0.1] = 1.0
    return SyndaData(clean.astype(np.float16), mask, np.clip(noisy, -1, 1).astype(np.float16),
                     np.zeros(n, np.int32))


def config(domain="depth", iterations=30, **gen) -> SyndaConfig:
    g = TINY if domain == "depth" else dataclasses.replace(TINY, decoders=("normals", "depth", "mask", "lightness"),
                                                           target="normals")
    aug = AugmentConfig(backgrounds=("perlin", "voronoi", "white"), depth_keep_background=0.5)
    return SyndaConfig(domain, dataclasses.replace(g, **gen), aug,
                       SyndaTrainConfig(iterations=iterations, batch=8, lr=2e-3, seed=1)).validate()


def held_loss(net, cfg, data):
    return evaluate_batch_loss(net, cfg, data, Augmenter(cfg.augment, cfg.domain, S), seed=5)["loss"]


# ------------------------------------------------------------------------------------------ data
def test_normals_of_planes_are_hand_values():
    """A plane rising by 0.1 normalised units per pixel along x in a 16 px patch: metric slope 0.1 * 16 / 2 =
    0.8, normal (0.8, 0, -1) / |.|; a flat patch faces the camera (0, 0, -1)."""
    x = torch.arange(S, dtype=torch.float32)
    d = (0.1 * x)[None, None, None].expand(1, 1, S, S).clone()
    n = normals_from_depth(d)
    want = torch.tensor([0.8, 0.0, -1.0]) / np.hypot(0.8, 1.0)
    assert torch.allclose(n[0, :, 5, 5], want, atol=1e-6)
    flat = normals_from_depth(torch.zeros(2, 1, S, S))
    assert torch.allclose(flat, torch.tensor([0.0, 0.0, -1.0])[None, :, None, None].expand(2, 3, S, S))


def test_depth_patch_with_the_window_geometry_is_extract_patch():
    """The noisy draws are cut with the clean view's virtual camera: with the same geometry, depth_patch is
    extract_patch; resample_nearest is aligned with it (a mask of the valid pixels)."""
    from data_tools.camera import Intrinsics
    from recog.patches import PatchConfig, depth_patch, extract_patch, resample_nearest
    intr = Intrinsics(fx=500.0, fy=500.0, cx=160.0, cy=120.0, width=320, height=240)
    rng = np.random.default_rng(0)
    depth = np.full((240, 320), 2.0, np.float32)
    depth[80:160, 100:220] = 1.5 + 0.05 * rng.random((80, 120))
    depth[rng.random((240, 320)) < 0.05] = 0.0
    cfg = PatchConfig(size=32, crop_m=0.4)
    p = extract_patch(depth, intr, (100, 80, 220, 160), cfg)
    q = depth_patch(depth, intr, p.R_ray, p.z_ref_m, p.bbox, cfg)
    assert np.array_equal(p.image, q.image)
    valid = resample_nearest(depth > 0, intr, p.R_ray, p.z_ref_m, cfg) > 0.5
    assert np.array_equal(valid, p.image < 1.0) or np.all(p.image[~valid] == 1.0)


# ------------------------------------------------------------------------------------------ training
@pytest.mark.parametrize("domain", ["depth", "rgb"])
def test_a_few_iterations_lower_the_loss(domain):
    data = boxes()
    cfg = config(domain, iterations=40)
    torch.manual_seed(1)
    from recog.synda.model import Generator
    before = held_loss(Generator(cfg.generator, domain).eval(), cfg, data)
    net, log = train_generator(cfg, data, progress=False, log_every=10)
    after = held_loss(net, cfg, data)
    assert after < 0.85 * before, (before, after)
    assert [r["step"] for r in log.steps] == [10, 20, 30, 40]
    assert log.steps[-1]["loss"] < log.steps[0]["loss"]
    want = {"loss", "normals", "depth", "mask", "output", "step"} | ({"lightness"} if domain == "rgb" else set())
    assert set(log.steps[-1]) == want


def test_batches_are_built_from_the_views():
    """Depth domain: the target's object pixels are the clean view's, the input's are its measured draw's
    (before blur: blur off, no occluders); the mask target is the view's mask."""
    data = boxes()
    cfg = config()
    aug = Augmenter(dataclasses.replace(cfg.augment, blurs=("none",), occluders=(0, 0)), "depth", S)
    idx, draw = np.array([3, 7]), np.array([1, 0])
    x, t = make_batch(data, idx, draw, aug, aug.draw(2, 0))
    m = torch.from_numpy(data.mask[idx])
    assert torch.equal(t["mask"][:, 0] > 0.5, m)
    assert torch.equal(t["depth"][:, 0][m], torch.from_numpy(data.clean[idx].astype(np.float32))[m])
    assert torch.equal(x[:, 0][m], torch.from_numpy(data.noisy[idx, draw].astype(np.float32))[m])
    assert t["normals"].shape == (2, 3, S, S)


def test_resume_continues_identically(tmp_path):
    """20 steps straight = 10 steps, a new process-like restart from the checkpoint, 10 more (same weights,
    same log)."""
    data = boxes()
    cfg = config(iterations=20)
    full, log_full = train_generator(cfg, data, tmp_path / "a.pt", progress=False, log_every=5, checkpoint_every=10)
    half = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, iterations=10))
    train_generator(half, data, tmp_path / "b.pt", progress=False, log_every=5, checkpoint_every=10)
    torch.manual_seed(999)                                # the resume must restore the random state itself
    resumed, log_res = train_generator(cfg, data, tmp_path / "b.pt", progress=False, log_every=5,
                                       checkpoint_every=10)
    assert log_res.resumed_from == 10 and log_res.steps == log_full.steps
    for (k, a), (_, b) in zip(full.state_dict().items(), resumed.state_dict().items()):
        assert torch.equal(a, b), k


def test_triplet_switch_trains_with_a_triplet_term():
    data = boxes()
    cfg = config(iterations=4, triplet=True)
    _, log = train_generator(cfg, data, progress=False, log_every=2)
    assert "triplet" in log.steps[-1] and log.steps[-1]["triplet"] >= 0


def test_trained_generator_save_load_identical(tmp_path):
    data = boxes()
    cfg = config(iterations=5)
    net, _ = train_generator(cfg, data, progress=False)
    save_generator(tmp_path / "g.pt", net, cfg, {"patch": {"size": S, "crop_m": 0.5}})
    net2, cfg2, info = load_generator(tmp_path / "g.pt", "depth")
    x = torch.from_numpy(data.noisy[:4, 0].astype(np.float32))[:, None]
    with torch.no_grad():
        a, b = net(x), net2(x)
    assert all(torch.equal(a[k], b[k]) for k in a)
    from recog.patches import PatchConfig
    from recog.synda.run import patch_mapper
    fn, _ = patch_mapper(tmp_path / "g.pt", PatchConfig(size=S, crop_m=0.5))
    assert np.array_equal(fn(x[:, 0].numpy()), a["output"][:, 0].numpy())
    assert np.array_equal(fn(x[0, 0].numpy()), a["output"][0, 0].numpy())
    with pytest.raises(RealgapError, match="trained on 16 px patches of 0.5 m"):
        patch_mapper(tmp_path / "g.pt", PatchConfig(size=S, crop_m=0.3))
    with pytest.raises(RealgapError, match="'depth' inputs, 'rgb' needed"):
        load_generator(tmp_path / "g.pt", "rgb")


def test_training_errors_are_one_line():
    data = boxes()
    with pytest.raises(RealgapError, match="at least 2 usable views"):
        train_generator(config(), dataclasses.replace(data, clean=data.clean[:1], mask=data.mask[:1],
                                                      noisy=data.noisy[:1], obj=data.obj[:1]), progress=False)
    big = dataclasses.replace(config(), generator=GeneratorConfig(size=32, widths=(4, 8, 8, 8, 8), distill_width=4,
                                                                  decoders=("depth",), target="depth"))
    with pytest.raises(RealgapError, match="training patches are 16 px, the generator takes 32"):
        train_generator(big.validate(), data, progress=False)
    rgbdata = dataclasses.replace(data, noisy=np.zeros((len(data), 0, S, S), np.float16))
    with pytest.raises(RealgapError, match="needs measured draws"):
        train_generator(config(), rgbdata, progress=False)


# ------------------------------------------------------------------------------------------ commands
def _gen_file(tmp_path, domain="depth"):
    """A 64 px generator (narrow, untrained) saved with the patch configuration of its training."""
    from recog.synda.model import Generator
    g = GeneratorConfig(size=64, widths=(2, 2, 2, 2, 2, 2), distill_width=2)
    g = dataclasses.replace(g, decoders=("normals", "depth", "mask"), target="depth") if domain == "depth" else g
    cfg = SyndaConfig(domain, g, AugmentConfig(), SyndaTrainConfig()).validate()
    torch.manual_seed(0)
    path = tmp_path / f"{domain}.pt"
    save_generator(path, Generator(g, domain).eval(), cfg, {"patch": {"size": 64, "crop_m": 0.2}})
    return path


def test_map_writes_every_modality_and_a_contact_sheet(tmp_path, capsys):
    import cv2

    from app.cli import main
    gen = _gen_file(tmp_path)
    x = np.random.default_rng(0).uniform(-1, 1, (2, 64, 64)).astype(np.float32)
    np.save(tmp_path / "p.npy", x)
    cv2.imwrite(str(tmp_path / "g.png"), (np.arange(64 * 64).reshape(64, 64) % 256).astype(np.uint8))
    out = tmp_path / "m"
    assert main(["synda", "map", str(gen), str(tmp_path / "p.npy"), str(tmp_path / "g.png"), "--out", str(out)]) == 0
    assert (out / "contact_sheet.png").stat().st_size > 1000
    for name in ("p_000", "p_001", "g"):
        assert sorted(f.name for f in (out / name).iterdir()) == ["depth.png", "input.png", "mask.png",
                                                                  "normals.png", "output.png"]
    rgb = _gen_file(tmp_path, "rgb")
    cv2.imwrite(str(tmp_path / "c.png"), np.zeros((64, 64, 3), np.uint8))
    assert main(["synda", "map", str(rgb), str(tmp_path / "c.png"), "--out", str(tmp_path / "r")]) == 0
    assert (tmp_path / "r" / "c" / "lightness.png").is_file()


@pytest.mark.parametrize("make, words", [
    (lambda d: np.save(d / "x.npy", np.zeros((2, 32, 32), np.float32)), "1-channel 64 x 64 images, got an array of "
                                                                         "shape (2, 1, 32, 32)"),
    (lambda d: __import__("cv2").imwrite(str(d / "x.png"), np.zeros((64, 64, 3), np.uint8)), "a colour image"),
    (lambda d: __import__("cv2").imwrite(str(d / "x.png"), np.zeros((64, 64), np.uint16)), "needs --bbox"),
    (lambda d: (d / "x.txt").write_text("hi"), "unknown input type"),
    (lambda d: np.save(d / "x.npy", np.full((64, 64), 5.0, np.float32)), "values must lie in [-1, 1] (normalised "
                                                                         "patches), got 5 to 5"),
])
def test_map_bad_inputs_are_one_line(tmp_path, capsys, make, words):
    from app.cli import main
    gen = _gen_file(tmp_path)
    make(tmp_path)
    src = next(p for p in tmp_path.iterdir() if p.stem == "x")
    assert main(["synda", "map", str(gen), str(src), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and words in err and str(src) in err


def test_bad_generator_and_objects_are_one_line(tmp_path, capsys):
    from app.cli import main
    bad = tmp_path / "bad.pt"
    torch.save({"format": "realgap-synda-generator", "version": 99}, bad)
    np.save(tmp_path / "p.npy", np.zeros((64, 64), np.float32))
    assert main(["synda", "map", str(bad), str(tmp_path / "p.npy"), "--out", str(tmp_path / "o")]) == 1
    assert "version 99" in capsys.readouterr().err
    assert main(["synda", "train", "--objects", str(tmp_path / "none"), "--domain", "depth", "--out",
                 str(tmp_path / "g.pt"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "none" in err


@pytest.mark.slow
def test_augment_contact_sheet_of_the_chairs(tmp_path):
    """``synda augment`` on the embedded chairs (simulates a few views: ~20 s)."""
    from app.cli import main
    assert main(["synda", "augment", "--objects", "chairs", "--domain", "depth", "--samples", "3", "--out",
                 str(tmp_path / "a")]) == 0
    z = np.load(tmp_path / "a" / "samples.npz")
    assert z["input"].shape == (3, 1, 64, 64) and z["measured"].shape == (3, 1, 64, 64)
    assert (tmp_path / "a" / "contact_sheet.png").stat().st_size > 1000


def test_mask_head_starts_at_the_prior_and_learns_the_foreground():
    """The mask head's bias starts at logit(mask_prior), so a fresh generator says ~prior everywhere; 30 steps on
    one fixed batch then lift the mean foreground probability above 0.5 (and above the background's). From a 0
    bias (prior 0.5, the old initialisation) the same 30 steps leave the foreground below 0.5: the trap that kept
    the shipped generator's mask under p = 0.52 (docs/synda.md)."""
    from recog.synda.loss import generator_loss
    from recog.synda.model import Generator
    data = boxes()

    def fg_bg(prior, steps):
        cfg = config("depth", mask_prior=prior)
        aug = Augmenter(cfg.augment, "depth", S)
        x, tgt = make_batch(data, np.arange(8), np.zeros(8, int), aug, aug.draw(8, 7))
        torch.manual_seed(0)
        net = Generator(cfg.generator, "depth").train()
        opt = torch.optim.Adam(net.parameters(), lr=2e-3, betas=(0.5, 0.999))
        for _ in range(steps):
            loss, _ = generator_loss(net(x), tgt, "depth")
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            p = torch.sigmoid(net(x)["mask"])
        fg = tgt["mask"] > 0.5
        return float(p[fg].mean()), float(p[~fg].mean())

    assert fg_bg(0.1, 0) == pytest.approx((0.1, 0.1), abs=0.01)
    fg, bg = fg_bg(0.1, 30)
    assert fg > 0.5 > bg, (fg, bg)
    assert fg_bg(0.5, 30)[0] < 0.5


def test_mask_prior_of_class_masks_and_bad_priors():
    from recog.synda.model import Generator
    g = dataclasses.replace(TINY, mask_classes=3, mask_prior=0.2)
    bias = Generator(g, "depth").decoders["mask"].head[1].bias.detach()
    assert torch.softmax(bias, 0).tolist() == pytest.approx([0.8, 0.1, 0.1], abs=1e-6)
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(RealgapError, match="mask_prior"):
            dataclasses.replace(TINY, mask_prior=bad).validate()
