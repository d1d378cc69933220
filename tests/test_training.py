"""data_tools.training: the one training loop (log cadence, running means, checkpoint cadence, lr schedule) and
its checkpoint file (an interrupted run resumed ends where an uninterrupted one does)."""
from __future__ import annotations

import numpy as np
import pytest

from data_tools.training import LossMeans, TrainingState, linear_ramp, run_steps


class _Saves:
    def __init__(self):
        self.steps = []

    def save(self, step, log):
        self.steps.append((step, len(log)))


def test_log_and_checkpoint_cadence_and_means_by_hand():
    hist, saves, lrs = [], _Saves(), []
    run_steps(lambda s: {"a": float(s), **({"b": 1.0} if s >= 4 else {})}, 7, history=hist, log_every=3,
              log_also=(5,), state=saves, checkpoint_every=2, lr=lrs.append, progress=False)
    # records after steps 3, 5 (log_also), 6 and 7 (the last); a mean over the steps since the last record
    assert hist == [{"step": 3, "a": 1.0}, {"step": 5, "a": 3.5, "b": 0.5}, {"step": 6, "a": 5.0, "b": 1.0},
                    {"step": 7, "a": 6.0, "b": 1.0}]
    assert saves.steps == [(2, 0), (4, 1), (6, 3), (7, 4)]         # every 2 before the last, then the last
    assert lrs == list(range(7))
    saves2 = _Saves()
    run_steps(lambda s: {}, 7, start=5, state=saves2, checkpoint_every=2, save_last=False, progress=False)
    assert saves2.steps == [(6, 0)]


def test_linear_ramp_and_loss_means():
    assert [linear_ramp(s, 6, 11, 0.5) for s in (0, 5, 6)] == [1.0, 1.0, 1.0]
    assert linear_ramp(8, 6, 11, 0.5) == pytest.approx(0.75) and linear_ramp(10, 6, 11, 0.5) == pytest.approx(0.5)
    assert linear_ramp(10, 0, 11, 0.5) == 1.0
    m = LossMeans()
    m.add({"x": 1.0})
    m.add({"x": 2.0, "y": 3.0})
    assert m.record(2) == {"step": 2, "x": 1.5, "y": 1.5} and m.record(3) == {"step": 3}


def test_training_state_resumes_exactly(tmp_path):
    torch = pytest.importorskip("torch")

    def train(path, stop=None):
        torch.manual_seed(0)
        net = torch.nn.Linear(3, 1)
        opt = torch.optim.Adam(net.parameters(), lr=0.1)
        rng = np.random.default_rng(1)
        state = TrainingState(path, {"net": net, "opt": opt}, rng)
        start, hist = state.resume() or (0, [])

        def step(s):
            if s == stop:
                raise KeyboardInterrupt
            x = torch.from_numpy(rng.normal(size=(4, 3)).astype(np.float32)) + torch.randn(4, 3)
            loss = (net(x) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            return {"loss": float(loss.detach())}
        run_steps(step, 10, start=start, history=hist, log_every=2, state=state, checkpoint_every=3, progress=False)
        return net, hist
    whole, hist = train(None)
    with pytest.raises(KeyboardInterrupt):
        train(tmp_path / "ck.pt", stop=7)
    again, hist2 = train(tmp_path / "ck.pt")
    assert hist2 == hist
    for a, b in zip(whole.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    from data_tools.errors import FormatError
    with pytest.raises(FormatError, match="bad.pt.*unreadable training checkpoint"):
        TrainingState(tmp_path / "bad.pt", {}, np.random.default_rng()).resume()


def test_resume_refuses_other_settings(tmp_path):
    """A checkpoint continues only under the settings it was trained with (a changed learning setting is a
    one-line error naming it); how long a run goes and how it reports may change (RESUMABLE_CHANGES)."""
    torch = pytest.importorskip("torch")
    import dataclasses

    from data_tools.errors import FormatError
    from data_tools.training import settings_of

    @dataclasses.dataclass
    class Inner:
        lr: float = 0.1
        sizes: tuple = (1, 2)

    @dataclasses.dataclass
    class Cfg:
        inner: Inner = dataclasses.field(default_factory=Inner)
        iterations: int = 10
        seed: int = 0

    assert settings_of(Cfg()) == {"inner.lr": 0.1, "inner.sizes": [1, 2], "seed": 0}

    def state(cfg):
        net = torch.nn.Linear(2, 1)
        return TrainingState(tmp_path / "ck.pt", {"net": net}, np.random.default_rng(0), settings=settings_of(cfg))
    state(Cfg()).save(3, [])
    assert state(Cfg(iterations=20)).resume()[0] == 3          # a longer run continues
    with pytest.raises(FormatError, match=r"ck.pt.*other settings \(inner.lr: 0.1 -> 0.2\)"):
        state(Cfg(inner=Inner(lr=0.2))).resume()
    legacy = TrainingState(tmp_path / "ck.pt", {"net": torch.nn.Linear(2, 1)}, np.random.default_rng(0))
    legacy.save(4, [])                                           # written without settings: continued as before
    assert state(Cfg(inner=Inner(lr=0.2))).resume()[0] == 4
