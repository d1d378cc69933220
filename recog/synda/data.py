"""SynDA's training data: clean synthetic modalities of the recogniser's objects, and for the depth
domain the same views measured by the project's sensor simulator with randomised effects.

The views are exactly the recogniser's (:mod:`recog.data`): the same viewpoint grid, jitter,
distance range, ground plane, clutter and chunking, with :class:`recog.data.DataConfig` as the
configuration. Per view and chunk file ``WORK/data/<object>/chunk_NNN.npz``:

* ``clean`` (n, S, S) float16: the ideal depth (the renderer alone, ``clean`` variant) cut into the
  recogniser's normalised patch (:func:`recog.patches.extract_patch`) - the target domain;
* ``mask`` (n, S, S) bool: the object's pixels in that patch (the renderer's instance ids);
* ``noisy`` (n, K, S, S) float16 (depth domain only): K simulations of the view by the full
  physical pipeline of the sensor preset, each with its own parameters drawn from
  :data:`recog.data.PHYSICAL_RANDOMISATION` (the randomised sensor effects; every effect draws its
  random numbers with ``sample`` and applies them with ``apply``, seeded per view and draw) and cut
  with the clean patch's virtual camera and reference depth, so that input and target align pixel
  by pixel (:func:`recog.patches.depth_patch`).

Deviation, on purpose: the issue draws the sensor effects every iteration as part of A; here they are drawn per
view (K draws, stored) and every training step picks one of them, because the full physical pipeline of a view
costs ~0.07 s (one core), ~3x a training step's share of a sample. See docs/synda.md, "Deviations".

Normals are not stored: :func:`normals_from_depth` derives them from a (clean) normalised depth
patch when a batch is built, so that they also follow the backgrounds A composes.

Deviation, on purpose: the noisy patch is cut with the clean view's reference depth z_ref, where a
measured scan uses its own (the 10th percentile of its measured depths); the two differ by ~1 mm
(see :mod:`recog.patches`), 0.002 normalised units for the chairs' 1.2 m crop.
"""
from __future__ import annotations

import io
import math
import os
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError
from recog.data import DataConfig, chunk_scene, jittered_pose, sensor_config, view_grid
from recog.objects import RecogObject
from recog.patches import PatchConfig, bbox_from_mask, depth_patch, extract_patch, resample_nearest

__all__ = ["SyndaData", "generate_synda_data", "load_synda_data", "normals_from_depth", "simulate_views"]

MIN_OBJECT_PX = 50
"""A view whose object covers fewer image pixels is left out (nothing to learn from)."""


def _seed(config: DataConfig, name: str, key, salt: str) -> int:
    return zlib.crc32(f"synda/{config.seed}/{name}/{key}/{salt}".encode()) & 0x7FFFFFFF


def simulate_views(obj: RecogObject, config: DataConfig, patch: PatchConfig, chunk: int, views: list[int],
                   noisy: bool) -> dict:
    """Clean patch, object mask and (``noisy``) ``config.draws`` physical-pipeline patches of the grid views
    ``views`` of one object (one chunk: one clutter layout and albedo; one randomised sensor per draw)."""
    from synth.sensor.simulator import SensorSimulator
    cs = chunk_scene(obj, config, chunk, lambda key, salt: _seed(config, obj.name, key, salt))
    dirs, rolls, dist, w, h = cs.dirs, cs.rolls, cs.dist, cs.width, cs.height
    scene, obj_ids, centre = cs.scene, cs.obj_ids, cs.centre
    clean_sim = SensorSimulator(sensor_config("clean", config.preset, w, h), None, scene)
    sims = [SensorSimulator(sensor_config("physical", config.preset, w, h,
                                          np.random.default_rng(_seed(config, obj.name, chunk, f"sensor{d}"))),
                            None, scene) for d in range(config.draws if noisy else 0)]
    intr = clean_sim.preset.intrinsics
    n, K, S = len(views), len(sims), patch.size
    out = {"clean": np.ones((n, S, S), np.float16), "mask": np.zeros((n, S, S), bool),
           "noisy": np.ones((n, K, S, S), np.float16), "view": np.asarray(views, np.int32), "ok": np.zeros(n, bool)}
    for k, v in enumerate(views):
        rng_v = np.random.default_rng(_seed(config, obj.name, v, "pose"))
        T_c2w = jittered_pose(rng_v, dirs[v], rolls[v], centre, dist, config.jitter_deg, 0.1 * obj.diameter_m)
        res = clean_sim.simulate(T_c2w, seed=0, with_rgb=False)
        ids = np.isin(res.instance_ids, np.asarray(obj_ids) + 1)
        box = bbox_from_mask(ids)
        if box is None or ids.sum() < MIN_OBJECT_PX:
            continue
        p = extract_patch(res.depth, intr, box, patch)
        out["clean"][k] = p.image
        out["mask"][k] = resample_nearest(ids, intr, p.R_ray, p.z_ref_m, patch) > 0.5
        for d, sim in enumerate(sims):
            r = sim.simulate(T_c2w, seed=_seed(config, obj.name, v, f"noise{d}"), with_rgb=False)
            out["noisy"][k, d] = depth_patch(r.depth, intr, p.R_ray, p.z_ref_m, box, patch).image
        out["ok"][k] = bool(out["mask"][k].any())
    return out


def _run(args) -> str:
    obj, config, patch, chunk, views, noisy, path = args
    data = simulate_views(obj, config, patch, chunk, views, noisy)
    from data_tools.results import atomic_write_bytes
    buf = io.BytesIO()
    np.savez_compressed(buf, **data)
    atomic_write_bytes(path, buf.getvalue())
    return path


def generate_synda_data(objects: list[RecogObject], config: DataConfig, patch: PatchConfig, out_dir,
                        noisy: bool, workers: int = 1, progress: bool = True) -> int:
    """Simulate every missing chunk into ``out_dir/<object>/`` (a killed run continues with the missing
    ones); returns the number of chunks made now."""
    config.validate()
    n_views = len(view_grid(config)[0])
    jobs = []
    for obj in objects:
        for c, start in enumerate(range(0, n_views, config.chunk_views)):
            f = Path(out_dir) / obj.name / f"chunk_{c:03d}.npz"
            if not f.is_file():
                f.parent.mkdir(parents=True, exist_ok=True)
                jobs.append((obj, config, patch, c, list(range(start, min(start + config.chunk_views, n_views))),
                             noisy, str(f)))
    if not jobs:
        return 0
    total = len(objects) * math.ceil(n_views / config.chunk_views)
    from recog.data import run_chunks
    run_chunks(_run, jobs, workers, progress, total, "simulating SynDA views")
    return len(jobs)


@dataclass
class SyndaData:
    """Every usable view of every object, in memory."""

    clean: np.ndarray
    """(N, S, S) float16 clean normalised depth patches in [-1, 1]."""
    mask: np.ndarray
    """(N, S, S) bool object masks."""
    noisy: np.ndarray
    """(N, K, S, S) float16 measured (simulated) patches of the same views; K = 0 for the rgb domain."""
    obj: np.ndarray
    """(N,) int object index."""

    def __len__(self) -> int:
        return len(self.obj)


def load_synda_data(objects: list[RecogObject], out_dir, noisy: bool) -> SyndaData:
    """Read the chunks of every object (views without a visible object left out)."""
    parts: dict[str, list] = {k: [] for k in ("clean", "mask", "noisy", "obj")}
    for i, obj in enumerate(objects):
        files = sorted((Path(out_dir) / obj.name).glob("chunk_*.npz"))
        if not files:
            raise FormatError(Path(out_dir) / obj.name, "no SynDA training chunks (generate the data first)")
        for f in files:
            try:
                z = np.load(f)
                ok = z["ok"]
                if noisy and z["noisy"].shape[1] == 0:
                    raise KeyError("noisy")
                for k in ("clean", "mask", "noisy"):
                    parts[k].append(z[k][ok])
                parts["obj"].append(np.full(int(ok.sum()), i, np.int32))
            except (OSError, ValueError, KeyError) as e:
                raise FormatError(f, f"unreadable SynDA training chunk ({type(e).__name__}); delete it to make it "
                                     f"again") from None
    return SyndaData(*(np.concatenate(parts[k]) for k in ("clean", "mask", "noisy", "obj")))


def normals_from_depth(depth, size: int | None = None):
    """(B, 3, S, S) unit normals (camera frame: x right, y down, z forward; facing the camera n_z < 0) of
    (B, 1, S, S) normalised depth patches (torch). The patch spans ``crop_m`` at z_ref and its depth unit is
    ``crop_m / 2``, so a metric slope is the normalised one times S / 2 per pixel; central differences
    (one-sided at the border). Approximation: orthographic (the virtual camera's small field of view)."""
    import torch
    s = depth.shape[-1] if size is None else size
    gy, gx = torch.gradient(depth[:, 0], dim=(1, 2))
    k = s / 2.0
    n = torch.stack([gx * k, gy * k, -torch.ones_like(gx)], 1)
    return n / n.norm(dim=1, keepdim=True)


def data_bytes(d: SyndaData) -> int:
    """Memory the data holds (bytes)."""
    return int(d.clean.nbytes + d.mask.nbytes + d.noisy.nbytes + d.obj.nbytes)


def folder_chunks(path: str | os.PathLike) -> int:
    """Chunk files already in a data folder (the resume report)."""
    p = Path(path)
    return sum(1 for _ in p.glob("*/chunk_*.npz")) if p.is_dir() else 0
