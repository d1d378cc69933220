"""Benchmark: SynDA in front of the triplet recogniser (thesis Tables 5.2-5.4; depth generators on depth scans,
rgb generators on the colour scans of ``synda testset``), on the same test scans for every row.

    .venv/bin/python benchmarks/bench_synda.py --recog clean=CLEAN_MODEL,physical=recog/weights/chairs \\
        --generator recog/weights/synda_depth/generator.pt \\
        --testset structure=TESTSET_A,changed=TESTSET_B [--icp] [--max-scans N] [--out bench_out/synda]
    .venv/bin/python benchmarks/bench_synda.py ... --ablation --objects chairs --iterations 300

Thesis Tables 5.2/5.3's three rows: ``--recog clean=CLEAN,atrained=ATRAINED --synda-recog clean`` (a recogniser
trained on clean synthetic views, one trained on A(synthetic) - ``recog train --synda-augment`` in depth,
``--input rgb`` in colour -, and SynDA + the clean one).

Rows per test set: each recogniser alone, and each recogniser reading the generator's mapping of the
measured patch (``recog eval --synda``). Columns: the descriptor's own k-NN vote accuracy and the
symmetry-aware rotation error of its nearest database pose (median, before ICP, on the scans the
vote gets right: the ``--no-icp`` evaluation); with ``--icp`` also the full pipeline (CAD
verification + ICP) accuracy and rotation error after ICP.

Colour domain: ``--generator`` an rgb generator with depth output (``synda train --domain rgb --target depth``)
and ``--testset colour=TS`` a colour test set (``realgap synda testset``); the rows of a depth recogniser without
the generator are then the recogniser reading the colour test set's rendered depth (a reference, not a colour
baseline); a colour recogniser (``recog train --input rgb``: the A-trained colour baseline) reads the colour
patches themselves. Table 5.2 for colour: ``--recog atrained=ATRAINED_RGB,clean=CLEAN --synda-recog clean``. The
``reads`` column says what each row's descriptor read: ``depth``, ``rgb`` or ``synda-rgb`` / ``synda-depth``.

Test sets (``realgap recog testset``) should come from a sensor the recogniser and the generator did
not see: the ``structure`` preset's physical pipeline, and the training sensor with effect parameters
outside the training randomisation (``recog testset --sensor kinect_v1 --effect-override EFFECT.PARAM=VALUE``
or ``--effect-preset beyond_training``).

``--ablation``: thesis Table 5.4 - cpu-preset generators of ``--domain`` (depth or rgb, final output ``--target``,
default depth) without the decoders other than the target, without
distillation, without self-attention, without skip connections, and with the bottleneck triplet
loss, each trained ``--iterations`` steps on the same views (``--objects``, kept in ``OUT/work/data``; a
generator file already in OUT is kept, so a killed run continues with the next variant), all trained before any
recogniser is read, then the first recogniser's vote accuracy / rotation error before ICP with each. Writes
``OUT/bench_synda.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _pairs(text: str) -> dict[str, str]:
    out = {}
    for item in text.split(","):
        name, _, path = item.partition("=")
        if not path:
            raise SystemExit(f"expected NAME=PATH, got {item!r}")
        out[name] = path
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--recog", required=True, help="NAME=MODEL,... recognisers (the first one is the ablation's)")
    ap.add_argument("--generator", default=None, help="the SynDA generator of the rows with SynDA (required "
                    "unless --ablation, whose rows are then the recognisers alone)")
    ap.add_argument("--testset", required=True, help="NAME=TESTSET,...")
    ap.add_argument("--icp", action="store_true", help="also the full pipeline (verification + ICP): slow")
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--synda-recog", default=None, help="NAME,... the recognisers that also get a row with the "
                    "generator in front (default: all)")
    ap.add_argument("--ablation", action="store_true", help="thesis Table 5.4 (trains 6 generators)")
    ap.add_argument("--objects", default="chairs", help="objects of the ablation's generators")
    ap.add_argument("--iterations", type=int, default=300, help="steps of each ablation generator")
    ap.add_argument("--variants", default=None, help="NAME,... the ablation variants to run (default all; two runs "
                    "with disjoint variants and their own --out can share the machine)")
    ap.add_argument("--subdivisions", type=int, default=1, help="viewpoint subdivisions of the ablation's views")
    ap.add_argument("--domain", default="depth", choices=("depth", "rgb"), help="input domain of the ablation's "
                    "generators (rgb: evaluate them on a colour test set, `synda testset`)")
    ap.add_argument("--target", default="depth", help="final output of the ablation's generators (depth: what "
                    "the recogniser reads)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench_out/synda")
    args = ap.parse_args(argv)
    import torch
    torch.set_num_threads(1)
    recogs, testsets = _pairs(args.recog), _pairs(args.testset)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from data_tools.errors import RealgapError
    from recog.synda.evaluate import evaluate_ablation, table_row, train_ablation
    from recog.synda.train import pick_threads
    rows = []
    trained = None
    if args.ablation:                # first: the recognisers are read after
        pick_threads(1)
        try:
            trained = train_ablation(args.objects, out, None if args.variants is None else args.variants.split(","),
                                     domain=args.domain, target=args.target, iterations=args.iterations,
                                     seed=args.seed, subdivisions=args.subdivisions)
        except RealgapError as e:         # an unknown --variants name or a bad --domain / --target: before any work
            raise SystemExit(f"bench_synda --ablation: {e}") from None
    with_synda = set(recogs) if args.synda_recog is None else set(filter(None, args.synda_recog.split(",")))
    if args.generator is None:
        if not args.ablation:
            raise SystemExit("--generator: needed unless --ablation")
        with_synda = set()
    if not with_synda <= set(recogs):
        raise SystemExit(f"--synda-recog: no recogniser named {sorted(with_synda - set(recogs))[0]!r}")
    from recog.model import Recogniser
    colour = [n for n in sorted(with_synda) if Recogniser.load(recogs[n]).input == "rgb"]
    if colour:     # before any row is computed
        raise SystemExit(f"--synda-recog: {colour[0]} reads colour (recog train --input rgb); a generator maps to "
                         f"depth, so give only depth recognisers a SynDA row")
    for ts, path in testsets.items():
        for name, model in recogs.items():
            for gen in ((None, args.generator) if name in with_synda else (None,)):
                row = {"testset": ts, "recogniser": name, "synda": bool(gen),
                       **table_row(model, path, gen, args.icp, args.max_scans)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    result = {"rows": rows, "generator": args.generator, "recognisers": recogs, "testsets": testsets}
    if args.ablation:
        result["ablation"] = evaluate_ablation(trained, next(iter(recogs.values())), testsets, out, args.max_scans)
    (out / "bench_synda.json").write_text(json.dumps(result, indent=2))
    print(f"{'test set':10s} {'recogniser':12s} {'reads':11s} {'vote %':>7s} {'rot med before':>14s}"
          + (f" {'full %':>7s} {'rot med after':>13s}" if args.icp else ""))
    for r in rows:
        line = (f"{r['testset']:10s} {r['recogniser']:12s} {r['reads']:11s} {100 * r['vote_accuracy']:7.1f} "
                f"{r['rot_err_deg_median_before_icp'] or float('nan'):14.1f}")
        if args.icp:
            line += f" {100 * r['accuracy_full']:7.1f} {r['rot_err_deg_median_after_icp'] or float('nan'):13.1f}"
        print(line)
    if args.ablation:
        print(f"\nTable 5.4 (generators in front of {next(iter(recogs))}): vote % / rot. median before ICP (deg)")
        print(f"{'variant':16s}" + "".join(f" {ts:>18s}" for ts in testsets) + f" {'all scans vote %':>17s}")
        for name, r in result["ablation"].items():
            if "error" in r:
                print(f"{name:16s} {r['error']}")
                continue
            cells = [r[ts] for ts in testsets]
            pooled = sum(c["vote_accuracy"] * c["n_scans"] for c in cells) / max(1, sum(c["n_scans"] for c in cells))
            print(f"{name:16s}" + "".join(f" {100 * c['vote_accuracy']:10.1f} / "
                                          f"{c['rot_err_deg_median_before_icp'] or float('nan'):5.1f}" for c in cells)
                  + f" {100 * pooled:17.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
