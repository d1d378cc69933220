"""``realgap neural``: the neural allocentric spatial memory (thesis chapter 4): train, evaluate."""
from __future__ import annotations

import argparse
import json
import sys

from app.commands import RESUMES, add_group, add_shared

NAME = "neural"
HELP = "neural allocentric spatial memory (localise, memorise, recall, hallucinate): train and evaluate"


def _configured(cfg, args, where: str):
    """``cfg`` (a dataclass) with the generated flags given on the command line applied, validated."""
    from app.commands.flags import config_overrides
    from data_tools.config import config_replace
    over = config_overrides(args)
    return config_replace(cfg, over, where).validate() if over else cfg.validate()


TRAIN_FLAG_ALIASES = {"model.features": ("--features",), "model.width": ("--width",),
                      "refine.steps": ("--refine-steps", "--refine_steps"),
                      "refine.rooms": ("--refine-rooms", "--refine_rooms"),
                      "refine.pool_batches": ("--refine-pool-batches", "--refine_pool_batches")}
"""``neural train`` flags of fields that moved into the nested configurations, kept under their names."""
TRAIN_FLAG_EXCLUDED = ("mode", "worlds_dir", "refine.seed", "model.occupancy")
"""``neural train`` fields without a generated flag (besides the model's sizes the data gives,
:data:`slam.neural.config.DERIVED_MODEL_FIELDS`): ``--mode`` and ``--worlds`` are written out (they choose the
preset and name an input folder), the refinement runs with the training's seed, the occupancy mask follows
``--occ-weight`` (:func:`slam.neural.config.derived_model`)."""


def register(parser: argparse.ArgumentParser) -> None:
    sub = add_group(parser)
    p = sub.add_parser("train", help="train the neural memory (2d: agents on images; 3d: RGB-D robot in rooms)",
                       description="Train encoder, localisation, LSTM memory, decoder and hallucination module "
                                   "(phases: pre-training, memory + recall, + hallucination GAN). Resumable.")
    from app.commands.flags import add_config_flags
    from slam.neural.config import (DERIVED_MODEL_FIELDS, PRESETS, HallucinationConfig, NeuralTrainConfig,
                                    RefineConfig, TopviewConfig)
    p.add_argument("--mode", default="2d", choices=tuple(PRESETS),
                   help="2d: agents walking on images; 3d: a ground robot's simulated kinect_v1 RGB-D sequences in "
                        "procedural rooms")
    add_shared(p, "--out", "the model folder", required=True, metavar="MODEL")
    p.add_argument("--preset", default="cpu", choices=tuple(PRESETS["2d"]),
                   help="cpu: <= 30 min on 2 cores; cpu-long: the shipped recipe (2d: front_2d, ~1 h 15 min on one "
                        "core; 3d: planar_3d, ~50 min on 2 cores + 18 min of refinement); gpu: larger")
    p.add_argument("--worlds", metavar="DIR", help="3d: folder of the simulated training/test rooms (made on "
                                                   "first use, reused after; default ~/.cache/realgap/neural_worlds)")
    add_shared(p, "--overwrite", "a model already in MODEL")
    add_shared(p, "--no-progress")
    add_config_flags(p.add_argument_group("training options (override --preset; defaults: NeuralTrainConfig's)"),
                     NeuralTrainConfig, aliases=TRAIN_FLAG_ALIASES,
                     exclude=(*TRAIN_FLAG_EXCLUDED, *(f"model.{k}" for k in DERIVED_MODEL_FIELDS)))
    p.set_defaults(func=_train, on_interrupt=RESUMES)
    p = sub.add_parser("train-topview", help="give a 3d model a trained top-view decoder (memory frozen)",
                       description="Train the per-cell read-out of a 3d model's memory into a colour floor plan "
                                   "(MODEL/topview.pt; 'neural train --mode 3d' makes one itself), the memory's "
                                   "weights untouched. slam run --backend neural then writes memory/topview.png.")
    p.add_argument("model", metavar="MODEL")
    add_config_flags(p.add_argument_group("top-view decoder options"), TopviewConfig)
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
    add_config_flags(p.add_argument_group("refinement options"), RefineConfig)
    p.add_argument("--worlds", metavar="DIR", help="folder of the simulated training rooms (default: the model's)")
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
    add_config_flags(p.add_argument_group("retraining options"), HallucinationConfig)
    p.add_argument("--worlds", metavar="DIR", help="3d: folder of the simulated training rooms (default: the model's)")
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

    from slam.neural.config import PRESETS
    from slam.neural.run import train_to_folder
    over = {"worlds_dir": str(args.worlds)} if args.worlds else {}
    cfg = _configured(dataclasses.replace(PRESETS[args.mode][args.preset], mode=args.mode, **over), args,
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
    from slam.neural.config import TopviewConfig
    from slam.neural.run import add_topview
    from app.pipelines import simulate_planar_room
    info = add_topview(args.model, _configured(TopviewConfig(), args, "neural train-topview"), overwrite=args.overwrite, worlds=args.worlds,
                       progress=not args.no_progress, log=lambda m: print(f"realgap: {m}", file=sys.stderr),
                       simulate=simulate_planar_room)
    last = info["log"][-1]["topview_l1"] if info["log"] else float("nan")
    print(f"{args.model}/topview.pt: top-view decoder trained ({info['steps']} steps, {info['seconds']:.0f} s); "
          f"last L1 {last:.3f}")
    return 0


def _refine(args) -> int:
    from slam.neural.config import RefineConfig
    from slam.neural.run import refine_folder
    from app.pipelines import simulate_planar_room
    rcfg = _configured(RefineConfig(), args, "neural refine-decoder")
    info = refine_folder(args.model, args.out, rcfg, worlds=args.worlds, overwrite=args.overwrite,
                         progress=not args.no_progress, log=lambda m: print(f"realgap: {m}", file=sys.stderr),
                         simulate=simulate_planar_room)
    last = info["log"][-1] if info["log"] else {}
    print(f"{args.out}: recall decoder refined ({rcfg.steps} steps, {info['seconds']:.0f} s this run); last L1 "
          f"{last.get('l1', float('nan')):.3f}, SSIM loss {last.get('ssim_loss', float('nan')):.3f}")
    return 0


def _refine_hallucination(args) -> int:
    from slam.neural.config import HallucinationConfig
    from slam.neural.run import refine_hallucination_folder
    from app.pipelines import simulate_planar_room
    hcfg = _configured(HallucinationConfig(), args, "neural refine-hallucination")
    info = refine_hallucination_folder(args.model, args.out, hcfg, worlds=args.worlds, overwrite=args.overwrite, progress=not args.no_progress,
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
