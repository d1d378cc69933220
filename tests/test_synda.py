"""SynDA foundations (recog/synda): config, generator, losses, augmentation A, save/load."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from data_tools.errors import RealgapError
from recog.synda.augment import Augmenter, load_image_bank, select, select_params
from recog.synda.config import (AugmentConfig, GeneratorConfig, SyndaConfig, synda_preset)
from recog.synda.io import GENERATOR_VERSION, load_generator, save_generator
from recog.synda.loss import bottleneck_triplet_loss, generator_loss, modality_loss
from recog.synda.model import Generator, SelfAttention
from recog.synda.polygons import polygon_masks, random_polygons
from recog.synda.shading import blinn_phong

S = 32
TINY = GeneratorConfig(size=16, widths=(4, 8, 8, 8), distill_width=4)
"""A 16 px generator for fast tests (the architecture is the same at any size)."""


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and msg
    return msg


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One torch thread: these tensors are tiny, and on a loaded 2-core machine two threads wait
    for each other (measured 100x slower per step)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def sphere(b: int, s: int = S):
    """A sphere filling 2/3 of the image: unit normals (camera frame, facing the camera: z < 0),
    mask and normalised depth."""
    c = (torch.arange(s) + 0.5 - s / 2) / (s / 3)
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    r2 = xx ** 2 + yy ** 2
    m = (r2 < 1).float()
    nz = -torch.sqrt((1 - r2).clamp_min(0))
    n = torch.stack([xx * m, yy * m, torch.where(m > 0, nz, -torch.ones_like(nz))])
    n = n / n.norm(dim=0, keepdim=True)
    depth = torch.where(m > 0, 0.5 * nz, torch.zeros_like(nz))
    rep = lambda t: t[None].repeat(b, *([1] * t.dim()))  # noqa: E731
    return {"normals": rep(n), "mask": rep(m[None]), "depth": rep(depth[None])}


@pytest.fixture(scope="module")
def bank():
    g = torch.Generator().manual_seed(3)
    return torch.rand(3, 3, 128, 128, generator=g)


def augmenter(domain="rgb", bank=None, hook=None, **kw):
    cfg = dataclasses.replace(AugmentConfig(), **kw)
    return Augmenter(cfg, domain, S, sensor_hook=hook, images=bank)


# ------------------------------------------------------------------------------------------ config
@pytest.mark.parametrize("preset", ["cpu", "gpu"])
@pytest.mark.parametrize("domain", ["rgb", "depth"])
def test_presets_are_valid(preset, domain):
    cfg = synda_preset(preset, domain)
    assert cfg.generator.size == 64 and cfg.in_channels == (3 if domain == "rgb" else 1)
    assert cfg.generator.target == ("normals" if domain == "rgb" else "depth")
    if preset == "gpu":
        assert cfg.generator.widths[-1] == 512 and cfg.generator.distill_width == 64


@pytest.mark.parametrize("change, words", [
    (lambda c: setattr(c.generator, "size", 32), "2 ** len(widths)"),
    (lambda c: setattr(c.generator, "decoders", ("normals", "colour")), "unknown"),
    (lambda c: (setattr(c.generator, "distillation", False), setattr(c.generator, "decoders", ("depth",))),
     "needs a normals decoder"),
    (lambda c: setattr(c, "domain", "depth"), "no lightness"),
    (lambda c: setattr(c, "domain", "ir"), "choose rgb or depth"),
    (lambda c: setattr(c.augment, "ambient", (0.3, 0.05)), "exceeds"),
    (lambda c: setattr(c.augment, "blur_kernel", (2, 4)), "odd"),
    (lambda c: setattr(c.augment, "vertices", (2, 10)), "vertices"),
    (lambda c: setattr(c.train, "lr", -1.0), "lr"),
])
def test_config_errors_are_one_line(change, words):
    cfg = synda_preset("cpu", "rgb")
    change(cfg)
    with pytest.raises(RealgapError) as e:
        cfg.validate()
    assert words in one_line(e)


def test_config_round_trips_through_json_and_overrides():
    from data_tools.config import config_from_dict, config_replace, config_to_dict
    cfg = synda_preset("cpu", "depth")
    assert config_from_dict(SyndaConfig, json.loads(json.dumps(config_to_dict(cfg)))) == cfg
    cfg2 = config_replace(cfg, {"generator.skips": "false", "augment.blurs": ["none", "median"]})
    assert cfg2.generator.skips is False and cfg2.augment.blurs == ("none", "median")
    with pytest.raises(RealgapError) as e:
        config_replace(cfg, {"generator.decoders": ["normals", "lightness"]})
    assert "no lightness" in one_line(e)


def test_unknown_preset_is_one_line():
    with pytest.raises(RealgapError) as e:
        synda_preset("tpu")
    assert "cpu, gpu" in one_line(e)


# ------------------------------------------------------------------------------------------ Blinn-Phong
def _shade(normal, light, a=0.1, d=0.5, s=0.05, hard=1.0):
    """Shade a 3x3 map of one normal (the centre pixel looks straight down the optical axis)."""
    n = torch.tensor(normal, dtype=torch.float64).view(1, 3, 1, 1).expand(1, 3, 3, 3)
    lgt = torch.tensor([light], dtype=torch.float64)
    coef = lambda v: torch.full((1, 3), v, dtype=torch.float64)  # noqa: E731
    y = blinn_phong(n, lgt, coef(a), coef(d), coef(s), torch.tensor([hard], dtype=torch.float64), focal_px=50.0)
    return y[0, :, 1, 1]


def test_blinn_phong_hand_values():
    toward = [0.0, 0.0, -1.0]                        # facing the camera (and a light behind it)
    s60, c60 = math.sin(math.radians(60)), math.cos(math.radians(60))
    # flat normal facing the light: D = 1, H = V = L, S = 1 -> a + d + s
    assert torch.allclose(_shade(toward, toward), torch.full((3,), 0.65, dtype=torch.float64))
    # normal tilted 60 deg from the light (= view) direction: D = N.H = cos 60 = 0.5
    y = _shade([s60, 0.0, -c60], toward, hard=2.0)
    assert torch.allclose(y, torch.full((3,), 0.1 + 0.5 * 0.5 + 0.05 * 0.25, dtype=torch.float64))
    # light 60 deg off-axis, normal facing the camera: D = 0.5, H halfway (30 deg): N.H = cos 30
    y = _shade(toward, [s60, 0.0, -c60], hard=1.0)
    assert torch.allclose(y, torch.full((3,), 0.1 + 0.5 * 0.5 + 0.05 * math.cos(math.radians(30)),
                                        dtype=torch.float64))
    # facing away from the light: ambient only
    assert torch.allclose(_shade([0.0, 0.0, 1.0], toward), torch.full((3,), 0.1, dtype=torch.float64))
    # bright coefficients saturate at 1
    assert torch.allclose(_shade(toward, toward, a=0.5, d=0.8, s=0.1), torch.ones(3, dtype=torch.float64))


def test_blinn_phong_rgb_coefficients_are_per_channel():
    n = torch.tensor([0.0, 0.0, -1.0]).view(1, 3, 1, 1).expand(1, 3, 3, 3)
    y = blinn_phong(n, torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.1, 0.2, 0.3]]),
                    torch.tensor([[0.0, 0.1, 0.2]]), torch.zeros(1, 3), torch.ones(1), 50.0)
    assert torch.allclose(y[0, :, 1, 1], torch.tensor([0.1, 0.3, 0.5]))


# ------------------------------------------------------------------------------------------ polygons
def test_polygon_generator_respects_its_parameters():
    g = torch.Generator().manual_seed(0)
    p, v_max = 400, 10
    n = torch.randint(3, v_max + 1, (p,), generator=g)
    eps = torch.rand(p, generator=g) * 0.5
    sig = torch.rand(p, generator=g) * 0.5
    r_mu = 5 + 10 * torch.rand(p, generator=g)
    centre = torch.full((p, 2), 30.0)
    verts, steps, radii = random_polygons(n, centre, r_mu, eps, sig, g, v_max)
    assert verts.shape == (p, v_max, 2)
    for i in range(p):
        k = int(n[i])
        assert len(torch.unique(verts[i], dim=0)) == k                      # exactly n vertices
        st = steps[i, :k] / (2 * math.pi / k)
        assert abs(float(steps[i].sum()) - 2 * math.pi) < 1e-4              # closes the loop
        lo, hi = (1 - eps[i]) / (1 + eps[i]), (1 + eps[i]) / (1 - eps[i])
        assert float(st.min()) >= lo - 1e-5 and float(st.max()) <= hi + 1e-5
        assert float(radii[i].min()) >= 0 and float(radii[i].max()) <= 2 * float(r_mu[i]) + 1e-5
        d = (verts[i, :k] - centre[i]).norm(dim=1)
        assert torch.allclose(d, radii[i, :k], atol=1e-4)
    # sigma = 0 gives the mean radius, epsilon = 0 equal steps (a regular polygon)
    verts, steps, radii = random_polygons(torch.full((5,), 6), centre[:5], torch.full((5,), 8.0), torch.zeros(5),
                                          torch.zeros(5), g, 10)
    assert torch.allclose(radii, torch.full_like(radii, 8.0))
    assert torch.allclose(steps[:, :6], torch.full((5, 6), 2 * math.pi / 6))


def test_polygon_rasterisation_counts_pixels():
    square = torch.tensor([[2.0, 2.0], [6.0, 2.0], [6.0, 6.0], [2.0, 6.0]])
    assert float(polygon_masks(square, 8, 8).sum()) == 16                 # centres 2.5 .. 5.5
    ell = torch.tensor([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [2.0, 2.0], [2.0, 4.0], [0.0, 4.0]])  # concave
    m = polygon_masks(ell, 8, 8)
    assert float(m.sum()) == 12 and m[3, 3] == 0 and m[1, 3] == 1 and m[3, 1] == 1
    degenerate = torch.tensor([[3.0, 3.0]] * 5)                             # padded, unused slot
    assert float(polygon_masks(degenerate, 8, 8).sum()) == 0


def test_polygon_rasterisation_matches_kornia_on_convex_polygons():
    """kornia fills convex polygons only (with pixel centres at integer coordinates): on regular
    polygons both rasterisers agree pixel for pixel."""
    import kornia
    g = torch.Generator().manual_seed(0)
    verts, _, _ = random_polygons(torch.full((20,), 7), torch.full((20, 2), 16.0) + torch.rand(20, 2, generator=g),
                                  torch.full((20,), 9.0), torch.zeros(20), torch.zeros(20), g, 7)
    ref = kornia.image.draw_convex_polygon(torch.zeros(20, 1, 32, 32), verts - 0.5, torch.ones(20, 1))[:, 0]
    assert torch.equal(polygon_masks(verts, 32, 32), ref)


# ------------------------------------------------------------------------------------------ augmentation
def test_augmentation_is_deterministic_and_keeps_shapes_and_ranges(bank):
    a = augmenter(bank=bank)
    x = sphere(6)
    out1, p1 = a(x, 7)
    out2, p2 = a(x, 7)
    assert p1.keys() == p2.keys() and all(torch.equal(p1[k], p2[k]) for k in p1)
    assert all(torch.equal(out1[k], out2[k]) for k in out1)
    assert all(torch.equal(out1[k], a.apply(x, p1)[k]) for k in out1)      # apply is pure
    out3, _ = a(x, 8)
    assert not torch.equal(out1["input"], out3["input"])
    assert out1["input"].shape == (6, 3, S, S) and out1["lightness"].shape == (6, 1, S, S)
    for v in out1.values():
        assert float(v.min()) >= -1 and float(v.max()) <= 1 and torch.isfinite(v).all()
    assert float(out1["input"].std()) > 0.1
    bgr = x["mask"] < 0.5
    assert torch.all(out1["lightness"][bgr] == -1) and float(out1["lightness"][~bgr].std()) > 0.01
    # every sample replays alone
    sub = a.apply(select(x, [4, 1]), select_params(p1, [4, 1]))
    assert torch.allclose(sub["input"], out1["input"][[4, 1]], atol=1e-6)


@pytest.mark.parametrize("kw", [
    {"textures": ("perlin",), "backgrounds": ("perlin",)}, {"textures": ("voronoi",), "backgrounds": ("voronoi",)},
    {"textures": ("white",), "backgrounds": ("white",)}, {"textures": ("none",), "backgrounds": ("image",)},
    {"blurs": ("gaussian",)}, {"blurs": ("box",)}, {"blurs": ("median",)}, {"occluders": (3, 3)},
])
def test_every_augmentation_kind_is_deterministic_and_in_range(bank, kw):
    a = augmenter(bank=bank, **kw)
    x = sphere(4)
    o1, p = a(x, 11)
    o2, _ = a(x, 11)
    assert torch.equal(o1["input"], o2["input"])
    assert float(o1["input"].min()) >= -1 and float(o1["input"].max()) <= 1
    assert o1["input"].shape == (4, 3, S, S)


def test_light_directions_respect_their_angle_range(bank):
    p = augmenter(bank=bank, light_angle_deg=(10.0, 40.0)).draw(200, 0)
    assert torch.allclose(p["light"].norm(dim=1), torch.ones(200), atol=1e-6)
    angle = torch.rad2deg(torch.acos(-p["light"][:, 2]))                    # from the camera's side
    assert float(angle.min()) >= 10 - 1e-3 and float(angle.max()) <= 40 + 1e-3
    for name, (lo, hi) in {"ambient": (0.05, 0.3), "diffuse": (0.1, 0.8), "specular": (0.0, 0.1)}.items():
        assert p[name].shape == (200, 3) and float(p[name].min()) >= lo and float(p[name].max()) <= hi


def test_textures_are_indexed_by_the_normals(bank):
    """Pixels with the same normal get the same hue and saturation wherever they are."""
    a = augmenter(bank=bank, textures=("perlin", "voronoi", "white"), occluders=(0, 0), blurs=("none",))
    x = sphere(6)
    n = torch.tensor([0.3, -0.2, -0.9])
    x["normals"] = (n / n.norm()).view(1, 3, 1, 1).expand(6, 3, S, S).contiguous()
    rgb = (a(x, 3)[0]["input"] + 1) / 2
    import kornia
    hls = kornia.color.rgb_to_hls(rgb)
    fg = x["mask"][:, 0] > 0.5
    for i in range(6):
        assert float(hls[i, 0][fg[i]].std()) < 1e-3 and float(hls[i, 2][fg[i]].std()) < 1e-3


def test_background_lightness_is_homogenised(bank):
    x = sphere(8)
    fg = x["mask"] > 0.5
    gap = {}
    for on in (True, False):
        a = augmenter(bank=bank, occluders=(0, 0), blurs=("none",), homogenise_background=on)
        out = a(x, 9)[0]
        import kornia
        light = kornia.color.rgb_to_hls((out["input"] + 1) / 2)[:, 1:2]
        gap[on] = [float(light[i][~fg[i]].mean() - light[i][fg[i]].mean()) for i in range(8)]
    assert np.mean(np.abs(gap[True])) < 0.05 < np.mean(np.abs(gap[False]))


@pytest.mark.parametrize("kind", ["gaussian", "box", "median"])
def test_blur_smooths_the_same_draw(bank, kind):
    """The draws do not depend on the allowed kinds' count, so one seed gives the same image
    with and without blur: blur lowers the total variation."""
    x = sphere(4)
    sharp = augmenter(bank=bank, blurs=("none",))(x, 5)[0]["input"]
    blurred = augmenter(bank=bank, blurs=(kind,))(x, 5)[0]["input"]
    tv = lambda t: (t[..., 1:, :] - t[..., :-1, :]).abs().mean() + (t[..., 1:] - t[..., :-1]).abs().mean()  # noqa
    assert float(tv(blurred)) < 0.9 * float(tv(sharp))


def test_occluders_cover_the_polygons(bank):
    a = augmenter(bank=bank, occluders=(2, 2), blurs=("none",))
    x = sphere(3)
    p = a.draw(3, 2)
    bare = dict(p, **{"occ.count": torch.zeros_like(p["occ.count"])})         # the same draw without them
    covered = polygon_masks(p["occ.verts"], S, S).amax(1, keepdim=True) > 0
    diff = (a.apply(x, p)["input"] - a.apply(x, bare)["input"]).abs().amax(1, keepdim=True) > 1e-6
    assert torch.equal(diff & ~covered, torch.zeros_like(diff))             # only polygons change
    assert covered.sum() > 0 and (diff & covered).sum() > 0.9 * covered.sum()


def test_depth_domain_with_sensor_hook(bank):
    calls = []

    def hook(d, seeds):
        calls.append(seeds.clone())
        g = torch.Generator().manual_seed(int(seeds[0]) % 2 ** 31)
        return d + 0.01 * torch.randn(d.shape, generator=g)

    a = augmenter("depth", bank=bank, hook=hook)
    x = sphere(3)
    o1, p = a(x, 4)
    o2 = a.apply(x, p)
    assert torch.equal(o1["input"], o2["input"]) and set(o1) == {"input", "target"}
    assert o1["input"].shape == (3, 1, S, S) and float(o1["input"].abs().max()) <= 1
    assert len(calls) == 2 and torch.equal(calls[0], p["sensor.seed"])
    no_hook = augmenter("depth", bank=bank).apply(x, p)["input"]
    assert not torch.equal(no_hook, o1["input"])


def test_depth_measured_input_and_kept_background(bank):
    """With measured inputs: a kept background is the measured one in the input and the clean one in the
    target; a replaced one is the same procedural depth in both; the target never has occluders or blur."""
    x = sphere(4)
    measured = (x["depth"] + 0.05).clamp(-1, 1)
    a = augmenter("depth", bank=bank, occluders=(0, 0), blurs=("none",))
    p = a.draw(4, 7)
    p["bg.keep"] = torch.tensor([True, False, True, False])
    out = a.apply({**x, "measured": measured}, p)
    assert torch.equal(out["input"][0], measured[0]) and torch.equal(out["target"][0], x["depth"][0])
    m = x["mask"][1] > 0.5
    assert torch.equal(out["target"][1][~m], out["input"][1][~m])
    assert torch.allclose(out["input"][1][m], measured[1][m]) and torch.equal(out["target"][1][m], x["depth"][1][m])


def test_bad_augmentation_input_is_one_line(bank):
    a = augmenter(bank=bank)
    with pytest.raises(RealgapError) as e:
        a({"normals": torch.zeros(2, 3, 16, 16), "mask": torch.zeros(2, 1, 16, 16)}, 0)
    assert "mask of shape (B, 1, 32, 32), got (2, 1, 16, 16)" in one_line(e)


@pytest.mark.slow
def test_image_bank_of_scikit_image():
    """The default backgrounds: the colour and grey sample images scikit-image ships (~5 s)."""
    bank = load_image_bank("skimage")
    assert bank.shape[0] >= 10 and bank.shape[1:] == (3, 128, 128)
    assert float(bank.min()) >= 0 and float(bank.max()) <= 1 and float(bank.std()) > 0.1


def test_image_bank_from_a_folder(tmp_path):
    from PIL import Image
    Image.fromarray(np.full((20, 30, 3), 200, np.uint8)).save(tmp_path / "a.png")
    Image.fromarray(np.full((10, 10), 50, np.uint8)).save(tmp_path / "b.png")
    bank = load_image_bank(str(tmp_path), side=16)
    assert bank.shape == (2, 3, 16, 16)
    assert torch.allclose(bank[0], torch.full_like(bank[0], 200 / 255), atol=1e-3)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(RealgapError) as e:
        load_image_bank(str(empty))
    assert "no background images" in one_line(e)


# ------------------------------------------------------------------------------------------ model
ABLATIONS = {
    "full": {}, "no_distillation": {"distillation": False}, "no_attention": {"attention": False},
    "no_skips": {"skips": False}, "triplet": {"triplet": True}, "normals_only": {"decoders": ("normals",)},
    "normals_mask": {"decoders": ("normals", "mask")},
    "normals_only_no_distillation": {"decoders": ("normals",), "distillation": False},
    "mask_classes": {"mask_classes": 4},
}


@pytest.mark.parametrize("name", list(ABLATIONS))
@pytest.mark.parametrize("domain", ["rgb", "depth"])
def test_generator_output_shapes_for_every_ablation(name, domain):
    cfg = dataclasses.replace(TINY, **ABLATIONS[name])
    if domain == "depth":
        cfg = dataclasses.replace(cfg, decoders=tuple(m for m in cfg.decoders if m != "lightness"), target="depth")
        if not cfg.distillation and "depth" not in cfg.decoders:
            cfg = dataclasses.replace(cfg, decoders=cfg.decoders + ("depth",))
    net = Generator(cfg, domain)
    out = net(torch.rand(3, 3 if domain == "rgb" else 1, 16, 16) * 2 - 1)
    expect = {m: cfg.channels(m) for m in cfg.decoders} | {"output": cfg.channels(cfg.target)}
    assert {k: v.shape for k, v in out.items() if k != "code"} == {k: (3, c, 16, 16) for k, c in expect.items()}
    assert ("code" in out) == cfg.triplet and (not cfg.triplet or out["code"].shape == (3, 8))
    assert float(out["output"].detach().abs().max()) <= 1
    assert (net.distiller is None) == (not cfg.distillation)
    if cfg.distillation:
        has_sa = any(isinstance(m, SelfAttention) for m in net.distiller.modules())
        assert has_sa == cfg.attention


@pytest.mark.parametrize("preset", ["cpu", "gpu"])
def test_preset_generators_follow_figure_5_4(preset):
    """Shapes only (on torch's meta device: no memory, no arithmetic): encoder 64 -> 1x1 code,
    the gpu decoder's concatenated blocks 2x2x1024 ... 32x32x128 as in Fig. 5.4."""
    cfg = synda_preset(preset, "rgb")
    with torch.device("meta"):
        net = Generator(cfg.generator, "rgb")
        x = torch.empty(2, 3, 64, 64)
        feats = net.encode(x)
        seen = []
        dec = net.decoders["normals"]
        net_out = dec(feats)
        y = feats[-1]
        for i, block in enumerate(dec.blocks[:-1]):
            y = torch.cat([block(y), feats[len(feats) - 2 - i]], 1)
            seen.append(tuple(y.shape[1:]))
    w = cfg.generator.widths
    assert [tuple(f.shape[1:]) for f in feats] == [(c, 64 >> (i + 1), 64 >> (i + 1)) for i, c in enumerate(w)]
    assert net_out.shape == (2, 3, 64, 64)
    if preset == "gpu":
        assert seen == [(1024, 2, 2), (1024, 4, 4), (512, 8, 8), (256, 16, 16), (128, 32, 32)]


def test_cpu_depth_generator_fits_the_shipping_budget():
    """The generator shipped for the depth domain must stay under 20 MB (float32 weights)."""
    cfg = synda_preset("cpu", "depth")
    with torch.device("meta"):
        net = Generator(cfg.generator, "depth")
    size = sum(t.numel() * 4 for t in list(net.parameters()) + list(net.buffers()) if t.is_floating_point())
    assert size < 20e6


def test_skips_change_the_decoder_inputs():
    with_skips = Generator(TINY)
    without = Generator(dataclasses.replace(TINY, skips=False))
    n = lambda g: sum(p.numel() for p in g.decoders["normals"].parameters())  # noqa: E731
    assert n(with_skips) > n(without)


def test_self_attention_starts_as_identity_and_then_mixes_positions():
    sa = SelfAttention(16)
    x = torch.randn(1, 16, 4, 4)
    assert torch.equal(sa(x), x)
    with torch.no_grad():
        sa.gamma.fill_(1.0)
        y1 = sa(x)
        x2 = x.clone()
        x2[0, :, 0, 0] += 5.0
        y2 = sa(x2)
    assert float((y2 - y1)[0, :, 3, 3].abs().max()) > 1e-4                   # a far position changes


def test_a_few_steps_lower_the_loss(bank):
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, triplet=True)
    net = Generator(cfg)
    a = Augmenter(AugmentConfig(), "rgb", 16, images=bank)
    x = sphere(6, 16)
    aug = a(x, 0)[0]
    targets = {"normals": x["normals"], "depth": x["depth"], "mask": x["mask"], "lightness": aug["lightness"]}
    opt = torch.optim.Adam(net.parameters(), 2e-3, betas=(0.5, 0.999))
    losses = []
    for _ in range(15):
        out = net(aug["input"])
        loss, parts = generator_loss(out, targets, cfg.target)
        c = out["code"]
        loss = loss + bottleneck_triplet_loss(c[:2], c[2:4], c[4:], torch.full((2,), 4.0))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert set(parts) == {"normals", "depth", "mask", "lightness", "output"}
    assert losses[-1] < 0.7 * losses[0]


def test_losses():
    t = torch.rand(2, 3, 4, 4) * 2 - 1
    assert float(modality_loss("normals", t + 0.5, t)) == pytest.approx(0.5)
    m = (torch.rand(2, 1, 4, 4) > 0.5).float()
    assert float(modality_loss("mask", (m * 2 - 1) * 20, m)) < 1e-6          # confident and right
    assert float(modality_loss("mask", torch.zeros(2, 1, 4, 4), m)) == pytest.approx(math.log(2), rel=1e-5)
    cls = torch.randint(0, 3, (2, 1, 4, 4))
    assert float(modality_loss("mask", torch.zeros(2, 3, 4, 4), cls)) == pytest.approx(math.log(3), rel=1e-5)
    # without distillation the output is the target decoder's map: counted once
    out = {"normals": t + 0.5, "output": None}
    out["output"] = out["normals"]
    total, parts = generator_loss(out, {"normals": t}, "normals")
    assert float(total) == pytest.approx(0.5) and set(parts) == {"normals"}
    with pytest.raises(RealgapError) as e:
        generator_loss({"depth": t[:, :1], "output": t}, {"normals": t}, "normals")
    assert "no ground truth for depth" in one_line(e)


# ------------------------------------------------------------------------------------------ save / load
def _tiny_config(domain="rgb") -> SyndaConfig:
    cfg = synda_preset("cpu", domain)
    gen = dataclasses.replace(TINY, decoders=cfg.generator.decoders, target=cfg.generator.target)
    return dataclasses.replace(cfg, generator=gen).validate()


def test_save_load_gives_identical_outputs(tmp_path):
    cfg = _tiny_config("depth")
    torch.manual_seed(1)
    net = Generator(cfg.generator, "depth")
    with torch.no_grad():                                                     # non-trivial state
        for m in net.modules():
            if isinstance(m, SelfAttention):
                m.gamma.fill_(0.7)
    net.train()
    net(torch.rand(4, 1, 16, 16))                                             # moves the batch-norm stats
    net.eval()
    x = torch.rand(2, 1, 16, 16) * 2 - 1
    ref = net(x)
    path = save_generator(tmp_path / "gen.pt", net, cfg, {"seed": 1})
    net2, cfg2, info = load_generator(path, "depth")
    out = net2(x)
    assert cfg2 == cfg and info == {"seed": 1}
    assert all(torch.equal(ref[k], out[k]) for k in ref)


def test_bad_generator_files_are_one_line(tmp_path):
    cfg = _tiny_config("rgb")
    net = Generator(cfg.generator, "rgb")
    path = save_generator(tmp_path / "gen.pt", net, cfg)
    with pytest.raises(RealgapError) as e:
        load_generator(path, "depth")
    assert "for 'rgb' inputs, 'depth' needed" in one_line(e) and "gen.pt" in one_line(e)
    blob = torch.load(path, weights_only=True)
    blob["version"] = GENERATOR_VERSION + 1
    torch.save(blob, tmp_path / "new.pt")
    with pytest.raises(RealgapError) as e:
        load_generator(tmp_path / "new.pt")
    assert "version" in one_line(e) and "new.pt" in one_line(e)
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(RealgapError) as e:
        load_generator(tmp_path / "junk.pt")
    assert "not a SynDA generator" in one_line(e)
    with pytest.raises(RealgapError) as e:
        load_generator(tmp_path / "missing.pt")
    assert "not found" in one_line(e)
    blob = torch.load(path, weights_only=True)
    blob["config"]["generator"]["widths"] = [4, 8, 8, 16]
    torch.save(blob, tmp_path / "mismatch.pt")
    with pytest.raises(RealgapError) as e:
        load_generator(tmp_path / "mismatch.pt")
    assert "weights do not fit" in one_line(e)


@pytest.mark.parametrize("shape", [(2, 1, 16, 16), (2, 3, 32, 32), (3, 16, 16), (2, 4, 16, 16)])
def test_wrong_image_size_or_channels_is_one_line(shape):
    net = Generator(TINY, "rgb")
    with pytest.raises(RealgapError) as e:
        net(torch.zeros(shape))
    assert "(B, 3, 16, 16)" in one_line(e)


@pytest.mark.parametrize("domain", ["depth", "rgb"])
def test_ablation_variants_change_one_switch_each(domain):
    """Table 5.4's variants (recog/synda/evaluate.py, run by benchmarks/bench_synda.py --ablation): each is the
    cpu preset with its one switch flipped, in either domain; without the auxiliary decoders only the target's
    decoder is left."""
    from recog.synda.evaluate import ABLATIONS, ablation_config
    full = ablation_config("full", domain, "depth", 10, 0).generator
    assert full.target == "depth" and full.distillation and full.attention and full.skips and not full.triplet
    changed = {}
    for name in ABLATIONS:
        g = ablation_config(name, domain, "depth", 10, 0).generator
        changed[name] = {f for f in ("decoders", "distillation", "attention", "skips", "triplet")
                         if getattr(g, f) != getattr(full, f)}
    assert changed == {"full": set(), "no_aux_decoders": {"decoders"}, "no_distillation": {"distillation"},
                       "no_attention": {"attention"}, "no_skips": {"skips"}, "with_triplet": {"triplet"}}
    assert ablation_config("no_aux_decoders", domain, "depth", 10, 0).generator.decoders == ("depth",)


def test_ablation_training_keeps_no_checkpoint_across_variants(tmp_path, monkeypatch):
    """``train_ablation``: a variant that fails is reported with its one line and leaves no checkpoint for the
    next variant to resume; a generator file already there is kept (a re-run continues with the next variant)."""
    import recog.synda.run as run
    from recog.synda.evaluate import ablation_file, train_ablation
    seen = []

    def fake_train(objects, gen, cfg, views, *, work, **kw):
        seen.append((gen.name, (work / "checkpoint.pt").exists()))
        work.mkdir(parents=True, exist_ok=True)
        (work / "checkpoint.pt").write_text("this variant's")
        if not cfg.generator.skips:
            raise RealgapError("no_skips failed")
        gen.write_text("generator")

    monkeypatch.setattr(run, "train_synda", fake_train)
    ablation_file(tmp_path, "full").write_text("kept")
    res = train_ablation("chairs", tmp_path, ["full", "no_skips", "no_attention"], log=lambda m: None)
    assert res["no_skips"] == {"error": "no_skips failed"} and "train_s" in res["no_attention"]
    assert seen == [("ablation_no_skips.pt", False), ("ablation_no_attention.pt", False)]
    assert ablation_file(tmp_path, "full").read_text() == "kept"
    assert not (tmp_path / "work" / "checkpoint.pt").exists()
