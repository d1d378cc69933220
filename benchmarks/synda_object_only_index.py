"""A recogniser's network with its database re-indexed on object-only clean patches (for SynDA's colour domain).

SynDA's rgb generator outputs depth on the object and far (+1) elsewhere: it cannot know the ground and clutter
behind a photographed object. The recogniser's database, though, holds patches with the ground and clutter around
the object (``recog.data``), so even a perfect mapping would be compared with views of another kind. This script
keeps a trained recogniser's network and rebuilds its database from the **clean** renderer's views of the same
grid with every pixel outside the object set to +1 (the chunks' object ``mask``), so that the database looks
like what SynDA writes (the thesis' recogniser is trained on renders of the object alone). The network is not
retrained; recogniser.json's ``info.reindexed`` says how the database was made.

    .venv/bin/python benchmarks/synda_object_only_index.py recog/weights/chairs OUT_MODEL [--work DIR]
"""
from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("out")
    ap.add_argument("--work", help="folder for the clean views (default OUT/data)")
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args(argv)
    import torch
    torch.set_num_threads(1)
    from recog.data import generate_training_data, load_training_data
    from recog.database import DescriptorDB
    from recog.model import Recogniser
    model = Recogniser.load(args.model)
    out = Path(args.out)
    work = Path(args.work) if args.work else out / "data"
    objs = [model.object(k) for k in range(len(model.names))]
    views = dataclasses.replace(model.data, variant="clean")
    t0 = time.perf_counter()
    generate_training_data(objs, views, model.patch, work, workers=args.workers, progress=False)
    td = load_training_data(objs, views, work)
    if td.mask is None:
        raise SystemExit("the chunks hold no object masks")
    patches = np.where(td.mask, td.patches[:, 0].astype(np.float32), 1.0).astype(np.float32)
    desc = model.describe(patches)
    model.db = DescriptorDB(desc, td.obj, td.R_local, td.offset[:, 0], td.view, "auto")
    model.info = {**model.info, "reindexed": {"from": str(args.model), "views": "clean, object only (+1 elsewhere)",
                                              "entries": int(len(desc)), "seconds": round(time.perf_counter() - t0, 1),
                                              "command": "benchmarks/synda_object_only_index.py " + " ".join(
                                                  sys.argv[1:] if argv is None else argv)}}
    out.mkdir(parents=True, exist_ok=True)
    model.save(out)
    print(f"{out}: {len(desc)} object-only database entries ({time.perf_counter() - t0:.0f} s)")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
