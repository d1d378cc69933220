"""One training loop for every trainer of the project (``neural train``, ``refine-decoder``, ``refine-hallucination``,
``train-topview``, ``recog train``): resume, checkpoint every N steps, log every N steps with running loss means,
a learning-rate schedule, a progress bar.

Why here: the trainers live in ``slam/neural`` and ``recog``, which may not import each other (dependencies point
data_tools <- synth <- recog, data_tools <- slam); ``data_tools`` is their only common ancestor. The loop itself is
plain Python. The checkpoint file (:class:`TrainingState`) is the one place outside ``recog/`` and ``slam/neural/``
that touches torch - imported inside its two methods, so importing this module does not load torch - an allowance
``tests/test_architecture.py`` names (``RESTRICTED``).
"""
from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["run_steps", "LossMeans", "TrainingState", "linear_ramp", "set_lr", "settings_of"]


def linear_ramp(step: int, decay_from: int, total: int, final: float) -> float:
    """1 until step ``decay_from``, then linear to ``final`` at the last step ``total - 1`` (``decay_from`` <= 0:
    always 1). A function of the step only, so a resumed run continues the same schedule."""
    a = int(decay_from)
    if a <= 0 or step < a:
        return 1.0
    t = (step - a) / max(total - 1 - a, 1)
    return 1.0 + (final - 1.0) * min(t, 1.0)


def set_lr(optimisers, lr: float) -> None:
    """Set the learning rate of every parameter group of ``optimisers``."""
    for o in optimisers:
        for g in o.param_groups:
            g["lr"] = lr


class LossMeans:
    """Named losses summed between two log records; :meth:`record` gives each sum over the number of steps added
    (a loss that joined mid-way is divided by all of them), rounded to 5 decimals, and starts again."""

    def __init__(self):
        self.sums: dict[str, float] = {}
        self.n = 0

    def add(self, losses: dict) -> None:
        for k, v in losses.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
        self.n += 1

    def record(self, step: int) -> dict:
        rec = {"step": step, **{k: round(v / self.n, 5) for k, v in self.sums.items()}}
        self.sums, self.n = {}, 0
        return rec


class TrainingState:
    """The resumable state of a training loop in one file: the state dicts of ``parts`` (name -> module or
    optimiser), the numpy Generator ``rng`` that draws the batches, torch's global random state, the next step and
    the loss log; written atomically (a kill while writing leaves the previous file), so a re-run continues with
    the same batches and random draws as an uninterrupted run. ``path`` None: nothing is saved or loaded.
    ``on_save(step)`` is called after each write and on a resume (a command's progress marker). ``settings``
    (see :func:`settings_of`) are stored with the state; a resume under other settings is refused, because it
    would silently continue a run made with the old ones."""

    def __init__(self, path: str | Path | None, parts: dict[str, Any], rng, what: str = "training checkpoint",
                 map_location="cpu", on_save: Callable[[int], None] | None = None, settings: dict | None = None):
        self.path = Path(path) if path else None
        self.parts, self.rng, self.what, self.map_location, self.on_save = parts, rng, what, map_location, on_save
        self.settings = settings

    def resume(self, log: Callable[[str], None] | None = None, total: int | None = None) -> tuple[int, list] | None:
        """(next step, log) from the file, restored into ``parts`` and the random states, or None when there is no
        file. Any unreadable or mismatching file is a one-line :class:`FormatError` naming it. ``log``: told
        "resuming <what> at step S of ``total`` from PATH" when a file was continued."""
        if self.path is None or not self.path.is_file():
            return None
        import torch

        from data_tools.errors import FormatError
        try:
            st = torch.load(self.path, map_location=self.map_location, weights_only=False)
        except Exception as e:
            raise FormatError(self.path, f"unreadable {self.what} ({type(e).__name__}); delete it to start again") \
                from None
        changed = _changed_setting(st.get("settings") if isinstance(st, dict) else None, self.settings)
        if changed:
            raise FormatError(self.path, f"{self.what} was written with other settings ({changed}); run with the "
                                         "same settings to continue it, or delete it to start again")
        try:
            for name, p in self.parts.items():
                p.load_state_dict(st[name])
            self.rng.bit_generator.state = st["rng"]
            torch.set_rng_state(st["torch_rng"])
            step, history = int(st["step"]), list(st.get("log", []))
        except Exception as e:
            raise FormatError(self.path, f"unreadable {self.what} ({type(e).__name__}); delete it to start again") \
                from None
        if self.on_save is not None:
            self.on_save(step)
        if log is not None:
            what = self.what.removesuffix(" checkpoint")
            log(f"resuming {what} at step {step}{'' if total is None else f' of {total}'} from {self.path}")
        return step, history

    def save(self, step: int, log: list) -> None:
        """Write the state with ``step`` the next step to run (nothing without a path)."""
        if self.path is None:
            return
        import torch

        from data_tools.results import atomic_write_bytes
        buf = io.BytesIO()
        state = {name: p.state_dict() for name, p in self.parts.items()}
        state.update(rng=self.rng.bit_generator.state, torch_rng=torch.get_rng_state(), step=int(step), log=list(log))
        if self.settings is not None:
            state["settings"] = self.settings
        torch.save(state, buf)
        atomic_write_bytes(self.path, buf.getvalue())
        if self.on_save is not None:
            self.on_save(step)


RESUMABLE_CHANGES = ("iterations", "checkpoint_every", "log_every", "workers", "device")
"""Settings a resumed run may change: how long it runs and how it reports, not what it learns (``device``: the same
run may continue on another machine). A trainer whose length field has another name adds it (refinements: ``steps``)."""


def settings_of(config, ignore: tuple = RESUMABLE_CHANGES) -> dict:
    """The fields of a (nested) dataclass ``config`` as plain JSON values (:func:`data_tools.config.config_to_dict`),
    flattened to dotted names, without the ``ignore`` names at any depth: what a checkpoint must have been trained
    with to be continued."""
    import json

    from data_tools.config import config_to_dict

    out: dict = {}

    def walk(d: dict, prefix: str) -> None:
        for k, v in d.items():
            if k in ignore:
                continue
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            else:
                out[prefix + k] = json.loads(json.dumps(v, default=str))
    walk(config_to_dict(config), "")
    return out


def _changed_setting(stored: dict | None, now: dict | None) -> str:
    """'name: old -> new' for the first setting that differs ('' when none does, or either side has none: a
    checkpoint written before settings were stored is continued as before)."""
    if not stored or not now:
        return ""
    for k in sorted(set(stored) | set(now)):
        if k in stored and k in now and stored[k] != now[k]:
            return f"{k}: {stored[k]!r} -> {now[k]!r}"
    return ""


def run_steps(step_fn: Callable[[int], dict], total: int, *, start: int = 0, history: list | None = None,
              log_every: int = 50, log_also: tuple = (), state: TrainingState | None = None,
              checkpoint_every: int = 0, save_last: bool = True, lr: Callable[[int], None] | None = None,
              progress: bool = True, desc: str = "training", unit: str = "step",
              postfix: Callable[[dict], str] | None = None) -> float:
    """Run ``step_fn(step)`` (one optimiser step; returns its losses as floats) for steps ``start`` .. ``total - 1``.

    Before each step ``lr(step)`` sets the learning rate (the schedule); after it the losses join running means,
    recorded into ``history`` (``{"step": step + 1, name: mean, ...}``, :class:`LossMeans`) every ``log_every`` steps,
    at the last step and after the steps in ``log_also`` (1-based); ``state`` is saved every ``checkpoint_every``
    steps before the last and, with ``save_last``, after it. ``postfix(record)`` is the progress bar's text.
    Returns the seconds the steps took."""
    history = [] if history is None else history
    bar = None
    if progress:
        from data_tools.progress import progress_bar
        bar = progress_bar(total=total, initial=start, desc=desc, unit=unit)
    means = LossMeans()
    t0 = time.perf_counter()
    for step in range(start, total):
        if lr is not None:
            lr(step)
        means.add(step_fn(step))
        done = step + 1
        if done % log_every == 0 or done == total or done in log_also:
            rec = means.record(done)
            history.append(rec)
            if bar is not None:
                bar.set_postfix_str(postfix(rec) if postfix is not None else
                                    " ".join(f"{k} {v:.3f}" for k, v in rec.items() if k != "step"))
        if state is not None and checkpoint_every and done % checkpoint_every == 0 and done < total:
            state.save(done, history)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    if state is not None and save_last:
        state.save(total, history)
    return seconds
