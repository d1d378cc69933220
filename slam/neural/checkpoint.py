"""Resumable training state of the neural memory's training loops (``train_memory``, the decoder refinement).

One file holds the state dicts of the trained modules and their optimisers, the numpy generator that draws the
batches, torch's global random state, the next step and the loss log; it is written atomically (a kill while
writing leaves the previous checkpoint), so a re-run that loads it continues with the same batches and the same
random draws as an uninterrupted run.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any

__all__ = ["save_training_state", "load_training_state"]


def save_training_state(path: str | Path, parts: dict[str, Any], rng, step: int, log: list) -> None:
    """Write ``parts`` (name -> module or optimiser: anything with ``state_dict``), the numpy Generator ``rng``,
    torch's random state, ``step`` (the next step to run) and ``log`` to ``path``, atomically."""
    import torch

    from data_tools.results import atomic_write_bytes
    buf = io.BytesIO()
    state = {name: p.state_dict() for name, p in parts.items()}
    state.update(rng=rng.bit_generator.state, torch_rng=torch.get_rng_state(), step=int(step), log=list(log))
    torch.save(state, buf)
    atomic_write_bytes(Path(path), buf.getvalue())


def load_training_state(path: str | Path, parts: dict[str, Any], rng, what: str, map_location="cpu") -> tuple[int, list]:
    """Restore what :func:`save_training_state` wrote into ``parts`` and ``rng`` (and torch's random state);
    returns (step, log). Any unreadable or mismatching file raises a one-line :class:`FormatError` naming it
    (``what``: e.g. "training checkpoint")."""
    import torch

    from data_tools.errors import FormatError
    path = Path(path)
    try:
        st = torch.load(path, map_location=map_location, weights_only=False)
        for name, p in parts.items():
            p.load_state_dict(st[name])
        rng.bit_generator.state = st["rng"]
        torch.set_rng_state(st["torch_rng"])
        return int(st["step"]), list(st.get("log", []))
    except Exception as e:
        raise FormatError(path, f"unreadable {what} ({type(e).__name__}); delete it to start again") from None
