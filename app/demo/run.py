"""``realgap demo``: the story of realgap in one run on embedded data.

1. the sensor lab names the effect a mystery sensor hides, fits it and the gap falls (:mod:`app.demo.lab`);
2. a room walk simulated by the kinect_v1 pipeline, registered by icp and by the neural memory, with novel
   and hallucinated views (:mod:`app.demo.explore`);
3. chairs recognised in scans of another sensor by a recogniser trained on simulation only
   (:mod:`app.demo.recognise`);
4. ``index.html`` with the three parts (:mod:`app.demo.page`) and a short summary on the terminal.

Each part keeps what it finished: a re-run (after Ctrl-C) continues where it stopped.
"""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from app.demo.config import DemoConfig

__all__ = ["run_demo", "summary_lines", "DEMO_OUTPUTS"]

DEMO_OUTPUTS = ("lab", "explore", "recog", "index.html", "summary.json", "timings.json", "demo_config.json",
                "incomplete.json")
"""What ``run_demo`` writes into its folder (and ``--overwrite`` removes before it starts again)."""


def run_demo(out: str | Path, config: DemoConfig | None = None, log: Callable[[str], None] = print,
             progress: bool = True, overwrite: bool = False) -> dict:
    """Run the three parts into ``out`` and write ``out/index.html`` and ``out/summary.json``;
    returns the facts (what the page shows). Parts already in ``out`` are kept (an interrupted demo
    continues); ``overwrite`` removes what an earlier demo wrote there (:data:`DEMO_OUTPUTS`, nothing
    else) and computes every part again."""
    from data_tools.config import config_to_dict
    from data_tools.outputs import check_output_dir, clear_incomplete, mark_incomplete
    from data_tools.results import atomic_write_json, make_header, write_result
    from app.demo.explore import run_explore_part
    from app.demo.lab import run_lab_part
    from app.demo.page import write_index
    from app.demo.recognise import run_recog_part
    cfg = (config or DemoConfig()).validate()
    out = check_output_dir(out, what="demo folder")
    if overwrite:
        import shutil
        for name in DEMO_OUTPUTS:
            p = out / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "demo_config.json", config_to_dict(cfg))
    t0 = time.perf_counter()
    timings_file = out / "timings.json"         # seconds each part took when it was computed (a re-run keeps them)
    timings = json.loads(timings_file.read_text()) if timings_file.is_file() else {}
    facts = {}
    parts = [("lab", "the sensor lab on a mystery sensor",
              lambda: run_lab_part(out / "lab", cfg.mystery_seed, cfg.mystery_frames, log, cfg.mystery_effect)),
             ("explore", "exploration: icp and the neural memory on a simulated room walk",
              lambda: run_explore_part(out / "explore", cfg.room_seed, cfg.room_frames, cfg.novel_frame,
                                       cfg.screenshot, log, progress, cfg.align)),
             ("recog", "recognition of chairs scanned by another sensor",
              lambda: run_recog_part(out / "recog", cfg.recog_scans, cfg.recog_model, cfg.seed, log, progress))]
    for i, (key, title, fn) in enumerate(parts):
        mark_incomplete(out, "realgap demo", i, len(parts), unit="parts")
        log(f"[{i + 1}/{len(parts)}] {title}")
        t = time.perf_counter()
        facts[key] = fn()
        dt = round(time.perf_counter() - t, 1)
        if key not in timings or dt > 2.0:       # under 2 s the part was only read back from disk
            timings[key] = dt
            atomic_write_json(timings_file, timings)
    facts["seconds"] = round(sum(timings[k] for k, _, _ in parts), 1)
    facts["this_run_s"] = round(time.perf_counter() - t0, 1)
    facts["timings_s"] = timings
    metrics = {"lab.gap_ideal": facts["lab"]["gap_ideal"], "lab.gap_base": facts["lab"]["gap_base"],
               "lab.gap_fitted": facts["lab"]["gap_fitted"],
               **{f"explore.{b}.ate_rmse_m": r.get("ate_rmse_m") for b, r in facts["explore"]["backends"].items()},
               "recog.accuracy": facts["recog"]["accuracy"]}
    write_result(out / "summary.json", make_header("demo", parameters=config_to_dict(cfg), seed=cfg.seed,
                                                   timings_s=timings, metrics=metrics), facts)
    write_index(out, facts)
    clear_incomplete(out)
    return facts


def summary_lines(out: str | Path, facts: dict) -> list[str]:
    """The 5-10 lines the terminal ends with."""
    lab, ex, rc = facts["lab"], facts["explore"], facts["recog"]
    gaps = " -> ".join(f"{h['gap']:.3f}" for h in lab["history"])
    same = "right" if lab["found_effect"] == lab["hidden_effect"] else "WRONG"
    resumed = facts.get("this_run_s", facts["seconds"]) < facts["seconds"] - 5
    lines = [f"realgap demo finished in {facts['seconds']:.0f} s" + (
        f" (this run {facts['this_run_s']:.0f} s: finished parts were kept)" if resumed else ""),
             f"  lab: the mystery sensor hid {lab['hidden_effect']}; the lab diagnosed {lab['found_effect']} ({same}); "
             f"gap {gaps}"]
    for b, r in ex["backends"].items():
        if r.get("ok"):
            lines.append(f"  exploration: {b:7s} ATE {r['ate_rmse_m'] * 100:.1f} cm (align {r.get('align') or 'se3'}), "
                         f"{r['frames_per_second']:.1f} frames/s")
        else:
            lines.append(f"  exploration: {b:7s} failed: {r.get('error')}")
    rot = rc["rot_err_deg_median"]
    lines.append(f"  recognition: {100 * rc['accuracy']:.0f} % of {rc['scans']} structure-sensor scans right, "
                 f"rotation error median {'-' if rot is None else f'{rot:.1f}'} deg after ICP")
    lines.append(f"  open {Path(out).resolve() / 'index.html'} for the whole story")
    return lines
