"""SynDA's optional descriptor-space (feature-matching) and object-weighted losses, and training from a generator
file (recog/synda/loss.py, train.py; ``synda train --descriptor-weight / --object-weight / --init``)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from data_tools.errors import RealgapError
from recog.synda.augment import Augmenter
from recog.synda.config import SyndaConfig
from recog.synda.io import save_generator
from recog.synda.loss import descriptor_loss, object_l1
from recog.synda.model import Generator
from recog.synda.train import evaluate_batch_loss, load_descriptor_net, train_generator
from tests.test_synda_train import S, boxes, config, one_thread  # noqa: F401  (autouse: one torch thread)


def tiny_recogniser(folder, size: int = S, crop_m: float = 0.5):
    """A LeNet recogniser folder (untrained, seed 0, its last layer x 30 so that its descriptors vary by units as a
    trained one's do, not by hundredths) reading ``size`` px patches of ``crop_m`` m."""
    from recog.data import DataConfig
    from recog.database import DescriptorDB
    from recog.model import Recogniser
    from recog.net import make_network
    from recog.patches import PatchConfig
    from recog.train import TrainConfig
    torch.manual_seed(0)
    net = make_network("lenet", size, 8).eval()
    with torch.no_grad():
        net.head[-1].weight.mul_(30.0)
    db = DescriptorDB(np.zeros((1, 8), np.float32), np.zeros(1, np.int64), np.eye(3)[None], np.zeros((1, 3)),
                      np.zeros(1, np.int64))
    obj = {"name": "box", "source": "embedded:chairs", "scale": 1.0, "symmetry": {"axis": None, "order": 1},
           "diameter_m": 0.4}
    Recogniser([obj], net, db, PatchConfig(size=size, crop_m=crop_m), DataConfig(),
               TrainConfig(network="lenet", descriptor=8)).save(folder)
    return folder


def with_losses(cfg: SyndaConfig, **train) -> SyndaConfig:
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **train)).validate()


def test_losses_are_hand_values():
    """object_l1: mean |pred - target| over the masked pixels only; descriptor_loss with the identity
    'network' (flatten): l2 = sum of squared differences, l1 = sum of absolute ones, averaged over the batch."""
    pred = torch.zeros(2, 1, 2, 2)
    tgt = torch.tensor([[1.0, 2.0], [3.0, 4.0]]).expand(2, 1, 2, 2)
    mask = torch.tensor([[1.0, 0.0], [0.0, 1.0]]).expand(2, 1, 2, 2)
    assert float(object_l1(pred, tgt, mask)) == pytest.approx((1 + 4) / 2)
    assert float(object_l1(pred, tgt, torch.zeros_like(mask))) == 0.0
    flat = torch.nn.Flatten()
    assert float(descriptor_loss(flat, pred, tgt, "l2")) == pytest.approx(1 + 4 + 9 + 16)
    assert float(descriptor_loss(flat, pred, tgt, "l1")) == pytest.approx(10.0)


def test_descriptor_loss_pulls_descriptors_together_and_keeps_the_recogniser_frozen(tmp_path):
    """60 steps with the descriptor loss on lower the descriptor distance between h_G's output and the clean
    target on a fixed batch (below what the same steps without it reach), and leave the recogniser's weights,
    in memory and on disk, bit-identical."""
    folder = tiny_recogniser(tmp_path / "rec")
    dnet = load_descriptor_net(folder, S, 0.5)
    frozen = {k: v.clone() for k, v in dnet.state_dict().items()}
    data = boxes()
    base = config(iterations=60)
    on = with_losses(base, descriptor_weight=1.0, descriptor_recogniser=str(folder))
    aug = Augmenter(on.augment, on.domain, S)

    def distance(net):
        return evaluate_batch_loss(net, on, data, aug, seed=5, descriptor_net=dnet)["descriptor"]

    torch.manual_seed(on.train.seed)
    before = distance(Generator(on.generator, on.domain).eval())
    net_on, log = train_generator(on, data, progress=False, log_every=10, descriptor_net=dnet)
    net_off, _ = train_generator(base, data, progress=False, log_every=10)
    after_on, after_off = distance(net_on), distance(net_off)
    assert after_on < 0.85 * before and after_on < 0.9 * after_off, (before, after_on, after_off)
    assert "descriptor" in log.steps[-1]
    for k, v in dnet.state_dict().items():
        assert torch.equal(v, frozen[k]), k
    reloaded = load_descriptor_net(folder, S)
    for k, v in reloaded.state_dict().items():
        assert torch.equal(v, frozen[k]), k
    # loaded from the config's path when no network is passed: the same run
    five = with_losses(on, iterations=5)
    net_a, _ = train_generator(five, data, progress=False, descriptor_net=dnet)
    net_b, _ = train_generator(five, data, progress=False)
    for (k, a), (_, b) in zip(net_a.state_dict().items(), net_b.state_dict().items()):
        assert torch.equal(a, b), k


def test_object_weight_lowers_the_error_on_the_object():
    data = boxes()
    on = with_losses(config(iterations=30), object_weight=5.0)
    aug = Augmenter(on.augment, on.domain, S)
    a, _ = train_generator(on, data, progress=False)
    b, _ = train_generator(config(iterations=30), data, progress=False)
    obj = [evaluate_batch_loss(n, on, data, aug, seed=5)["object"] for n in (a, b)]
    assert obj[0] < obj[1], obj


def test_init_starts_from_the_file(tmp_path):
    """One step at a vanishing learning rate from --init's file leaves its weights (the run starts from them,
    not from the seed's); a file of another architecture is a one-line error."""
    data = boxes()
    cfg = config(iterations=1)
    torch.manual_seed(123)
    g = Generator(cfg.generator, "depth").eval()
    save_generator(tmp_path / "g.pt", g, cfg, {})
    tiny = with_losses(cfg, lr=1e-12)
    net, _ = train_generator(tiny, data, progress=False, init=tmp_path / "g.pt")
    for (k, a), (_, b) in zip(g.state_dict().items(), net.state_dict().items()):
        if a.dtype.is_floating_point and "running" not in k:
            assert torch.allclose(a, b, atol=1e-6), k
    other = dataclasses.replace(cfg, generator=dataclasses.replace(cfg.generator, distill_width=8)).validate()
    save_generator(tmp_path / "o.pt", Generator(other.generator, "depth"), other, {})
    with pytest.raises(RealgapError, match="architecture differs"):
        train_generator(cfg, data, progress=False, init=tmp_path / "o.pt")


def test_bad_recogniser_is_one_line(tmp_path, capsys):
    from app.cli import main
    with pytest.raises(RealgapError, match="not a recogniser folder"):
        load_descriptor_net(tmp_path / "nope", S)
    folder = tiny_recogniser(tmp_path / "rec")
    with pytest.raises(RealgapError, match="reads 16 px patches of 0.5 m, the generator's are 64 px"):
        load_descriptor_net(folder, 64)
    with pytest.raises(RealgapError, match="of 0.5 m, the generator's are 16 px of 0.7 m"):
        load_descriptor_net(folder, S, 0.7)
    with pytest.raises(RealgapError, match="needs descriptor_recogniser"):
        with_losses(config(), descriptor_weight=1.0)
    assert main(["synda", "train", "--objects", "chairs", "--domain", "depth", "--out", str(tmp_path / "g.pt"),
                 "--descriptor-weight", "1", "--descriptor-recogniser", str(tmp_path / "nope"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not a recogniser folder" in err and "nope" in err
    assert main(["synda", "train", "--objects", "chairs", "--domain", "depth", "--out", str(tmp_path / "g.pt"),
                 "--descriptor-weight", "1", "--descriptor-recogniser", str(folder), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "reads 16 px patches" in err


def test_bad_init_fails_before_any_view_is_simulated(tmp_path, capsys):
    """``synda train --init`` with a generator of the other domain is a one-line error before the views are
    simulated (the work folder stays empty), and so is --device cuda on a machine without a GPU."""
    from app.cli import main
    cfg = config(iterations=1)
    rgb = dataclasses.replace(cfg, domain="rgb").validate()
    save_generator(tmp_path / "rgb.pt", Generator(rgb.generator, "rgb"), rgb, {})
    work = tmp_path / "work"
    assert main(["synda", "train", "--objects", "chairs", "--domain", "depth", "--init", str(tmp_path / "rgb.pt"),
                 "--work", str(work), "--out", str(tmp_path / "g.pt"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "rgb.pt" in err, err
    assert not (work / "data").exists() or not any((work / "data").iterdir())
    if not torch.cuda.is_available():
        assert main(["synda", "train", "--objects", "chairs", "--domain", "depth", "--device", "cuda",
                     "--work", str(work), "--out", str(tmp_path / "g.pt"), "--no-progress"]) == 1
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "no GPU" in err, err
        assert not (work / "data").exists() or not any((work / "data").iterdir())
