"""``neural``: registration by the neural allocentric spatial memory (thesis chapter 4, MapNet-style).

Only observations are used - no odometry, no poses beyond the first frame's. The first frame's
ground-truth pose (``groundtruth.txt``) gives the world frame, the camera height, pitch and roll
(a ground robot: they stay fixed); the memory estimates x, y and yaw of the others:

1. every ``stride``-th processed frame is a *memory step*: its RGB-D image is reduced to the
   network's size, its pixels are ground-projected into the r turned egocentric grids
   (:mod:`slam.neural.data3d`, :mod:`slam.neural.geometry3d`);
2. the trained model (``model``, default the project's shipped ``slam/neural/weights/planar_3d``)
   registers the steps one after the other: the pose field of each step against the memory so far
   (searched around the previous estimate; each pose scored on the memory cells observed so far,
   ``score`` ``overlap``, not the thesis' sum over the whole view, ``sum``; times a Gaussian motion
   prior on the move from it: ``prior_move_m``, ``prior_turn_deg``; 0 and ``sum`` = the thesis'
   plain field), then the LSTM memory update;
3. the pose of a step is the field's maximum refined to sub-cell / sub-heading precision by the
   centroid of the field over its 3 x 3 neighbours and the two neighbouring headings (the grid
   itself is ``cell_m`` = 15 cm and 30 deg coarse);
4. frames between memory steps get poses interpolated in time (linear x, y; shortest-arc yaw) and
   say so in their ``reason`` (the last processed frame is always a memory step).

``fitness`` of a step is the pose field's maximum probability (1 = certain). The memory (features
and occupancy, ``.npy``) and PNG pictures of the occupancy (stretched to its own range) and of the
memory's three principal feature components on the observed cells (those some registered view field
covered, ``observed.npy``; not the occupancy LSTM's output, see :mod:`slam.neural.memory`) are
written to ``RUN/memory/`` (:meth:`NeuralBackend.save_outputs`), with the decoded top view
(``topview.png``: the trained per-cell colour read-out of :mod:`slam.neural.topview`, row 0 = ahead of
the first frame) when the model has one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import ConfigError, FormatError
from slam.registration import RegistrationBackend, TrackResult, register_backend

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "neural" / "weights" / "planar_3d"
"""The project's own 3D weights (``realgap neural train --mode 3d``; see their README)."""


@dataclass
class NeuralConfig:
    """Options of the neural registration backend."""

    model: str = ""
    """Model folder made by ``realgap neural train --mode 3d`` (empty: the shipped planar_3d weights)."""
    stride: int = 10
    """Processed frames between two memory steps (training used 5-15 frames at 30 fps)."""
    max_reach_m: float = 12.0
    """The memory covers this distance from the first frame in every direction, metres."""
    refine: bool = True
    """Refine the field's maximum to sub-cell / sub-heading precision (centroid of its neighbours)."""
    prior_move_m: float = 0.15
    """Motion prior: standard deviation of the planar move between two memory steps, metres (0 = no prior,
    the thesis' field). The default is the training rooms' motion at ``stride`` 10 (RMS 0.10 m per step)
    widened by the grid's rounding (one 15 cm cell); scale it with ``stride`` and the robot's speed."""
    prior_turn_deg: float = 15.0
    """Motion prior: standard deviation of the turn between two memory steps, degrees (0 = no prior): half a
    heading step of the shipped model, chosen on held-out rooms no training used (docs/neural.md)."""

    score: str = "overlap"
    """How a pose is scored against the memory: ``overlap`` (the view's agreement with the memory averaged over the
    view cells that fall on observed memory cells; not in the thesis) or ``sum`` (the thesis' correlation summed
    over the whole view). With ``sum`` the shipped model's heading never leaves the first frame's: the pose whose
    view re-covers the last written one scores highest (docs/neural.md)."""

    def validate(self) -> "NeuralConfig":
        if int(self.stride) < 1:
            raise ConfigError(f"neural.stride must be >= 1, got {self.stride}")
        if not self.max_reach_m > 0:
            raise ConfigError(f"neural.max_reach_m must be > 0, got {self.max_reach_m}")
        if not (self.prior_move_m >= 0 and self.prior_turn_deg >= 0):
            raise ConfigError(f"neural.prior_move_m and neural.prior_turn_deg must be >= 0, got "
                              f"{self.prior_move_m}, {self.prior_turn_deg}")
        from slam.neural.config import POSE_SCORES
        if self.score not in POSE_SCORES:
            raise ConfigError(f"neural.score must be one of {POSE_SCORES}, got {self.score!r}")
        if (self.prior_move_m == 0) != (self.prior_turn_deg == 0):
            raise ConfigError("neural.prior_move_m and neural.prior_turn_deg: set both > 0 (a motion prior) or both "
                              "to 0 (none)")
        return self

    def motion_prior(self, cell_m: float, rotations: int) -> tuple[float, float] | None:
        """(sigma in cells, sigma in heading steps of 2 pi / ``rotations``) of the motion prior, or None."""
        if self.prior_move_m == 0:
            return None
        return self.prior_move_m / cell_m, self.prior_turn_deg / (360.0 / rotations)


@register_backend
class NeuralBackend(RegistrationBackend):
    name = "neural"
    Config = NeuralConfig
    online = False
    uses_color = True

    def __init__(self, config, intrinsics, tsdf_config, sensor=None):
        super().__init__(config, intrinsics, tsdf_config, sensor)
        self._snap: dict | None = None

    def _load(self):
        from slam.neural.io import load_model
        folder = Path(self.config.model) if self.config.model else DEFAULT_MODEL
        model, tcfg, info = load_model(folder)
        if tcfg.mode != "3d":
            raise FormatError(folder / "neural.json", f"a {tcfg.mode} model; the neural backend needs a 3d one "
                                                      "(realgap neural train --mode 3d)")
        return model, tcfg, folder

    def run_offline(self, reader, indices, progress=True):
        from slam.neural.data3d import frame_arrays, view_geometry
        from slam.neural.fields import refine_peak
        from slam.neural.geometry3d import allocentric_to_world
        self.config.validate()
        model, tcfg, folder = self._load()
        w = tcfg.world
        T0 = reader.poses[indices[0]]
        if not np.all(np.isfinite(T0)):
            raise FormatError(reader.path, "the neural backend needs the first frame's pose (groundtruth.txt): it "
                                           "fixes the world frame, the camera height, pitch and roll")
        R_c_L, wedge = view_geometry(reader.intrinsics, T0, w)
        steps = list(range(0, len(indices), int(self.config.stride)))
        if steps[-1] != len(indices) - 1:
            steps.append(len(indices) - 1)
        imgs, cells = [], []
        bar = None
        if progress:
            from data_tools.progress import progress_bar
            bar = progress_bar(total=len(steps), desc="neural: encoding frames", unit="frame")
        for s in steps:
            f = reader[indices[s]]
            if f.rgb is None:
                raise FormatError(reader.path, f"frame {indices[s]} has no colour image: the neural model reads RGB-D")
            img, c = frame_arrays(f.rgb, f.depth, reader.intrinsics, R_c_L, w)
            imgs.append(img)
            cells.append(c)
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        reach = int(math.ceil(self.config.max_reach_m / w.cell_m))
        from slam.neural.inference import register_sequence
        out = register_sequence(model, np.stack(imgs), np.stack(cells), wedge, w.view + 2 * reach,
                                motion_prior=self.config.motion_prior(w.cell_m, model.cfg.rotations),
                                score=self.config.score)
        fields, centres = out["fields"], out["centres"]
        r = model.cfg.rotations
        est, conf = [], []
        for t in range(len(steps)):
            if t == 0:
                est.append((0.0, 0.0, 0.0))
                conf.append(None)
                continue
            row, col, kk, p = refine_peak(fields[t], centres[t], self.config.refine)
            est.append((row, col, kk * 2 * math.pi / r))
            conf.append(p)
        key_poses = [allocentric_to_world(T0, a, b, y, w.cell_m) for a, b, y in est]
        self._snap = {"psi": out["psi"], "occ": out["occ"], "seen": out["seen"], "cell_m": w.cell_m,
                      "T0": T0, "model": str(folder), "steps": [int(indices[s]) for s in steps],
                      "estimates": [list(map(float, e)) for e in est]}
        return self._all_frames(reader, indices, steps, key_poses, est, conf, T0, w.cell_m)

    def _all_frames(self, reader, indices, steps, key_poses, est, conf, T0, cell_m):
        from slam.neural.geometry3d import allocentric_to_world
        results = [None] * len(indices)
        for t, s in enumerate(steps):
            results[s] = TrackResult(key_poses[t], conf[t], None, False, "memory step" if t else "first frame")
        ts = reader.timestamps[np.asarray(indices)]
        for t in range(len(steps) - 1):
            a, b = steps[t], steps[t + 1]
            ea, eb = np.asarray(est[t]), np.asarray(est[t + 1])
            dyaw = (eb[2] - ea[2] + math.pi) % (2 * math.pi) - math.pi
            for s in range(a + 1, b):
                al = (ts[s] - ts[a]) / max(ts[b] - ts[a], 1e-12)
                row, col = ea[:2] + al * (eb[:2] - ea[:2])
                results[s] = TrackResult(allocentric_to_world(T0, row, col, ea[2] + al * dyaw, cell_m), None, None,
                                         False, "interpolated between memory steps")
        return results

    def save_outputs(self, out: Path) -> None:
        """RUN/memory/: memory.npy (n, U, U) features, occupancy.npy (U, U), observed.npy (U, U) uint8 (1 on the cells
        a registered view field covered), memory.json (cell size, first
        pose, model, memory steps and their allocentric estimates), occupancy.png, features.png, and topview.png
        (the decoded colour floor plan, unobserved cells dimmed) when the model has a top-view decoder."""
        if self._snap is None:
            return
        from data_tools.results import atomic_write_bytes, atomic_write_image, atomic_write_json
        d = Path(out) / "memory"
        d.mkdir(parents=True, exist_ok=True)
        import io
        for name, file, dtype in (("psi", "memory.npy", np.float32), ("occ", "occupancy.npy", np.float32),
                                  ("seen", "observed.npy", np.uint8)):
            buf = io.BytesIO()
            np.save(buf, self._snap[name].astype(dtype))
            atomic_write_bytes(d / file, buf.getvalue())
        atomic_write_json(d / "memory.json", {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                                              for k, v in self._snap.items() if k not in ("psi", "occ", "seen")})
        occ, seen = self._snap["occ"], self._snap["seen"]
        span = max(float(occ.max() - occ.min()), 1e-9)
        atomic_write_image(d / "occupancy.png", ((occ - occ.min()) / span * 255).astype(np.uint8))
        atomic_write_image(d / "features.png", memory_picture(self._snap["psi"], seen))
        from slam.neural.topview import decode_topview, load_topview, topview_picture
        dec = load_topview(self._snap["model"], self._snap["psi"].shape[0])
        if dec is not None:      # the model's trained top-view decoder: the map's colours
            atomic_write_image(d / "topview.png", topview_picture(decode_topview(dec, self._snap["psi"], occ), seen))


def memory_picture(psi: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(U, U, 3) uint8 BGR top view of a memory (n, U, U): its three principal feature components as
    colours on the ``seen`` (U, U) cells, black elsewhere (row 0 = ahead of the first frame)."""
    n, U, _ = psi.shape
    X = psi.reshape(n, -1).T
    seen = seen.reshape(-1)
    out = np.zeros((U * U, 3))
    if seen.sum() >= 3:
        Y = X[seen] - X[seen].mean(0)
        _, _, Vt = np.linalg.svd(Y, full_matrices=False)
        C = Y @ Vt[:3].T
        lo, hi = np.percentile(C, 2, axis=0), np.percentile(C, 98, axis=0)
        out[seen, :C.shape[1]] = np.clip((C - lo) / np.maximum(hi - lo, 1e-9), 0, 1)
    return (out.reshape(U, U, 3) * 255).astype(np.uint8)
