"""A journal of objective evaluations, so an interrupted fit or diagnosis continues where it stopped.

The lab's searches (:func:`synth.lab.descent.search`) are deterministic: the same data, model, seed
and gaps give the same sequence of evaluated parameter values. A journal records each
evaluation's gap under a key that identifies *everything* it depends on (the full sensor
configuration, the frames of the measured sequence, the comparison settings and the seed). A
re-run replays the recorded gaps instead of simulating again, walks the same path and reaches
the identical result; only the evaluations the killed run had not finished are computed.

The file is JSON lines, appended and flushed after every evaluation; a line cut by a kill is
ignored. The journal is removed by the command when its result is saved.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

__all__ = ["EvalJournal"]


class EvalJournal:
    """Gaps of finished objective evaluations, stored at ``path`` (JSON lines ``{"key", "gap"}``)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.gaps: dict[str, float] = {}
        self.replayed = 0
        """Evaluations answered from the journal in this process."""
        if self.path.is_file():
            for line in self.path.read_text(errors="replace").splitlines():
                try:
                    d = json.loads(line)
                    self.gaps[str(d["key"])] = float(d["gap"])
                except (ValueError, KeyError, TypeError):
                    continue  # the line a kill cut short
        self.loaded = len(self.gaps)
        """Evaluations found on disk when opened."""

    @staticmethod
    def key(config, frame_indices, compare_config, seed: int, seq_dir, extra: dict | None = None) -> str:
        """Identity of one evaluation: sensor config, absolute frame indices, compare settings, seed, sequence
        (and ``extra`` objective settings, e.g. the noise-curve weight, when given)."""
        from data_tools.config import config_to_dict
        d = {"config": config.to_json(), "frames": [int(i) for i in frame_indices],
             "compare": config_to_dict(compare_config), "seed": int(seed), "sequence": str(Path(seq_dir).resolve())}
        if extra:
            d["extra"] = extra
        blob = json.dumps(d, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()

    def get(self, key: str) -> float | None:
        g = self.gaps.get(key)
        if g is not None:
            self.replayed += 1
        return g

    def put(self, key: str, gap: float) -> None:
        self.gaps[key] = float(gap)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as f:
            f.write(json.dumps({"key": key, "gap": float(gap)}) + "\n")
            f.flush()

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)
