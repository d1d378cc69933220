"""``realgap neural``: the neural allocentric spatial memory (thesis chapter 4): train, evaluate."""
from __future__ import annotations

import argparse
import json
import sys

from app.commands import RESUMES, add_group, add_shared

NAME = "neural"
HELP = "neural allocentric spatial memory (localise, memorise, recall, hallucinate): train and evaluate"


def _config_flags(p: argparse.ArgumentParser, cls, prefix: str = "", exclude: tuple = ()) -> None:
    """One flag per field of dataclass ``cls`` (``--NAME VALUE``; a nested dataclass field's fields as
    ``--NAME.FIELD``), its help the field's docstring and default - as ``slam run`` generates its flags - so a new
    training option is on the command line without being written here. Values land in ``args`` as ``cfg:NAME``."""
    import dataclasses
    import typing

    from data_tools.config import field_docs
    docs, hints, inst = field_docs(cls), typing.get_type_hints(cls), cls()
    for f in dataclasses.fields(cls):
        if f.name in exclude:
            continue
        if dataclasses.is_dataclass(hints[f.name]):
            _config_flags(p, hints[f.name], f"{prefix}{f.name}.")
            continue
        doc = " ".join(docs.get(f.name, "").split()).replace("%", "%%")
        names = [f"--{prefix}{f.name.replace('_', '-')}"] + ([f"--{prefix}{f.name}"] if "_" in f.name else [])
        p.add_argument(*names, dest=f"cfg:{prefix}{f.name}", default=argparse.SUPPRESS, metavar="VALUE",
                       help=f"{doc} (default: {getattr(inst, f.name)})".lstrip())


def _configured(cfg, args, where: str):
    """``cfg`` (a dataclass) with the generated flags given on the command line applied, validated."""
    from data_tools.config import config_replace
    over = {k[4:]: v for k, v in vars(args).items() if k.startswith("cfg:")}
    return config_replace(cfg, over, where).validate() if over else cfg.validate()


def register(parser: argparse.ArgumentParser) -> None:
    sub = add_group(parser)
    p = sub.add_parser("train", help="train the neural memory (2d: agents on images; 3d: RGB-D robot in rooms)",
                       description="Train encoder, localisation, LSTM memory, decoder and hallucination module "
                                   "(phases: pre-training, memory + recall, + hallucination GAN). Resumable.")
    p.add_argument("--mode", default="2d", choices=("2d", "3d"), help="2d: agents walking on images; 3d: a ground robot's simulated "
                        "kinect_v1 RGB-D sequences in procedural rooms")
    add_shared(p, "--out", "the model folder", required=True, metavar="MODEL")
    p.add_argument("--preset", default="cpu", choices=("cpu", "cpu-long", "gpu"),
                   help="cpu: <= 30 min on 2 cores; cpu-long: the shipped recipe (2d: front_2d, ~1 h 15 min on one "
                        "core; 3d: planar_3d, ~50 min on 2 cores + 18 min of refinement); gpu: larger")
    p.add_argument("--worlds", metavar="DIR", help="3d: folder of the simulated training/test rooms (made on "
                                                   "first use, reused after; default ~/.cache/realgap/neural_worlds)")
    add_shared(p, "--seed", "(default 0)", default=0)
    add_shared(p, "--overwrite", "a model already in MODEL")
    add_shared(p, "--no-progress")
    from slam.neural.train import NeuralTrainConfig
    _config_flags(p.add_argument_group("training options (override --preset; defaults: NeuralTrainConfig's)"),
                  NeuralTrainConfig, exclude=("mode", "seed", "worlds_dir"))
    p.set_defaults(func=_train, on_interrupt=RESUMES)
    p = sub.add_parser("train-topview", help="give a 3d model a trained top-view decoder (memory frozen)",
                       description="Train the per-cell read-out of a 3d model's memory into a colour floor plan "
                                   "(MODEL/topview.pt; 'neural train --mode 3d' makes one itself), the memory's "
                                   "weights untouched. slam run --backend neural then writes memory/topview.png.")
    p.add_argument("model", metavar="MODEL")
    p.add_argument("--steps", type=int, default=300, help="optimiser steps (default 300)")
    p.add_argument("--worlds", metavar="DIR", help="folder of the simulated training rooms (default: the model's)")
    add_shared(p, "--overwrite", "a top-view decoder already in MODEL")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_train_topview)
    p = sub.add_parser("refine-decoder", help="retrain a model's recall decoder with an SSIM term (memory frozen)",
                       description="Copy a model into OUT with its recall decoder refined (L1 + SSIM; 3d: on --rooms "
                                   "simulated rooms; 2d: on training walks). Encoder, localisation, LSTMs and "
                                   "hallucination module are unchanged, so localisation is identical. Resumable: "
                                   "re-run with the same --out.")
    p.add_argument("model", metavar="MODEL")
    add_shared(p, "--out", "the refined model's folder", required=True, metavar="OUT")
    from slam.neural.refine import RefineConfig
    _config_flags(p.add_argument_group("refinement options"), RefineConfig, exclude=("seed",))
    p.add_argument("--worlds", metavar="DIR", help="folder of the simulated training rooms (default: the model's)")
    add_shared(p, "--seed", "(default 0)", default=0)
    add_shared(p, "--overwrite", "a model already in OUT")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_refine, on_interrupt=RESUMES)
    p = sub.add_parser("refine-hallucination", help="train a model's occupancy mask and retrain its hallucination "
                                                    "module (memory frozen)",
                       description="Copy a model into OUT with its occupancy mask trained to the observed cells "
                                   "(L_occ) and its hallucination module retrained (L_hallu + L_corrupt + GAN) on "
                                   "its training data. Encoder, localisation, memory LSTM and recall decoder are "
                                   "unchanged, so localisation and recall are identical; a 3d model's top-view "
                                   "decoder, which reads the occupancy, is retrained. Resumable: re-run with the "
                                   "same --out.")
    p.add_argument("model", metavar="MODEL")
    add_shared(p, "--out", "the retrained model's folder", required=True, metavar="OUT")
    from slam.neural.refine_hallucination import HallucinationConfig
    _config_flags(p.add_argument_group("retraining options"), HallucinationConfig, exclude=("seed",))
    p.add_argument("--topview-steps", type=int, default=300,
                   help="3d: steps of the top-view decoder's retraining (default 300; 0 = none)")
    p.add_argument("--worlds", metavar="DIR", help="3d: folder of the simulated training rooms (default: the model's)")
    add_shared(p, "--seed", "(default 0)", default=0)
    add_shared(p, "--overwrite", "a model already in OUT")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_refine_hallucination, on_interrupt=RESUMES)
    p = sub.add_parser("eval", help="localisation, recall and hallucination metrics + baselines (JSON)")
    p.add_argument("model", metavar="MODEL")
    add_shared(p, "--out", "folder for neural_eval.json", metavar="DIR")
    p.add_argument("--mode", choices=("2d", "3d"), help="check that MODEL is of this mode (default: MODEL's)")
    p.add_argument("--sequences", type=int, default=None,
                   help="2d: test walks (default 64); 3d: 10-step image samples of the test rooms (default 24)")
    p.add_argument("--planar", action="append", default=[], metavar="SEQ",
                   help="3d: also localise on this planar sequence (neural vs icp), repeatable")
    add_shared(p, "--overwrite", "an existing neural_eval.json")
    add_shared(p, "--json", "(neural_eval.json's content)")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_eval)


def _train(args) -> int:
    import dataclasses

    from slam.neural.run import train_to_folder
    from slam.neural.train import TRAIN_PRESETS, TRAIN_PRESETS_3D
    over = {"worlds_dir": str(args.worlds)} if args.worlds else {}
    presets = TRAIN_PRESETS_3D if args.mode == "3d" else TRAIN_PRESETS
    cfg = _configured(dataclasses.replace(presets[args.preset], mode=args.mode, seed=args.seed, **over), args,
                      "neural train")
    from app.pipelines import simulate_planar_room
    _model, tlog, folder = train_to_folder(cfg, args.out, overwrite=args.overwrite, progress=not args.no_progress,
                                           log=lambda m: print(f"realgap: {m}", file=sys.stderr),
                                           simulate=simulate_planar_room)
    last = tlog.steps[-1] if tlog.steps else {}
    print(f"{folder}: neural memory trained ({cfg.iterations} steps, {tlog.seconds:.0f} s this run); last losses "
          + " ".join(f"{k} {v:.3f}" for k, v in last.items() if k != "step"))
    return 0


def _train_topview(args) -> int:
    from slam.neural.run import add_topview
    from app.pipelines import simulate_planar_room
    info = add_topview(args.model, args.steps, overwrite=args.overwrite, worlds=args.worlds,
                       progress=not args.no_progress, log=lambda m: print(f"realgap: {m}", file=sys.stderr),
                       simulate=simulate_planar_room)
    last = info["log"][-1]["topview_l1"] if info["log"] else float("nan")
    print(f"{args.model}/topview.pt: top-view decoder trained ({info['steps']} steps, {info['seconds']:.0f} s); "
          f"last L1 {last:.3f}")
    return 0


def _refine(args) -> int:
    from slam.neural.refine import RefineConfig
    from slam.neural.run import refine_folder
    from app.pipelines import simulate_planar_room
    rcfg = _configured(RefineConfig(seed=args.seed), args, "neural refine-decoder")
    info = refine_folder(args.model, args.out, rcfg, worlds=args.worlds, overwrite=args.overwrite,
                         progress=not args.no_progress, log=lambda m: print(f"realgap: {m}", file=sys.stderr),
                         simulate=simulate_planar_room)
    last = info["log"][-1] if info["log"] else {}
    print(f"{args.out}: recall decoder refined ({rcfg.steps} steps, {info['seconds']:.0f} s this run); last L1 "
          f"{last.get('l1', float('nan')):.3f}, SSIM loss {last.get('ssim_loss', float('nan')):.3f}")
    return 0


def _refine_hallucination(args) -> int:
    from slam.neural.refine_hallucination import HallucinationConfig
    from slam.neural.run import refine_hallucination_folder
    from app.pipelines import simulate_planar_room
    hcfg = _configured(HallucinationConfig(seed=args.seed), args, "neural refine-hallucination")
    info = refine_hallucination_folder(args.model, args.out, hcfg, topview_steps=args.topview_steps,
                                       worlds=args.worlds, overwrite=args.overwrite, progress=not args.no_progress,
                                       log=lambda m: print(f"realgap: {m}", file=sys.stderr),
                                       simulate=simulate_planar_room)
    occ = info["occ_log"][-1]["occ"] if info["occ_log"] else float("nan")
    last = info["log"][-1] if info["log"] else {}
    print(f"{args.out}: occupancy and hallucination retrained ({hcfg.occ_steps} + {hcfg.steps} steps, "
          f"{info['seconds']:.0f} s this run); last L_occ {occ:.4f}, L_hallu {last.get('hallu', float('nan')):.3f}, "
          f"L_corrupt {last.get('corrupt', float('nan')):.4f}")
    return 0


def _eval(args) -> int:
    from slam.neural.run import evaluate_folder
    from app.pipelines import simulate_planar_room
    r = evaluate_folder(args.model, args.out, args.sequences, overwrite=args.overwrite, progress=not args.no_progress,
                        mode=args.mode, extra_sequences=args.planar,
                        log=lambda m: print(f"realgap: {m}", file=sys.stderr), simulate=simulate_planar_room)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    if r["mode"] == "3d":
        loc, h, b = r["localisation"], r["hallucination"], r["baseline_tsdf_inpainting"]
        print(f"ATE RMSE neural {loc['neural']['ate_rmse_m_mean']:.3f} m vs icp {loc['icp']['ate_rmse_m_mean']:.3f} m "
              f"(cell {r['cell_m']:g} m; within 2 cells: {loc['within_2_cells_of_icp']}); anamnesis L1 "
              f"{r['anamnesis']['l1']:.3f} SSIM {r['anamnesis']['ssim_thesis']:.2f}; hallucination L1 {h['l1']:.3f} "
              f"SSIM {h['ssim_thesis']:.2f} (TSDF + inpainting: L1 {b['l1']:.3f} SSIM {b['ssim_thesis']:.2f}); "
              f"{args.out}/neural_eval.json")
        return 0
    a, h, m = r["anamnesis"], r["hallucination"], r["baseline_mosaic_inpainting"]
    print(f"APE median {r['ape_px']['median']:.2f} px (mean {r['ape_px']['mean']:.2f}); anamnesis L1 {a['l1']:.3f} "
          f"SSIM {a['ssim_thesis']:.2f}; hallucination L1 {h['l1']:.3f} SSIM {h['ssim_thesis']:.2f} (mosaic + "
          f"inpainting: L1 {m['l1']:.3f} SSIM {m['ssim_thesis']:.2f})" + (f"; {args.out}/neural_eval.json" if args.out else ""))
    return 0
