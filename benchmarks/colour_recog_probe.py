"""Probe: does the colour recogniser's training (``recog train --input rgb``) learn? Short training runs on the
training views of an existing recogniser folder, then a self-check on new A renders of 400 of its views.

    .venv/bin/python benchmarks/colour_recog_probe.py --data MODEL/data --iterations 150 --set pair_weight=0.1
    .venv/bin/python benchmarks/colour_recog_probe.py --data MODEL/data --iterations 150 --easy
    .venv/bin/python benchmarks/colour_recog_probe.py --data MODEL/data --checkpoint MODEL/checkpoint.pt

``MODEL/data`` holds ``clean`` training chunks of the chairs (``recog train --variant clean``). The self-check: 400
views (fixed choice, seed 0), each rendered twice by A with the seed 12345 (:func:`recog.train.render_colour_views`);
for every view's second render the nearest first render of *another* view: how often it is the same object (chance
1/3 for the chairs) and the median pose angle to it (degrees; the median between random views is printed beside).
``--easy``: a diagnostic of the pipeline, not a baseline - A without texture, occluder, blur or background (the
shaded object on black), for training and self-check alike. ``--checkpoint``: only the self-check of a training
checkpoint (a running or killed ``recog train --input rgb``) or of a finished recogniser's ``weights.pt``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def easy_renderer(data, size: int):
    """A's shading only: no texture, occluder or blur, black (-1) outside the object mask."""
    import numpy as np
    import torch

    from recog.synda.augment import Augmenter
    from recog.synda.config import synda_preset
    from recog.synda.data import normals_from_depth
    cfg = dataclasses.replace(synda_preset("cpu", "rgb").augment, textures=("none",), occluders=(0, 0),
                              blurs=("none",), backgrounds=("perlin",))
    aug = Augmenter(cfg, "rgb", size)
    masks = torch.from_numpy(data.mask)

    def run(x, rows, seed: int):
        m = masks[torch.from_numpy(np.asarray(rows))].to(device=x.device, dtype=torch.float32)[:, None]
        y = aug.apply({"normals": normals_from_depth(x.float()), "mask": m}, aug.draw(len(rows), seed))["input"]
        return y * m - (1 - m)
    return run


def self_check(net, sub, renders) -> dict:
    import numpy as np
    import torch

    from recog.symmetry import sym_angles
    with torch.no_grad():
        d0, d1 = net(torch.from_numpy(renders[:, 0])).numpy(), net(torch.from_numpy(renders[:, 1])).numpy()
    D = ((d1[:, None] - d0[None]) ** 2).sum(-1)
    np.fill_diagonal(D, np.inf)
    nn = D.argmin(1)
    A = np.degrees(sym_angles(sub.R_local, sub.R_local, None))
    return {"same_object": float(np.mean(sub.obj[nn] == sub.obj)),
            "pose_angle_to_nearest_deg": float(np.median(A[np.arange(len(nn)), nn])),
            "pose_angle_random_deg": float(np.median(A[np.triu_indices(len(A), 1)])),
            "spread": float(d0.std(0).mean())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--data", required=True, help="a recogniser's data folder with clean chunks of the chairs")
    ap.add_argument("--objects", default="chairs")
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="TrainConfig overrides (JSON values), e.g. pair_weight=0.0, network=\"deeper\"")
    ap.add_argument("--easy", action="store_true", help="the pipeline diagnostic (see the module docstring)")
    ap.add_argument("--checkpoint", help="self-check this training checkpoint instead of training")
    args = ap.parse_args(argv)
    import numpy as np
    import torch
    torch.set_num_threads(1)
    import recog.train as T
    from recog.data import DataConfig, load_training_data
    from recog.net import make_network
    from recog.objects import load_objects
    from recog.symmetry import detect_symmetry
    if args.easy:
        T.colour_renderer = easy_renderer
    objs = load_objects(args.objects)
    for o in objs:
        o.symmetry = detect_symmetry(o.merged())
    td = load_training_data(objs, DataConfig(variant="clean"), args.data)
    sel = np.sort(np.random.default_rng(0).choice(len(td), 400, replace=False))
    sub = dataclasses.replace(td, patches=td.patches[sel], obj=td.obj[sel], view=td.view[sel],
                              R_local=td.R_local[sel], offset=td.offset[sel], mask=td.mask[sel])
    renders = T.render_colour_views(sub, 64, 12345)
    over = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    cfg = dataclasses.replace(T.TrainConfig(), input="rgb", log_every=25, iterations=args.iterations, **over)
    t0 = time.perf_counter()
    if args.checkpoint:
        st = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
        net = make_network(cfg.network, 64, cfg.descriptor, 3)
        net.load_state_dict(st["net"] if "net" in st else st)       # a checkpoint or a recogniser's weights.pt
        net.eval()
        res = {"checkpoint": args.checkpoint, "step": int(st["step"]) if "step" in st else None}
    else:
        net, log = T.train_network(td, [o.symmetry for o in objs], cfg, 64, progress=False)
        res = {"overrides": over, "easy": args.easy, "iterations": args.iterations,
               "log": [{k: round(v, 3) for k, v in s.items()} for s in log.steps]}
    res.update(self_check(net, sub, renders), seconds=round(time.perf_counter() - t0, 1))
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
