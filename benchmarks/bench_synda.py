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
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ABLATIONS = {
    "full": {},
    "no_aux_decoders": {"decoders": ("TARGET",)},
    "no_distillation": {"distillation": False},
    "no_attention": {"attention": False},
    "no_skips": {"skips": False},
    "with_triplet": {"triplet": True},
}
"""Table 5.4's switches (GeneratorConfig overrides); ``TARGET`` stands for the generator's final output
(``no_aux_decoders`` keeps only its decoder)."""


def ablation_config(name: str, domain: str, target: str, iterations: int, seed: int):
    """The cpu preset of ``domain`` decoding ``target``, with variant ``name``'s switch (validated)."""
    from recog.synda.config import synda_preset
    cfg = synda_preset("cpu", domain)
    over = {k: tuple(target if m == "TARGET" else m for m in v) if k == "decoders" else v
            for k, v in ABLATIONS[name].items()}
    gen_cfg = dataclasses.replace(cfg.generator, target=target, **over)
    return dataclasses.replace(cfg, generator=gen_cfg, train=dataclasses.replace(
        cfg.train, iterations=iterations, seed=seed)).validate()


def _pairs(text: str) -> dict[str, str]:
    out = {}
    for item in text.split(","):
        name, _, path = item.partition("=")
        if not path:
            raise SystemExit(f"expected NAME=PATH, got {item!r}")
        out[name] = path
    return out


def evaluate_row(model_path: str, testset: str, generator: str | None, icp: bool, max_scans: int | None) -> dict:
    """Vote accuracy and rotation error before ICP (no-ICP run); with ``icp`` also the full pipeline."""
    from recog.evaluate import evaluate
    from recog.model import Recogniser
    model = Recogniser.load(model_path)
    reads = model.input
    if generator:      # main() has refused a SynDA row for a colour recogniser before any row
        from recog.synda.run import use_synda
        reads = f"synda-{use_synda(model, generator)['domain']}"
    t0 = time.perf_counter()
    r = evaluate(model, testset, None, icp=False, progress=False, max_scans=max_scans)
    row = {"reads": reads, "n_scans": r["n_scans"], "vote_accuracy": r["accuracy_descriptor"],
           "rot_err_deg_median_before_icp": r["before_icp"]["rot_err_deg"]["median"],
           "rot_within_20deg_before_icp": r["before_icp"]["rot_err_deg"].get("acc_at_20"),
           "seconds_no_icp": round(time.perf_counter() - t0, 1)}
    if icp:
        t0 = time.perf_counter()
        f = evaluate(model, testset, None, icp=True, progress=False, max_scans=max_scans)
        row.update(accuracy_full=f["accuracy"], vote_accuracy_full_run=f["accuracy_descriptor"],
                   rot_err_deg_median_after_icp=f["rot_err_deg"]["median"],
                   trans_err_mm_median_after_icp=None if f["trans_err_m"]["median"] is None
                   else 1000 * f["trans_err_m"]["median"], seconds_icp=round(time.perf_counter() - t0, 1))
    return row


def train_ablation(args, out: Path) -> dict:
    """Train the Table 5.4 generators of ``args.variants`` on the same views (``OUT/work/data``) into
    ``OUT/ablation_NAME.pt``; a file already there is kept. Returns {name: {"train_s": s} or {"error": line}}."""
    from data_tools.errors import RealgapError
    from recog.data import DataConfig
    from recog.synda.run import train_synda
    from recog.synda.train import pick_threads
    pick_threads(1)
    names = list(ABLATIONS) if args.variants is None else args.variants.split(",")
    unknown = [n for n in names if n not in ABLATIONS]
    if unknown:
        raise SystemExit(f"--variants: unknown {unknown[0]!r}; choose from {', '.join(ABLATIONS)}")
    res = {}
    for name in names:
        cfg = ablation_config(name, args.domain, args.target, args.iterations, args.seed)
        views = DataConfig(variant="physical", seed=args.seed, subdivisions=args.subdivisions)
        gen = out / f"ablation_{name}.pt"
        t0 = time.perf_counter()
        if not gen.is_file():
            print(f"ablation {name}: training {args.iterations} steps", flush=True)
            try:
                train_synda(args.objects, gen, cfg, views, work=out / "work", keep_work=True,
                            progress=True, command="bench_synda --ablation " + name)
            except RealgapError as e:
                res[name] = {"error": str(e)}
                continue
            finally:     # the views are shared, the checkpoint is this variant's (the next would resume it)
                (out / "work" / "checkpoint.pt").unlink(missing_ok=True)
        res[name] = {"train_s": round(time.perf_counter() - t0, 1)}
    return res


def evaluate_ablation(trained: dict, first_model: str, testsets: dict[str, str], out: Path,
                      max_scans: int | None) -> dict:
    """Each trained variant's generator in front of ``first_model`` on every test set (vote, before ICP)."""
    res = {}
    for name, r in trained.items():
        res[name] = dict(r)
        if "error" not in r:
            res[name].update({ts: evaluate_row(first_model, path, str(out / f"ablation_{name}.pt"), False, max_scans)
                              for ts, path in testsets.items()})
        print(name, json.dumps(res[name]), flush=True)
    return res


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
    rows = []
    trained = train_ablation(args, out) if args.ablation else None     # first: the recognisers are read after
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
                       **evaluate_row(model, path, gen, args.icp, args.max_scans)}
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
