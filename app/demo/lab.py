"""Part 1 of the demo: the sensor lab on a mystery sensor.

A "measured" sequence comes from :mod:`synth.lab.mystery`, a depth-sensor generator written apart
from the simulator (its own camera, raw-disparity conversion and scene family) that hides one
physical effect; its ``answer.json`` is read only at the end. The lab compares the sequence with the
ideal model and with a base model (axial noise + range limits, fitted), diagnoses the missing effect,
adds it fitted and compares again: the gap history falls, and the hidden answer is printed beside
what the lab found. Every step is its own folder, kept when finished (a re-run resumes).
"""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

__all__ = ["BASE_EFFECTS", "run_lab_part"]

BASE_EFFECTS = "axial_noise,range_limits"
"""What the lab's model holds before the diagnosis: the two effects every depth sensor has."""


def _compare(seq: Path, out: Path, label: str, against: Path | None, seed: int, log, **req) -> dict:
    """One ``sensor compare`` step into its own folder (skipped when finished); returns its metrics."""
    from synth.lab.runs import LabRequest, compare_sequence
    if not (out / "metrics.json").is_file():
        log(f"      compare: {label}")
        compare_sequence(LabRequest(str(seq), seed=seed, **req), out, label=label,
                         compare_against=str(against) if against else None)
    return json.loads((out / "metrics.json").read_text())


def run_lab_part(out: Path, seed: int, frames: int, log: Callable[[str], None] = print,
                 effect: str = "edge_fattening") -> dict:
    """The lab on the mystery sensor into ``out`` (``out/mystery`` the sequence, ``out/1_ideal``,
    ``2_base``, ``4_fitted`` compare folders, ``3_diagnose``). Returns the part's facts."""
    from synth.lab.mystery import generate
    seq = out / "mystery"
    if not (seq / "groundtruth.txt").is_file() or not (seq / "answer.json").is_file():
        log(f"      the mystery sensor records {frames} frames -> {seq}")
        generate(seq, effect=effect or "random", seed=seed, n_frames=frames)
    ideal = _compare(seq, out / "1_ideal", "ideal depth", None, seed, log, effects="none")
    base = _compare(seq, out / "2_base", "base model (fitted)", out / "1_ideal", seed, log,
                    effects=BASE_EFFECTS, fit=True)
    diag_dir = out / "3_diagnose"
    if not (diag_dir / "best_model.json").is_file() or (diag_dir / "incomplete.json").exists():
        from synth.lab.runs import LabRequest, diagnose_sequence
        log("      diagnose: which effect is missing from the base model?")
        diagnose_sequence(LabRequest(str(seq), effects=BASE_EFFECTS, seed=seed), diag_dir, overwrite=True)
    diag = json.loads((diag_dir / "diagnosis.json").read_text())
    ranking = diag.get("ranking") or []
    if not ranking:
        from data_tools.errors import RealgapError
        raise RealgapError(f"{diag_dir}/diagnosis.json: the diagnosis ranked no candidate")
    best = ranking[0]
    fitted = _compare(seq, out / "4_fitted", f"+ {best['effect']} (fitted)", out / "2_base", seed, log,
                      model=str(diag_dir / "best_model.json"))
    answer = json.loads((seq / "answer.json").read_text())         # read only now: the lab never sees it
    from synth.lab.history import load_history
    history = load_history(out / "4_fitted")
    return {"sequence": str(seq), "hidden_effect": answer.get("effect"), "hidden_parameters": answer.get("params"),
            "found_effect": best["effect"], "found_gain": best.get("gain"), "evidence": best.get("evidence", ""),
            "fitted_parameters": {k: v for k, v in (best.get("params") or {}).items()
                                  if k.startswith(best["effect"] + ".")},
            "gap_ideal": ideal["gap"], "gap_base": base["gap"], "gap_fitted": fitted["gap"],
            "history": history, "report": str(out / "4_fitted" / "report.html"),
            "diagnosis": str(diag_dir / "diagnosis.html")}
