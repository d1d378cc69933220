"""Benchmark: the thesis' comparison (section 3.4.3, Fig. 3.12) - the same triplet-CNN recogniser
trained on clean, gaussian-noise and physically simulated views, tested on the same "measured"
scans made by another sensor.

    .venv/bin/python benchmarks/bench_recog.py [--set tless|chairs] [--variants clean,gaussian,physical]
                                               [--per-object 40] [--out bench_out/recog] [--networks lenet]

``--set tless``: T-LESS obj_01-06 from ../shared/data/tless_cad (six look-alike industrial parts,
millimetre CAD); ``--set chairs``: the three near-identical embedded office chairs. Training views
come from the kinect_v1 sensor (``realgap recog train``, cpu preset); the test scans from the
``structure`` preset's full physical pipeline (``realgap recog testset``: another projector,
baseline and focal length, random continuous viewpoints, off-centre objects, other clutter).
The baseline is the ``clean`` variant (ideal depth), measured in the same run on the same scans.
Everything is resumable: a re-run reuses finished recognisers and test sets in ``--out``.

Prints one row per variant (and network): accuracy, symmetry-aware rotation error (median before
and after ICP, share within 20 deg), translation error after ICP, training time; writes
``OUT/bench_recog_<set>.json``. On 2 CPU cores the three T-LESS variants take about 40 minutes.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--set", choices=("tless", "chairs"), default="tless")
    ap.add_argument("--variants", default="clean,gaussian,physical")
    ap.add_argument("--networks", default="lenet")
    ap.add_argument("--per-object", type=int, default=40)
    ap.add_argument("--iterations", type=int, default=None, help="override the cpu preset's 3000 steps")
    ap.add_argument("--out", default="bench_out/recog")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    os.environ.setdefault("REALGAP_NO_PROGRESS", "1")

    import dataclasses

    from recog.data import DataConfig
    from recog.evaluate import evaluate
    from recog.model import Recogniser
    from recog.objects import load_objects
    from recog.run import train_recogniser
    from recog.testset import TestsetConfig, make_testset
    from recog.train import TRAIN_PRESETS

    if args.set == "tless":
        shared = Path(os.environ.get("REALGAP_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
        files = [shared / "tless_cad" / f"obj_{i:02d}.ply" for i in range(1, 7)]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            print(f"T-LESS models not found ({missing[0]}); set REALGAP_SHARED_DATA or use --set chairs")
            return 1
        spec = [str(f) for f in files]
    else:
        spec = "chairs"
    out = Path(args.out)
    test = out / f"{args.set}_test"
    t0 = time.perf_counter()
    if not (test / "labels.json").is_file():
        make_testset(load_objects(spec), test, TestsetConfig(per_object=args.per_object), overwrite=True,
                     progress=False)
    print(f"test set {test}: {len(json.loads((test / 'labels.json').read_text()))} scans "
          f"(structure, physical) in {time.perf_counter() - t0:.0f} s")
    rows = []
    for net in args.networks.split(","):
        for variant in args.variants.split(","):
            folder = out / f"{args.set}_{variant}_{net}"
            train = dataclasses.replace(TRAIN_PRESETS["cpu"], network=net,
                                        **({"iterations": args.iterations} if args.iterations else {}))
            t1 = time.perf_counter()
            if (folder / "recogniser.json").is_file():
                model = Recogniser.load(folder)
            else:
                model = train_recogniser(spec, folder, DataConfig(variant=variant), train, workers=args.workers,
                                         progress=False).model
            t_train = time.perf_counter() - t1
            r = evaluate(model, test, folder / "eval", progress=False)
            b = r["before_icp"]
            rows.append({"variant": variant, "network": net, "accuracy": r["accuracy"],
                         "accuracy_descriptor": r["accuracy_descriptor"],
                         "rot_med_before": b["rot_err_deg"]["median"], "rot_med_after": r["rot_err_deg"]["median"],
                         "rot_acc20_before": b["rot_err_deg"]["acc_at_20"],
                         "rot_acc20_after": r["rot_err_deg"]["acc_at_20"],
                         "trans_med_after_mm": None if r["trans_err_m"]["median"] is None
                         else 1000 * r["trans_err_m"]["median"],
                         "train_s": model.info.get("timings_s", {}), "this_run_s": round(t_train, 1),
                         "per_object_accuracy": r["per_object_accuracy"]})
            print(_row(rows[-1]), flush=True)
    base = next((r for r in rows if r["variant"] == "clean"), None)
    print()
    print(f"{'variant':10s} {'net':7s} {'acc %':>6s} {'rot med before':>15s} {'rot med after':>14s} "
          f"{'<=20deg before':>15s} {'t med mm':>9s} {'vote acc %':>10s}  acc vs clean")
    for r in rows:
        ratio = f"{r['accuracy'] / base['accuracy']:.2f}x" if base and base["accuracy"] else "-"
        print(_row(r) + f"  {ratio}")
    (out / f"bench_recog_{args.set}.json").write_text(json.dumps(rows, indent=1))
    return 0


def _row(r: dict) -> str:
    f = lambda x, fmt: "-" if x is None else format(x, fmt)  # noqa: E731
    return (f"{r['variant']:10s} {r['network']:7s} {100 * r['accuracy']:6.1f} {f(r['rot_med_before'], '15.1f')} "
            f"{f(r['rot_med_after'], '14.1f')} {f(100 * r['rot_acc20_before'] if r['rot_acc20_before'] is not None else None, '14.0f')}% "
            f"{f(r['trans_med_after_mm'], '9.1f')} {100 * r['accuracy_descriptor']:10.1f}")


if __name__ == "__main__":
    sys.exit(main())
