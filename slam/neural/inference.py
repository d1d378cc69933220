"""Inference with a trained neural memory, as the rest of realgap calls it: register a sequence of 3D memory
steps (:func:`register_sequence`: the ``neural`` registration backend), recall or hallucinate the view at a
camera pose from a neural run's memory snapshot (:func:`recall_view`: ``slam render`` and the viewer)."""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["register_sequence", "recall_view"]


def register_sequence(model, images, cells, wedge, memory: int, motion_prior=None, score: str = "sum") -> dict:
    """Run a 3D model over one sequence of memory steps: images (T, 4, H, W), cells (T, r, H * W), the view
    wedge (q, q) bool, a memory of side ``memory`` cells, ``motion_prior`` (sigma cells, sigma heading steps) or
    None, ``score`` sum | overlap (:meth:`slam.neural.memory.NeuralMemory.forward`). Returns numpy arrays: fields
    (T, r, P, P) local pose fields, centres (T, 2) allocentric middle of each field, psi (n, U, U), occ (U, U) and
    seen (U, U) bool (the cells a registered view field covered)."""
    import numpy as np
    import torch
    vm = torch.from_numpy(np.asarray(wedge, np.float32))
    with torch.no_grad():
        out = model(torch.from_numpy(np.asarray(images, np.float32))[None], vm, None,
                    cells=torch.from_numpy(np.asarray(cells, np.int64))[None], memory=int(memory),
                    motion_prior=motion_prior, score=score)
    return {"fields": out["fields"][0].numpy(), "centres": out["centres"][0].numpy(),
            "psi": out["psi"][0].numpy(), "occ": out["occ"][0, 0].numpy(), "seen": out["seen"][0, 0].numpy() > 0}


def recall_view(run_dir: str | os.PathLike, pose_c2w, hallucinate: bool = False, size: tuple[int, int] | None = None):
    """The view a neural run's memory recalls at camera-to-world ``pose_c2w`` (4, 4): RUN/memory's
    features at the pose (a window culled at the pose rounded to the memory's cell and heading grid) decoded by the
    run's model; with ``hallucinate`` the hallucination module fills the memory's unobserved cells
    first. Returns (rgb (H, W, 3) uint8, depth (H, W) float32 metres, 0 = none): the decoder's
    image (40 x 30 for the shipped model), resized to ``size`` = (W, H) when given (bilinear)."""
    import json

    import cv2
    import numpy as np
    import torch

    from data_tools.errors import FormatError
    from slam.neural.geometry3d import planar_relative
    from slam.neural.io import load_model
    d = Path(run_dir) / "memory"
    meta_p = d / "memory.json"
    if not meta_p.is_file():
        raise FormatError(run_dir, "not a neural run (memory/memory.json missing; made by 'slam run --backend neural')")
    meta = json.loads(meta_p.read_text())
    model, tcfg, _ = load_model(meta["model"])
    try:
        psi = torch.from_numpy(np.load(d / "memory.npy"))[None]
        occ = torch.from_numpy(np.load(d / "occupancy.npy"))[None, None]
    except (OSError, ValueError) as e:
        raise FormatError(d, f"unreadable memory snapshot ({e})") from None
    if psi.shape[1] != model.cfg.features:
        raise FormatError(d / "memory.npy", f"{psi.shape[1]} features per cell, the model {meta['model']} has "
                                            f"{model.cfg.features}")
    cell, T0 = float(meta["cell_m"]), np.asarray(meta["T0"])
    row, col, yaw = planar_relative(T0, np.asarray(pose_c2w, float), cell)
    k = yaw / (2 * np.pi / model.cfg.rotations)          # heading in units of the memory's turns (real)
    U = psi.shape[-1]
    if max(abs(row), abs(col)) > U // 2:
        raise FormatError(meta_p, f"the pose is {max(abs(row), abs(col)) * cell:.1f} m from the first frame, "
                                  f"outside the memory ({U // 2 * cell:.1f} m)")
    w = tcfg.world
    from data_tools.camera import read_camera_json
    from slam.neural.data3d import view_geometry
    _, wedge = view_geometry(read_camera_json(Path(run_dir) / "camera.json").intrinsics, T0, w)
    vm = torch.from_numpy(wedge.astype(np.float32))
    with torch.no_grad():
        mem = model.hallucinate(psi, occ) if hallucinate else psi
        img = model.recall(mem, torch.tensor([[row, col, k]], dtype=torch.float32), vm)[0].numpy()
    rgb = np.clip((np.transpose(img[:3], (1, 2, 0)) + 1) / 2, 0, 1)
    depth = (img[3] + 1) / 2 * w.max_range_m
    depth = np.where(img[3] > -0.95, depth, 0.0).astype(np.float32)
    if size is not None:
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR)
        depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
    return (rgb * 255).round().astype(np.uint8), depth
