"""The colour recogniser (``recog train --input rgb``, SynDA's A-trained colour baseline): networks with an input
channel count, the shipped 1-channel recogniser unchanged, A's colour renders of the training views, a few
deterministic training steps, ``recog train`` / ``recog eval`` on colour, and one-line errors for a patch of the
wrong channel count."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from app.cli import main  # noqa: E402
from data_tools.errors import ConfigError, RealgapError  # noqa: E402
from recog.data import TrainingData  # noqa: E402
from recog.net import check_input, make_network  # noqa: E402
from recog.train import TrainConfig, colour_renderer, render_colour_views, train_network  # noqa: E402


def _pattern(n: int, s: int = 64) -> np.ndarray:
    yy, xx = np.mgrid[0:s, 0:s] / (s - 1.0)
    return np.stack([np.clip(np.sin(6 * xx + k) * np.cos(4 * yy - k), -1, 1) for k in range(n)]).astype(np.float32)


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], np.float32)


def _views(s: int = 32, per: int = 5) -> TrainingData:
    """Two hand-made objects seen from ``per`` in-plane angles each, 2 identical (clean) draws: a hemisphere (disc
    mask) and a tilted plate (square mask), on a flat background at +1; masks are the object's pixels."""
    yy, xx = (np.mgrid[0:s, 0:s] - (s - 1) / 2) / (s / 2)
    patches, masks, obj, R = [], [], [], []
    for o in range(2):
        for v in range(per):
            a = np.radians(360 * v / per)
            u, w = np.cos(a) * xx - np.sin(a) * yy, np.sin(a) * xx + np.cos(a) * yy
            if o == 0:
                m = xx ** 2 + yy ** 2 < 0.5
                d = np.where(m, -np.sqrt(np.clip(0.5 - xx ** 2 - yy ** 2, 0, None)), 1.0)
            else:
                m = (np.abs(u) < 0.55) & (np.abs(w) < 0.35)
                d = np.where(m, 0.3 * u - 0.2, 1.0)
            patches.append(np.stack([d, d]))
            masks.append(m)
            obj.append(o)
            R.append(_rz(360 * v / per))
    n = len(obj)
    return TrainingData(np.asarray(patches, np.float16), np.asarray(obj), np.tile(np.arange(per), 2),
                        np.asarray(R), np.zeros((n, 2, 3), np.float32), ["ball", "plate"], np.asarray(masks))


def test_networks_take_a_channel_count():
    """A 3-channel network maps (B, 3, S, S) to (B, d); only the first convolution's shape depends on the channels;
    the 1-channel network is built (and initialised) as before the option: the same weights for the same seed."""
    for name in ("lenet", "deeper"):
        net = make_network(name, 64, 16, channels=3).eval()
        assert net.channels == 3
        with torch.no_grad():
            assert tuple(net(torch.zeros(2, 3, 64, 64)).shape) == (2, 16)
        first = next(iter(net.parameters()))
        assert first.shape[1] == 3
        torch.manual_seed(5)
        a = make_network(name, 64, 16).state_dict()
        torch.manual_seed(5)
        b = make_network(name, 64, 16, channels=1).state_dict()
        assert list(a) == list(b) and all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ConfigError, match="1 \\(depth\\) or 3 \\(colour\\)"):
        make_network("lenet", 64, 16, channels=2)


def test_shipped_depth_recogniser_loads_unchanged():
    """The shipped recogniser (recorded before networks took a channel count) loads as a 1-channel depth network and
    gives the descriptors it gave then (values recorded from the previous code, 1e-5)."""
    from recog.model import Recogniser
    m = Recogniser.load("recog/weights/chairs")
    assert m.input == "depth" and m.net.channels == 1
    d = m.describe(_pattern(4))
    before = [[0.0285689, -0.6415952, 1.0301473, -0.8164163], [0.0778206, -1.9329433, 0.2817168, -1.0032538],
              [0.0284192, -0.8175977, 0.4040366, -0.517882], [0.0074905, -0.3841071, 1.0502193, -0.6628705]]
    np.testing.assert_allclose(d[:, :4], before, atol=1e-5)
    np.testing.assert_array_equal(m.describe(_pattern(4)[:, None]), d)     # (N, 1, S, S) is the same input


def test_colour_renders_are_seeded_and_follow_the_mask():
    """A's colour renders of depth patches: (B, 3, S, S) in [-1, 1], a function of the seed; the object's pixels
    come from the shading of its normals (they change with the depth patch); one render of every view and draw,
    deterministic for a seed; views without masks are a one-line error."""
    td = _views()
    render = colour_renderer(td, 32)
    x = torch.from_numpy(td.patches[:4, 0].astype(np.float32))[:, None]
    rows = np.arange(4)
    a, b, c = render(x, rows, 3), render(x, rows, 3), render(x, rows, 4)
    assert a.shape == (4, 3, 32, 32) and float(a.min()) >= -1 and float(a.max()) <= 1
    assert torch.equal(a, b) and not torch.equal(a, c)
    flat = render(torch.ones_like(x) * -0.5, rows, 3)       # same seed and masks, other depth: only the object differs
    m = torch.from_numpy(td.mask[:4])[:, None].expand_as(a)
    assert float((a[m] - flat[m]).abs().mean()) > 0.01
    views = render_colour_views(td, 32, seed=9, batch=4)
    assert views.shape == (10, 2, 3, 32, 32)
    np.testing.assert_array_equal(views, render_colour_views(td, 32, seed=9, batch=4))
    with pytest.raises(ConfigError, match="object masks"):
        colour_renderer(dataclasses.replace(td, mask=None), 32)


def test_colour_training_is_deterministic_for_a_seed():
    """A few steps of the project's training loop on A's colour renders: a 3-channel network, finite losses, the
    same weights for the same seed, other weights for another seed; and it learns (loss of the last steps below the
    first ones on this easy two-object set)."""
    td = _views()
    cfg = dataclasses.replace(TrainConfig(), input="rgb", iterations=3, batch=8, log_every=1, descriptor=16)
    syms = [None, None]
    n1, log1 = train_network(td, syms, cfg, 32, progress=False)
    n2, _ = train_network(td, syms, cfg, 32, progress=False)
    n3, _ = train_network(td, syms, dataclasses.replace(cfg, seed=1), 32, progress=False)
    w1, w2, w3 = n1.state_dict(), n2.state_dict(), n3.state_dict()
    assert n1.channels == 3 and w1["features.0.weight"].shape[1] == 3
    assert all(torch.equal(w1[k], w2[k]) for k in w1) and not all(torch.equal(w1[k], w3[k]) for k in w1)
    assert len(log1.steps) == 3 and all(np.isfinite(s["loss"]) for s in log1.steps)
    with pytest.raises(ConfigError, match="synda-augment"):
        dataclasses.replace(cfg, synda_augment=0.5).validate()


def test_checkpoint_records_the_input(tmp_path):
    """A training checkpoint records what the network reads: continuing a depth run as a colour one (or the reverse)
    is a one-line error naming the checkpoint, and a colour run resumed from its checkpoint ends with the weights of
    an uninterrupted one."""
    td = _views()
    syms = [None, None]
    depth = dataclasses.replace(TrainConfig(), iterations=2, batch=4, checkpoint_every=1, descriptor=8)
    ck = tmp_path / "checkpoint.pt"
    train_network(td, syms, depth, 32, checkpoint=ck, progress=False)
    with pytest.raises(RealgapError) as e:
        train_network(td, syms, dataclasses.replace(depth, input="rgb"), 32, checkpoint=ck, progress=False)
    assert "\n" not in str(e.value) and "input" in str(e.value) and str(ck) in str(e.value)
    rgb = dataclasses.replace(depth, input="rgb", iterations=4, checkpoint_every=2)
    whole = train_network(td, syms, rgb, 32, progress=False)[0].state_dict()
    ck2 = tmp_path / "rgb.pt"
    train_network(td, syms, dataclasses.replace(rgb, iterations=2), 32, checkpoint=ck2, progress=False)
    resumed, log = train_network(td, syms, rgb, 32, checkpoint=ck2, progress=False)
    assert log.resumed_from == 2
    assert all(torch.equal(whole[k], resumed.state_dict()[k]) for k in whole)


def test_colour_recogniser_train_eval_and_wrong_channels(tmp_path, capsys):
    """``recog train --input rgb`` builds a 3-channel recogniser whose database holds A renders (its json records
    the input); ``recog eval`` reads a colour test set's colour images with it; a depth test set, a SynDA generator
    in front of it, or a patch of the wrong channel count are one-line errors; weights of another channel count
    than recogniser.json says are a one-line error at load."""
    import trimesh

    from recog.model import Recogniser
    objs = []
    for name, ext in (("box", (0.10, 0.06, 0.05)), ("slab", (0.12, 0.03, 0.03))):
        trimesh.creation.box(extents=ext).export(tmp_path / f"{name}.ply")
        objs.append(str(tmp_path / f"{name}.ply"))
    model = tmp_path / "m"
    assert main(["recog", "train", "--objects", ",".join(objs), "--variant", "clean", "--input", "rgb",
                 "--out", str(model), "--subdivisions", "0", "--iterations", "4", "--batch", "8", "--workers", "1",
                 "--no-progress"]) == 0
    m = Recogniser.load(model)
    assert m.input == "rgb" and m.net.channels == 3
    assert json.loads((model / "recogniser.json").read_text())["train"]["input"] == "rgb"
    n = len(m.db)
    assert n > 0 and np.isfinite(m.db.descriptors).all()
    # a patch of the wrong channel count, in both directions
    for bad, net_model in ((_pattern(2, 64), m), (np.zeros((2, 3, 64, 64), np.float32), Recogniser.load(
            "recog/weights/chairs"))):
        with pytest.raises(ConfigError) as e:
            net_model.describe(bad)
        assert "\n" not in str(e.value) and "channel" in str(e.value)
    with pytest.raises(ConfigError, match="reads 3-channel colour patches"):
        check_input(m.net, torch.zeros(1, 1, 64, 64))
    # eval on colour scans: a colour test set of the two boxes
    ts = tmp_path / "ts"
    assert main(["synda", "testset", "--objects", ",".join(objs), "--per-object", "1", "--out", str(ts),
                 "--no-progress"]) == 0
    out = tmp_path / "e"
    assert main(["recog", "eval", str(model), str(ts), "--no-icp", "--out", str(out), "--no-progress"]) == 0
    r = json.loads((out / "eval.json").read_text())
    assert r["n_scans"] == 2 and 0 <= r["accuracy_descriptor"] <= 1
    from app.viewer.data import RecogSession          # the viewer shows the colour patch the descriptor read
    view = RecogSession(out, ts).scan(0)
    assert view["patch"].shape == (64, 64, 3) and "mapped" not in view
    assert view["predicted"] == json.loads((out / "predictions.jsonl").read_text().splitlines()[0])["predicted"]
    capsys.readouterr()
    assert main(["recog", "eval", str(model), str(ts), "--synda", "recog/weights/synda_depth/generator.pt",
                 "--no-icp", "--json", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "this recogniser reads colour" in err, err
    labels = json.loads((ts / "labels.json").read_text())
    (ts / "labels.json").write_text(json.dumps([{k: v for k, v in x.items() if k != "rgb"} for x in labels]))
    assert main(["recog", "eval", str(model), str(ts), "--no-icp", "--json", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "this recogniser reads colour" in err and "labels.json" in err
    # weights of 3 channels with recogniser.json saying depth
    meta = json.loads((model / "recogniser.json").read_text())
    meta["train"]["input"] = "depth"
    (model / "recogniser.json").write_text(json.dumps(meta))
    with pytest.raises(RealgapError) as e:
        Recogniser.load(model)
    assert "\n" not in str(e.value) and "weights.pt" in str(e.value)
