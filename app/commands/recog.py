"""``realgap recog``: CAD-based recognition trained only on simulated depth (thesis 3.2.1 / 3.4.3).

* ``recog train --objects DIR|FILES|chairs --variant physical|gaussian|clean --out MODEL``
* ``recog eval MODEL TESTSET --out DIR [--synda GEN]`` (eval.json, predictions.jsonl, CDF figures); ``--json`` prints
  eval.json's content
* ``recog predict MODEL DEPTH.png --bbox x0,y0,x1,y1``
* ``recog testset --objects ... --out TESTSET`` (scans with another sensor, labels.json)
"""
from __future__ import annotations

import argparse
import json
import sys

from app.commands import RESUMES, add_group, add_shared, positive_float, positive_int, ranged
from data_tools.errors import ConfigError

NAME = "recog"
HELP = "object class + 6-DoF pose recognition trained on simulated depth scans (triplet CNN)"
DESCRIPTION = ("Train a triplet-CNN recogniser of CAD models on simulated depth views (no real image), "
               "evaluate it on test scans, recognise one window.")


def register(parser: argparse.ArgumentParser) -> None:
    sub = add_group(parser)
    p = sub.add_parser("train", help="simulate views of the objects and train the recogniser",
                       description="Simulate object-centred views of every object with the --variant sensor model, "
                                   "train the descriptor network (triplet + pair loss, dynamic margin) and index "
                                   "every view. Killed runs continue when re-run.")
    p.add_argument("--objects", required=True, help="a folder of .ply/.obj models, a comma list of files, or "
                                                    "'chairs' (the three embedded office chairs)")
    p.add_argument("--variant", default="physical", choices=("clean", "gaussian", "physical"),
                   help="training data: ideal depth, ideal + Nguyen axial noise, or the full physical pipeline "
                        "with randomised parameters (default physical)")
    add_shared(p, "--out", "the recogniser folder", required=True, metavar="MODEL")
    p.add_argument("--preset", default="cpu", choices=("cpu", "gpu"),
                   help="training size: cpu = LeNet, 3000 steps (minutes on 2 cores); gpu = deeper net, 20000 steps")
    p.add_argument("--sensor", default="kinect_v1", help="sensor preset of the training views (default kinect_v1)")
    p.add_argument("--subdivisions", type=ranged("--subdivisions", int, 0, 5),
                   help="icosahedron subdivisions of the viewpoints, 0..5 (default 2)")
    p.add_argument("--scale", type=positive_float("--scale"),
                   help="file units -> metres (default: guessed; 0.001 for millimetre CAD)")
    from app.commands.flags import add_config_flags
    from recog.train import TrainConfig
    add_config_flags(p.add_argument_group("training options (override --preset; defaults: the cpu preset's)"),
                     TrainConfig, exclude=("seed",))
    p.add_argument("--symmetry", action="append", metavar="NAME=AXIS:ORDER",
                   help="declare an object's symmetry instead of detecting it (e.g. obj_05=z:2, obj_01=z:inf)")
    p.add_argument("--drop-data", action="store_true", help="delete the simulated training patches at the end")
    add_shared(p, "--workers", "processes simulating views (default 2)", default=2)
    add_shared(p, "--seed", "of views and training (default 0)", default=0)
    add_shared(p, "--overwrite", "a recogniser already in MODEL")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_train, on_interrupt=RESUMES)

    p = sub.add_parser("eval", help="accuracy and pose errors on a test set (eval.json + CDF figures)")
    p.add_argument("model", metavar="MODEL")
    p.add_argument("testset", metavar="TESTSET", help="folder with camera.json, depth/ and labels.json")
    add_shared(p, "--out", "folder for eval.json, predictions.jsonl and figures/", metavar="DIR")
    p.add_argument("--no-icp", action="store_true", help="report the database poses only")
    p.add_argument("--synda", metavar="GEN", help="a SynDA generator whose output is depth (realgap synda train): the "
                                                 "recogniser reads its mapping of each measured patch (--domain depth) "
                                                 "or of each colour image (--domain rgb --target depth, on a colour "
                                                 "test set made by 'realgap synda testset')")
    p.add_argument("--k", type=ranged("--k", int, 1), default=5, help="neighbours voting for the object (default 5)")
    add_shared(p, "--max-frames", "evaluate the first N scans")
    add_shared(p, "--overwrite", "an eval.json already in DIR")
    add_shared(p, "--json", "eval.json's content (to write it to a file, give --out DIR: DIR/eval.json)")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_eval)

    p = sub.add_parser("predict", help="recognise the object in one window of a depth image")
    p.add_argument("model", metavar="MODEL")
    p.add_argument("depth", metavar="DEPTH.png")
    p.add_argument("--bbox", required=True, help="the window x0,y0,x1,y1 in pixels")
    p.add_argument("--camera", help="camera.json (default: next to the image or in its parent folder)")
    p.add_argument("--no-icp", action="store_true", help="skip the ICP refinement")
    add_shared(p, "--json")
    p.set_defaults(func=_predict)

    p = sub.add_parser("testset", help="simulate labelled test scans with another sensor")
    p.add_argument("--objects", required=True, help="as for recog train")
    add_shared(p, "--out", "the test set folder", required=True, metavar="TESTSET")
    p.add_argument("--sensor", default="structure", help="sensor preset (default structure: not a training sensor)")
    p.add_argument("--effects", default="physical", help="physical, direct or a comma list (default physical)")
    p.add_argument("--effect-override", action="append", default=[], metavar="EFFECT.PARAM=VALUE",
                   help="set an effect parameter of the sensor model (repeatable or a comma list), e.g. "
                        "ir_capture.read_noise_e=20: scans with effects never seen in training")
    p.add_argument("--effect-preset", default="", metavar="NAME",
                   help="a named set of effect overrides: beyond_training = every parameter of the physical "
                        "training randomisation half its range's width above the upper end (--effect-override wins)")
    p.add_argument("--per-object", type=int, default=40, help="scans per object (default 40)")
    p.add_argument("--scale", type=positive_float("--scale"), help="file units -> metres (default: guessed)")
    add_shared(p, "--seed", "(default 1000)", default=1000)
    add_shared(p, "--overwrite", "a test set already in TESTSET")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_testset)


def _log(msg: str) -> None:
    print(f"realgap: {msg}", file=sys.stderr)


def _train(args) -> int:
    from recog.run import parse_symmetries, train_recogniser
    data, train = train_configs(args)
    o = train_recogniser(args.objects, args.out, data, train, scale=args.scale, symmetries=parse_symmetries(
        args.symmetry), workers=args.workers, overwrite=args.overwrite, keep_data=not args.drop_data,
        progress=not args.no_progress, log=_log)
    info = o.model.info
    print(f"{o.folder}: recogniser of {len(o.model.names)} objects ({', '.join(o.model.names)}), "
          f"{info['database_entries']} database entries; training views {o.seconds['views_s']:.0f} s "
          f"({o.chunks_made} chunks simulated, {o.chunks_kept} kept), network {o.seconds['train_s']:.0f} s; "
          f"noise self-check: nearest view of a second draw is the same object in "
          f"{100 * o.self_check['same_object']:.1f} %")
    return 0


def train_configs(args):
    """(DataConfig, TrainConfig) of ``recog train`` arguments."""
    import dataclasses

    from app.commands.flags import config_overrides
    from data_tools.config import config_replace
    from recog.data import DataConfig
    from recog.train import TRAIN_PRESETS
    train = config_replace(dataclasses.replace(TRAIN_PRESETS[args.preset], seed=args.seed), config_overrides(args),
                           "recog train")
    over = {"subdivisions": args.subdivisions} if args.subdivisions is not None else {}
    return DataConfig(variant=args.variant, preset=args.sensor, seed=args.seed, **over).validate(), train.validate()


def _eval(args) -> int:
    from data_tools.outputs import check_output_dir
    from recog.evaluate import evaluate
    from recog.model import Recogniser
    out = check_output_dir(args.out, finished="eval.json", overwrite=args.overwrite) if args.out else None
    model = Recogniser.load(args.model)
    if args.synda:
        from recog.synda.run import use_synda
        use_synda(model, args.synda)
    r = evaluate(model, args.testset, out, icp=not args.no_icp, k=args.k,
                 progress=not args.no_progress, max_scans=args.max_frames)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    b = r["before_icp"]

    def num(v, scale=1.0):      # a median of no correctly recognised scan is None
        return "n/a" if v is None else f"{scale * v:.1f}"
    print(f"accuracy {100 * r['accuracy']:.1f} % on {r['n_scans']} scans; rotation error (symmetry-aware) median "
          f"{num(b['rot_err_deg']['median'])} deg before ICP, {num(r['rot_err_deg']['median'])} deg after; "
          f"translation median {num(r['trans_err_m']['median'], 1000)} mm" + (f"; {out}/eval.json" if out else ""))
    return 0


def _predict(args) -> int:
    from recog.run import predict_file
    pred = predict_file(args.model, args.depth, args.bbox, args.camera, icp=not args.no_icp)
    if args.json:
        print(json.dumps(pred.to_json(), indent=2))
        return 0
    t = pred.pose[:3, 3]
    print(f"{pred.object} (descriptor distance {pred.distance:.3f}); pose object-to-camera: t = "
          f"[{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m, R = {pred.pose[:3, :3].round(4).tolist()}")
    return 0


def _testset(args) -> int:
    from recog.objects import load_objects
    from recog.testset import TestsetConfig, make_testset, parse_effect_overrides
    if args.per_object < 1:
        raise ConfigError(f"--per-object must be >= 1, got {args.per_object}")
    cfg = TestsetConfig(sensor=args.sensor, effects=args.effects, per_object=args.per_object, seed=args.seed,
                        effect_preset=args.effect_preset, effect_overrides=parse_effect_overrides(args.effect_override))
    n = make_testset(load_objects(args.objects, args.scale), args.out, cfg, overwrite=args.overwrite,
                     progress=not args.no_progress)
    print(f"{args.out}: {n} scans by {args.sensor} ({args.effects}); labels in {args.out}/labels.json")
    return 0
