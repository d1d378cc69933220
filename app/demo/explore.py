"""Part 2 of the demo: exploration of a room, classic and neural registration side by side.

A ground robot's walk through a furnished ``procedural_room`` (never seen by the neural model's
training) is measured by the full kinect_v1 simulator; ``batch`` registers it with ``icp`` (frame-to-model
ICP + TSDF) and ``neural`` (the shipped ``planar_3d`` allocentric memory) and scores both against the
ground truth. At one pose the TSDF and the memory render the view, and the memory hallucinates a view
turned away from everything the robot saw there. Every step is kept when finished (a re-run resumes).
"""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["run_explore_part", "turned_pose"]


def turned_pose(pose_c2w: np.ndarray, degrees: float) -> np.ndarray:
    """``pose_c2w`` turned by ``degrees`` about the camera's own y axis (down in the OpenCV optical
    frame: a positive angle turns the view to the right, a yaw for a level camera)."""
    a = np.deg2rad(degrees)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    out = np.array(pose_c2w, float).copy()
    out[:3, :3] = out[:3, :3] @ R
    return out


def _views(seq: Path, icp_run: Path, neural_run: Path, frame: int, out: Path) -> dict:
    """Measured colour at ``frame`` beside the TSDF's and the memory's renders at that (estimated) pose,
    and the memory's recall and hallucination 90 deg to the right: ``out/views.png``."""
    import cv2

    from data_tools.results import atomic_save_figure, new_figure
    from data_tools.sequence import SequenceReader
    from data_tools.trajectory import read_tum
    from slam.render import render_run, save_view
    png = out / "views.png"
    if png.is_file():
        return json.loads((out / "views.json").read_text())
    out.mkdir(parents=True, exist_ok=True)
    reader = SequenceReader(seq)
    measured = cv2.cvtColor(cv2.imread(str(seq / reader.rgb_files[frame])), cv2.COLOR_BGR2RGB)
    pose_icp = read_tum(icp_run / "trajectory.txt").poses[frame]
    pose_neu = read_tum(neural_run / "trajectory.txt").poses[frame]
    tsdf = render_run(icp_run, pose_icp, source="volume" if (icp_run / "volume.npz").is_file() else "mesh")
    recall = render_run(neural_run, pose_neu, source="neural")
    turned = turned_pose(pose_neu, 90.0)
    recall_turned = render_run(neural_run, turned, source="neural")
    halluc = render_run(neural_run, turned, source="neural", hallucinate=True)
    for name, v in (("tsdf", tsdf), ("neural_recall", recall), ("neural_turned", recall_turned),
                    ("neural_hallucinated", halluc)):
        save_view(v, out / f"{name}.png")
    fig = new_figure(16.0, 3.6)
    axes = fig.subplots(1, 5)
    panels = [(measured, f"measured colour, frame {frame}"), (tsdf.rgb, "TSDF ray cast (icp run)"),
              (recall.rgb, "neural memory: recall"), (recall_turned.rgb, "memory, 90 deg right: recall"),
              (halluc.rgb, "memory, 90 deg right: hallucinated")]
    for ax, (img, title) in zip(axes, panels):
        ax.imshow(np.asarray(img))
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
    fig.suptitle("Novel views at one pose (TSDF: magenta = never observed; the memory decodes every cell)", fontsize=11)
    atomic_save_figure(fig, png, dpi=90)
    facts = {"frame": frame, "figure": str(png), "tsdf_coverage": tsdf.coverage, "recall_coverage": recall.coverage,
             "turned_recall_coverage": recall_turned.coverage, "hallucinated_coverage": halluc.coverage}
    (out / "views.json").write_text(json.dumps(facts, indent=2) + "\n")
    return facts


def run_explore_part(out: Path, room_seed: int, frames: int, novel_frame: int, screenshot: bool,
                     log: Callable[[str], None] = print, progress: bool = True, align: str = "auto") -> dict:
    """Exploration into ``out`` (``out/room`` the simulated sequence, ``out/batch`` the icp + neural
    report, ``out/views`` the novel views, ``out/viewer.png``). Returns the part's facts."""
    from app.pipelines import simulate_planar_room
    from slam.batch import load_results, run_batch
    seq = out / "room"
    if not (seq / "groundtruth.txt").is_file() or (seq / "incomplete.json").exists():
        log(f"      simulating the room walk ({frames} frames, kinect_v1 physical pipeline) -> {seq}")
        simulate_planar_room(room_seed, frames, seq, progress=progress)
    batch = out / "batch"
    def scored_with(a: str) -> bool:      # the batch's runs are kept; another --align only rescores them
        return all((r.get("align") or "").split(":")[0] == a for r in load_results(batch) if r.get("ok"))
    if (not (batch / "results.json").is_file() or (batch / "incomplete.json").exists()
            or not scored_with(align)):
        log(f"      registering it with icp and neural (batch, align {align})")
        run_batch([seq], ["icp", "neural"], batch, progress=progress, align=align)
    rows = {r["backend"]: r for r in load_results(batch)}
    runs = batch / "runs" / seq.name
    log("      novel views from the TSDF and from the memory")
    views = _views(seq, runs / "icp", runs / "neural", novel_frame, out / "views")
    shot = out / "viewer.png"
    shot_note = ""
    if screenshot and not shot.is_file():
        log("      viewer screenshot (off-screen)")
        try:
            from app.viewer.run import open_viewer
            open_viewer([str(seq), str(runs / "icp"), str(runs / "neural")], screenshot=str(shot),
                        frame=novel_frame, size="1600x900")
        except Exception as e:  # no EGL / GL here: the rest of the demo stands without the picture
            shot_note = f"viewer screenshot skipped: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
            log(f"      {shot_note}")
    return {"sequence": str(seq), "frames": frames, "report": str(batch / "index.html"),
            "comparison_plot": str(batch / "plots" / "comparison.png"),
            "backends": {b: {k: r.get(k) for k in ("ok", "ate_rmse_m", "ape_median_m", "frames_per_second",
                                                    "frames_failed", "error", "align")} for b, r in rows.items()},
            "views": views, "screenshot": str(shot) if shot.is_file() else None, "screenshot_note": shot_note}
