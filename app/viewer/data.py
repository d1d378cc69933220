"""What the viewer shows, loaded without any plotting library: a sequence and the runs on it, a
sensor-lab folder, or a recognition evaluation. Everything here is numpy and is tested on its own;
:mod:`app.viewer.window` only draws it.

Inputs (``realgap view PATH...``): each PATH is a TUM-layout sequence (``depth.txt``) or a SLAM
run folder (``config.json`` + ``trajectory.txt``). A run names its sequence in its config.json,
so ``realgap view RUN`` alone finds the frames; the ground truth is the sequence's
``groundtruth.txt``. Frames are read on demand (a 1000-frame sequence is never held in memory).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError, RealgapError

__all__ = ["RunTrack", "SequenceSession", "LabSession", "RecogSession", "load_session", "TRACK_COLOURS",
           "frustum_lines"]

TRACK_COLOURS = {"ground truth": (0.95, 0.95, 0.95), "icp": (1.0, 0.55, 0.0), "rgbd_odometry": (0.2, 0.8, 0.2),
                 "neural": (0.0, 0.8, 1.0), "colmap": (0.85, 0.3, 0.85), "virtual camera": (1.0, 0.9, 0.0)}
"""Colour (RGB in [0, 1]) of each trajectory; other backends get :data:`_SPARE` colours."""
_SPARE = [(0.9, 0.2, 0.3), (0.4, 0.5, 1.0), (0.6, 0.9, 0.3)]


@dataclass
class RunTrack:
    """One registration run on the sequence."""

    name: str
    """Label (the backend, plus the folder name when two runs share a backend)."""
    backend: str
    run_dir: Path
    trajectory: object
    """:class:`~data_tools.trajectory.Trajectory` of the registered frames (world frame of the run)."""
    failed_timestamps: np.ndarray
    """Timestamps of frames the backend could not register."""
    ape_m: np.ndarray | None = None
    """(N,) position error of each registered pose after origin alignment (the run's first pose onto
    the ground truth's), metres: drift shows as a growing error (None without ground truth)."""
    aligned_positions: np.ndarray | None = None
    """(N, 3) the run's positions moved into the ground truth's frame by that alignment."""
    alignment: np.ndarray | None = None
    """(4, 4) the alignment (run frame -> ground-truth frame)."""
    colour: tuple = (1.0, 1.0, 1.0)

    @property
    def has_mesh(self) -> bool:
        return (self.run_dir / "mesh.ply").is_file()


def _is_sequence(p: Path) -> bool:
    return (p / "depth.txt").is_file()


def _is_run(p: Path) -> bool:
    return (p / "config.json").is_file() and ((p / "trajectory.txt").is_file() or (p / "stats.json").is_file())


class SequenceSession:
    """A sequence, its ground truth and the runs on it."""

    def __init__(self, sequence: Path | None, runs: list[Path], simulated: Path | None = None):
        from data_tools.sequence import SequenceReader
        self.runs: list[RunTrack] = []
        self.simulated = SequenceReader(simulated) if simulated is not None else None
        """A second sequence of the same frames (e.g. ``sensor simulate`` or ``synth sequence
        --sensor`` output): its depth is shown beside the measured one, with the residual."""
        self.simulated_path = Path(simulated) if simulated is not None else None
        seq = sequence
        for r in runs:
            meta = json.loads((r / "config.json").read_text())
            if seq is None and meta.get("sequence"):
                seq = Path(meta["sequence"])
        if seq is None:
            raise FormatError(runs[0] if runs else Path("."), "no sequence: give the sequence folder too "
                                                              "(the run's config.json does not name one)")
        self.reader = SequenceReader(seq)
        self.path = Path(seq)
        self.intrinsics = self.reader.intrinsics
        self.gt = self.reader.trajectory if self.reader.has_groundtruth else None
        names = []
        for k, r in enumerate(runs):
            self.runs.append(self._load_run(r, names, k))
        self.virtual_pose = self.pose(0).copy()

    def _load_run(self, r: Path, names: list[str], k: int) -> RunTrack:
        from data_tools.trajectory import read_tum
        stats = json.loads((r / "stats.json").read_text()) if (r / "stats.json").is_file() else {}
        meta = json.loads((r / "config.json").read_text())
        backend = str(meta.get("config", {}).get("backend") or stats.get("backend") or "run")
        if not (r / "trajectory.txt").is_file():
            raise FormatError(r, "run folder without trajectory.txt (unfinished run? 'realgap slam run' "
                                 "continues it)")
        traj = read_tum(r / "trajectory.txt")
        name = backend if backend not in names else f"{backend} ({r.name})"
        names.append(name)
        colour = TRACK_COLOURS.get(backend, _SPARE[k % len(_SPARE)])
        track = RunTrack(name, backend, r, traj, np.asarray(stats.get("failed_timestamps", []), float), colour=colour)
        if self.gt is not None and len(traj) >= 1:
            # a run's world frame is its first registered camera: origin alignment (first pose onto the
            # ground truth's pose at that time) places it exactly, even for a short or straight walk
            # where an SE(3) fit is ill-conditioned
            import warnings

            from slam import metrics
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                a = metrics.ate(self.gt, traj, align="origin")
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = a.alignment.s * a.alignment.R, a.alignment.t
            err = np.full(len(traj), np.nan)
            idx = np.clip(np.searchsorted(traj.timestamps, a.timestamps), 0, len(traj) - 1)
            ok = np.abs(traj.timestamps[idx] - a.timestamps) < 1e-6
            err[idx[ok]] = a.errors[ok]
            track.ape_m = err
            track.alignment = T
            track.aligned_positions = traj.positions @ T[:3, :3].T + T[:3, 3]
        return track

    # ---------------------------------------------------------------- frames
    def __len__(self) -> int:
        return len(self.reader)

    def pose(self, i: int) -> np.ndarray:
        """Camera-to-world pose of frame i: ground truth, else the first run's registered pose, else identity."""
        p = self.reader.poses[i]
        if np.all(np.isfinite(p)):
            return p
        ts = self.reader.timestamps[i]
        for r in self.runs:
            j = np.searchsorted(r.trajectory.timestamps, ts)
            if j < len(r.trajectory) and abs(r.trajectory.timestamps[j] - ts) < 1e-6:
                return (r.alignment if r.alignment is not None else np.eye(4)) @ r.trajectory.poses[j]
        return np.eye(4)

    def frame(self, i: int):
        """(rgb (H, W, 3) uint8 or None, depth (H, W) float32 metres) of frame i."""
        f = self.reader[i]
        return f.rgb, f.depth

    def simulated_depth(self, i: int) -> np.ndarray | None:
        """(H, W) float32 depth (metres) of the second sequence's frame with frame i's timestamp
        (within SAME_FRAME_S: simulations keep the timestamps), None when there is no second sequence or no such frame."""
        if self.simulated is None:
            return None
        ts = np.asarray(self.simulated.timestamps)
        if not len(ts):
            return None
        j = int(np.argmin(np.abs(ts - self.reader.timestamps[i])))
        if abs(ts[j] - self.reader.timestamps[i]) > SAME_FRAME_S:
            return None
        d = self.simulated.read_depth(j)
        return d if d.shape == self.intrinsics.shape else None

    def frame_points(self, i: int, step: int = 4, max_depth: float = 6.0):
        """(points (N, 3) world metres, colours (N, 3) uint8 or None) of frame i, every ``step``-th pixel."""
        rgb, depth = self.frame(i)
        from data_tools.geometry import unproject
        d = depth[::step, ::step]
        intr = self.intrinsics.scaled(1.0 / step) if step > 1 else self.intrinsics
        if d.shape != intr.shape:
            d = d[:intr.height, :intr.width]
        pts = unproject(d, intr).reshape(-1, 3)
        ok = (d.reshape(-1) > 0) & (d.reshape(-1) < max_depth)
        T = self.pose(i)
        pts = pts[ok] @ T[:3, :3].T + T[:3, 3]
        col = None
        if rgb is not None:
            c = rgb[::step, ::step][:intr.height, :intr.width].reshape(-1, 3)
            col = c[ok]
        return pts, col

    def frame_state(self, i: int) -> dict:
        """Per-run state at frame i: registered or failed, and the APE there (metres)."""
        ts = self.reader.timestamps[i]
        out = {}
        for r in self.runs:
            j = np.searchsorted(r.trajectory.timestamps, ts)
            hit = j < len(r.trajectory) and abs(r.trajectory.timestamps[j] - ts) < 1e-6
            failed = bool(np.any(np.abs(r.failed_timestamps - ts) < 1e-6))
            ape = float(r.ape_m[j]) if hit and r.ape_m is not None and np.isfinite(r.ape_m[j]) else None
            out[r.name] = {"registered": bool(hit), "failed": failed, "ape_m": ape,
                           "pose_index": int(j) if hit else None}
        return out

    # ---------------------------------------------------------------- novel views
    def novel_views(self, pose_c2w: np.ndarray, scale: float = 0.5, hallucinate: bool = False) -> dict[str, object]:
        """Name -> :class:`slam.render.RenderedView` (or a one-line reason string) of the virtual
        camera ``pose_c2w`` (ground-truth frame) from every run's model: a run's mesh is in the
        run's own frame, so the pose is moved by the inverse of the run's alignment. A neural run's
        memory (in the ground-truth frame of the sequence's first pose) gives ``"neural"``: the view
        it recalls (``hallucinate``: after its hallucination module), decoded and resized."""
        from slam.render import RenderedView, render_mesh
        out: dict[str, object] = {}
        intr = self.intrinsics.scaled(scale)
        for r in self.runs:
            if r.backend == "neural":
                from data_tools.errors import RealgapError
                from slam.neural.inference import recall_view
                try:
                    rgb, depth = recall_view(r.run_dir, pose_c2w, hallucinate, size=(intr.width, intr.height))
                    out["neural"] = RenderedView(rgb, depth, pose_c2w, intr)
                except RealgapError as e:
                    out["neural"] = str(e)
                continue
            if not r.has_mesh:
                out[r.name] = f"{r.name}: no mesh.ply in {r.run_dir.name}"
                continue
            mesh = self._mesh(r)
            T = np.linalg.inv(r.alignment) @ pose_c2w if r.alignment is not None else pose_c2w
            out[r.name] = render_mesh(mesh, intr, T)
        if all(isinstance(v, str) for v in out.values()) and self.reader.has_scene:
            mesh, _ = self.reference_mesh()       # no run model: the sequence's own reference (GT frame)
            out["scene.json reference"] = render_mesh(mesh, intr, pose_c2w)
        if not any(r.backend == "neural" for r in self.runs):
            out["neural"] = "no neural run"
        return out

    _meshes: dict = {}

    def _mesh(self, r: RunTrack):
        from data_tools.mesh import load_mesh
        key = str(r.run_dir)
        if key not in self._meshes:
            self._meshes[key] = load_mesh(r.run_dir / "mesh.ply", validate=False)
        return self._meshes[key]

    _reference = None

    def reference_mesh(self):
        """The world model to draw: the first run's TSDF mesh (moved into the ground-truth frame),
        else the sequence's scene.json meshes, else None (the viewer then fuses frame points)."""
        for r in self.runs:
            if r.has_mesh:
                m = self._mesh(r)
                return m.transformed(r.alignment) if r.alignment is not None else m, f"{r.name} TSDF mesh"
        if self.reader.has_scene:
            if self._reference is not None:
                return self._reference
            from data_tools.mesh import TriMesh
            sc = self.reader.scene
            v, t, off = [], [], 0
            for m in sc.meshes:
                v.append(m.vertices)
                t.append(m.triangles + off)
                off += len(m.vertices)
            self._reference = TriMesh(np.concatenate(v), np.concatenate(t), "scene"), "scene.json"
            return self._reference
        return None, "fused frame points"


def frustum_lines(pose_c2w: np.ndarray, intr, size_m: float = 0.15) -> np.ndarray:
    """(16, 3) segment end points (8 segments) of a camera frustum at ``pose_c2w``, world metres."""
    w, h = intr.width, intr.height
    corners = np.array([[(0 - intr.cx) / intr.fx, (0 - intr.cy) / intr.fy, 1.0],
                        [(w - intr.cx) / intr.fx, (0 - intr.cy) / intr.fy, 1.0],
                        [(w - intr.cx) / intr.fx, (h - intr.cy) / intr.fy, 1.0],
                        [(0 - intr.cx) / intr.fx, (h - intr.cy) / intr.fy, 1.0]]) * size_m
    T = np.asarray(pose_c2w, float)
    c = T[:3, 3]
    wc = corners @ T[:3, :3].T + c
    segs = []
    for k in range(4):
        segs += [c, wc[k], wc[k], wc[(k + 1) % 4]]
    return np.asarray(segs)


# --------------------------------------------------------------------------- sensor lab

class LabSession:
    """A sensor-lab folder (``realgap sensor compare --out LABDIR``): the measured sequence, the
    model, the gap history; any frame can be re-simulated with any effect switched off."""

    def __init__(self, labdir: str | os.PathLike):
        from synth.lab.measured import MeasuredSequence
        from synth.sensor.config import SensorConfig
        self.path = Path(labdir)
        cfg_path = self.path / "lab_config.json"
        if not cfg_path.is_file():
            raise FormatError(self.path, "not a sensor-lab folder (lab_config.json missing; made by "
                                         "'realgap sensor compare --out')")
        self.lab_config = json.loads(cfg_path.read_text())
        seq = self.lab_config.get("sequence")
        if not seq:
            raise FormatError(cfg_path, "names no measured sequence")
        self.config = SensorConfig.load(self.path / "sensor_config.json")
        self.enabled = {e.name: bool(e.enabled) for e in self.config.effects}
        self.measured = MeasuredSequence.load(seq, max_frames=self.lab_config.get("frames"),      # the lab's frames
                                              frame_slice=self.lab_config.get("frame_slice"))
        self.metrics = json.loads((self.path / "metrics.json").read_text()) if (self.path / "metrics.json").is_file() \
            else {}
        hist = self.path / "history.json"
        self.history = json.loads(hist.read_text()).get("entries", []) if hist.is_file() else []
        self.seed = int(self.lab_config.get("seed", 0) or 0)

    def __len__(self) -> int:
        return len(self.measured)

    @property
    def effects(self) -> list[str]:
        return list(self.enabled)

    def toggle(self, name: str) -> bool:
        """Switch effect ``name`` on/off; returns its new state."""
        if name not in self.enabled:
            raise RealgapError(f"the lab model has no effect {name!r} ({', '.join(self.enabled)})")
        self.enabled[name] = not self.enabled[name]
        return self.enabled[name]

    def simulate(self, i: int) -> dict:
        """Measured depth, simulated depth (the model with the current on/off switches, the lab's
        seed; the lab's own convention: frame k uses seed + its index) and the residual measured -
        simulated in millimetres (NaN where either is a hole; the sign of the lab's report.html)."""
        import dataclasses
        effects = [e.replace() for e in self.config.effects]
        for e in effects:
            e.enabled = self.enabled[e.name]
        cfg = dataclasses.replace(self.config, effects=effects)
        sim = self.measured.simulate(cfg, seed=self.seed, frames=[i])[0]
        meas = self.measured.measured_depth(i)
        res = np.where((meas > 0) & (sim > 0), (meas - sim) * 1000.0, np.nan).astype(np.float32)
        return {"measured": meas, "simulated": sim, "residual_mm": res}

    def breakdown_figure(self) -> Path | None:
        for name in ("figures/breakdown_distance.png", "figures/history.png"):
            if (self.path / name).is_file():
                return self.path / name
        return None


# --------------------------------------------------------------------------- recognition

class RecogSession:
    """A recognition evaluation (``realgap recog eval --out DIR``) over its test set."""

    def __init__(self, eval_dir: str | os.PathLike, testset: str | os.PathLike):
        from recog.model import Recogniser
        from recog.testset import read_testset
        self.path = Path(eval_dir)
        pj = self.path / "predictions.jsonl"
        if not pj.is_file():
            raise FormatError(self.path, "not a recognition evaluation (predictions.jsonl missing; made by "
                                         "'realgap recog eval --out')")
        self.rows = [json.loads(line) for line in pj.read_text().splitlines() if line.strip()]
        ev = json.loads((self.path / "eval.json").read_text())
        model_path = next((Path(i["path"]).parent for i in ev["header"]["inputs"] if i["role"] == "model"), None)
        if model_path is None:
            raise FormatError(self.path / "eval.json", "names no model")
        self.model = Recogniser.load(model_path)
        self.camera, scans = read_testset(testset, self.model.names)
        self.scans = {s.file: s for s in scans}
        self.testset = Path(testset)
        self.summary = {k: ev.get(k) for k in ("accuracy", "accuracy_descriptor", "n_scans")}
        self.icp = bool(ev.get("icp", True))
        """Whether the evaluation refined by ICP (``recog eval --no-icp``: the viewer shows the same answers)."""
        self.synda = ev.get("synda")
        """The SynDA generator the evaluation read through (``recog eval --synda``), or None."""
        if self.synda:
            from recog.synda.run import use_synda
            use_synda(self.model, self.synda)
        self.reads_colour = self.model.reads_colour
        """The descriptor reads the scans' colour images (a colour recogniser, or an rgb generator in front)."""
        if self.reads_colour and any(sc.rgb is None for sc in scans):
            raise FormatError(self.testset / "labels.json", "this evaluation read colour images, these scans have "
                                                            "none (give the colour test set it was made on)")

    def __len__(self) -> int:
        return len(self.rows)

    def scan(self, i: int) -> dict:
        """Measured points (camera frame) of scan i's window, the recognised model's mesh at the
        estimated pose, and whether it was right; with a SynDA evaluation also the patch the generator
        read (``patch``: (S, S) normalised depth, or (S, S, 3) uint8 colour for an rgb generator) and its
        mapping (``mapped``, (S, S) normalised depth); for a colour recogniser the colour patch it read."""
        from data_tools.sequence import read_depth_png, read_rgb_image
        row = self.rows[i]
        sc = self.scans[row["file"]]
        depth = read_depth_png(self.testset / sc.file, self.camera.depth_scale)
        intr = self.camera.intrinsics
        rgb = read_rgb_image(self.testset / sc.rgb, (intr.height, intr.width)) if self.reads_colour else None
        pred = self.model.predict(depth, intr, sc.bbox, icp=self.icp, colour=rgb)
        x0, y0, x1, y1 = sc.bbox
        gx, gy = (x1 - x0) // 2, (y1 - y0) // 2
        x0, y0, x1, y1 = max(x0 - gx, 0), max(y0 - gy, 0), x1 + gx, y1 + gy
        win = depth[y0:y1, x0:x1]
        vv, uu = np.nonzero(win > 0)
        z = win[vv, uu]
        pts = np.stack([(uu + x0 - intr.cx) / intr.fx * z, (vv + y0 - intr.cy) / intr.fy * z, z], 1)
        obj = self.model.object(self.model.index_of(pred.object))
        mesh = obj.merged().transformed(pred.pose)
        out = {"points": pts, "mesh": mesh, "object": sc.object, "predicted": pred.object,
               "correct": pred.object == sc.object, "file": sc.file, "pose_true": sc.pose, "pose": pred.pose}
        if self.synda or self.reads_colour:
            from recog.patches import extract_patch
            p = extract_patch(depth, intr, sc.bbox, self.model.patch)
            if self.reads_colour:
                from recog.synda.colour_testset import colour_patch
                c = colour_patch(rgb, intr, p, self.model.patch)              # (3, S, S) in [-1, 1]
                out["patch"] = np.clip((c.transpose(1, 2, 0) + 1.0) * 127.5, 0, 255).astype(np.uint8)
                if self.synda:
                    out["mapped"] = np.asarray(self.model.patch_map(c))
            else:
                out.update(patch=p.image, mapped=np.asarray(self.model.patch_map(p.image)))
        return out


SAME_FRAME_S = 1e-3
"""Timestamps of a sequence and of its simulation closer than this are the same frame."""


def load_session(paths: list[str], lab: str | None = None, recog: list[str] | None = None):
    """The session the arguments of ``realgap view`` describe (RealgapError naming a bad path)."""
    from data_tools.outputs import check_input_dir
    if lab:
        return LabSession(check_input_dir(lab, "lab folder", "--lab"))
    if recog:
        ev = Path(recog[0])
        if ev.is_file() and ev.name.endswith(".json"):      # the eval.json itself
            ev = ev.parent
        return RecogSession(check_input_dir(ev, "evaluation folder", "--recog"),
                            check_input_dir(recog[1], "test set folder", "--recog"))
    if not paths:
        raise RealgapError("give a sequence and/or run folders (or --lab LABDIR, --recog EVAL TESTSET)")
    seq, sim, runs = None, None, []
    for p in paths:
        d = check_input_dir(p, "sequence or run folder")
        if _is_run(d):
            runs.append(d)
        elif _is_sequence(d):
            if seq is None:
                seq = d
            elif sim is None:
                sim = d
            else:
                raise RealgapError(f"{d}: a third sequence (view a sequence, optionally its simulation, and runs)")
        else:
            raise FormatError(d, "neither a sequence (depth.txt) nor a SLAM run (config.json + trajectory.txt)")
    if sim is not None:
        from data_tools.sequence import SequenceReader
        a, b = SequenceReader(seq), SequenceReader(sim)
        if tuple(a.intrinsics.shape) != tuple(b.intrinsics.shape):
            raise FormatError(sim, f"its images are {b.intrinsics.width}x{b.intrinsics.height} px, the sequence's "
                                   f"{a.intrinsics.width}x{a.intrinsics.height} px (the second sequence must be a "
                                   f"simulation of the first)")
        ta, tb = np.asarray(a.timestamps, float), np.asarray(b.timestamps, float)
        j = np.clip(np.searchsorted(ta, tb), 1, max(len(ta) - 1, 1)) if len(ta) > 1 else np.zeros(len(tb), int)
        near = np.minimum(np.abs(ta[j] - tb), np.abs(ta[j - 1] - tb)) if len(ta) > 1 else np.abs(ta[0] - tb)
        if not len(tb) or np.mean(near < SAME_FRAME_S) < 0.5:
            raise FormatError(sim, f"shares no timestamp with the sequence for {np.mean(near >= SAME_FRAME_S):.0%} "
                                   f"of its frames (the second sequence must be a simulation of the same frames)")
    return SequenceSession(seq, runs, sim)
