"""Benchmark: is h_G's output in the clean recogniser's domain? The in-distribution check behind docs/synda.md's
"why": on views the generator was trained on (``synda train --keep-work`` keeps them in ``GEN.work/data``), the
recogniser's nearest database entry (exact k = 1 search, no vote, no pose) for

    clean          the clean patch (the recogniser's own training domain: its ceiling)
    measured       a measured draw of the same view (the physical pipeline, no augmentation A)
    h(measured)    the generator's output for the measured draw (what ``recog eval --synda`` feeds it)
    h(clean)       the generator's output for the clean patch (a mapping into the clean domain should keep it)

plus the output's L1 to the clean patch over the patch and on the object's pixels, and how many of the outputs
land on each object (a collapse onto one object shows there).

    .venv/bin/python benchmarks/bench_synda_domain.py --recog CLEAN_MODEL --views GEN.work/data \\
        --generator recog/weights/synda_depth/generator.pt [--generator OTHER.pt ...] [--objects chairs] [--n 150] [--out OUT.json]

In-distribution on purpose: a generator that fails here cannot help on unseen sensors. The views must be of the
recogniser's objects, cut with its patch configuration (checked by :func:`recog.synda.run.check_patch_match`).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def nearest_object(model, patches):
    """(N,) object index of the nearest database descriptor of each (N, S, S) patch."""
    import numpy as np
    desc = model.describe(np.ascontiguousarray(patches, np.float32))
    db = model.db.descriptors
    d2 = (desc ** 2).sum(1)[:, None] - 2 * desc @ db.T + (db ** 2).sum(1)[None]
    return model.db.obj[np.argmin(d2, 1)]


def run(recog: str, views: str, generators: list[str], n: int, seed: int, draw: int, objects: str = "chairs") -> dict:
    import numpy as np
    import torch
    from recog.model import Recogniser
    from recog.objects import load_objects
    from recog.synda.data import load_synda_data
    from recog.synda.run import check_patch_match, patch_mapper
    torch.set_num_threads(1)
    model = Recogniser.load(recog)
    objs = load_objects(objects, None)
    if [o.name for o in objs] != model.names:
        raise SystemExit(f"--objects gives {[o.name for o in objs]}, the recogniser knows {model.names}")
    data = load_synda_data(objs, views, True)
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(len(data), min(n, len(data)), replace=False))
    truth = data.obj[idx]
    clean = data.clean[idx].astype(np.float32)
    meas = data.noisy[idx, draw].astype(np.float32)
    mask = data.mask[idx]

    def acc(p):
        o = nearest_object(model, p)
        return {"accuracy": round(float(np.mean(o == truth)), 4),
                "nearest_object_counts": np.bincount(o, minlength=len(model.names)).tolist()}

    res = {"recogniser": recog, "views": views, "n": int(len(idx)), "objects": model.names,
           "clean": acc(clean), "measured": acc(meas), "generators": {}}
    for g in generators:
        fn, info = patch_mapper(g)
        check_patch_match(info, model.patch, g)
        hm, hc = fn(meas), fn(clean)
        res["generators"][g] = {"h(measured)": acc(hm), "h(clean)": acc(hc),
                                "l1_patch": round(float(np.abs(hm - clean).mean()), 4),
                                "l1_object": round(float(np.abs(hm - clean)[mask].mean()), 4)}
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recog", required=True, help="the clean-trained recogniser folder")
    ap.add_argument("--views", required=True, help="GEN.work/data of 'synda train --keep-work' (depth domain)")
    ap.add_argument("--generator", action="append", required=True, help="a depth generator (repeatable)")
    ap.add_argument("--objects", default="chairs", help="the objects of the views, as for synda train (default chairs)")
    ap.add_argument("--n", type=int, default=150, help="views drawn (default 150)")
    ap.add_argument("--draw", type=int, default=0, help="which measured draw of each view (default 0)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="write the result as JSON here")
    a = ap.parse_args(argv)
    res = run(a.recog, a.views, a.generator, a.n, a.seed, a.draw, a.objects)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=1))
    print(f"{res['n']} training views, nearest database object right for: clean {100 * res['clean']['accuracy']:.1f} %, "
          f"measured {100 * res['measured']['accuracy']:.1f} %")
    for g, r in res["generators"].items():
        print(f"{g}: h(measured) {100 * r['h(measured)']['accuracy']:.1f} % {r['h(measured)']['nearest_object_counts']}, "
              f"h(clean) {100 * r['h(clean)']['accuracy']:.1f} %, L1 to clean {r['l1_patch']:.3f} (object {r['l1_object']:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
