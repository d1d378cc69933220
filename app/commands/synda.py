"""``realgap synda``: SynDA (thesis ch. 5), a generator that maps real-like inputs into the clean
synthetic domain the recogniser was trained on.

* ``synda train --objects DIR|FILES|chairs --domain rgb|depth --out GEN`` (progress, checkpoints, resume)
* ``synda map GEN INPUT... --out DIR`` (every intermediate modality as a PNG + a contact sheet)
* ``synda augment --objects ... --out DIR`` (a contact sheet of A's samples)
* ``synda testset --objects ... --out TESTSET`` (colour test scans rendered unlike A, for ``recog eval --synda``)
* ``synda reindex MODEL --out MODEL2`` (the recogniser with an object-only database, what an rgb generator writes)
"""
from __future__ import annotations

import argparse
import sys

from app.commands import RESUMES, add_group, add_shared, positive_int
from app.commands.flags import add_config_flags, config_overrides
from data_tools.results import current_command
from recog.synda.config import SyndaTrainConfig

NAME = "synda"
HELP = "SynDA: map measured / real-like inputs into the clean synthetic domain (thesis ch. 5)"
DESCRIPTION = ("Train a multi-decoder U-Net with self-attentive distillation on augmented synthetic views of "
               "CAD objects, map inputs with it, look at the augmentation.")


FLAG_ALIASES = {"generator.target": ("--target",)}
"""``synda train`` flags kept under their short names: ``--target`` chooses the final output's modality."""


def add_synda_flags(p) -> None:
    """One generated flag per field of :class:`SyndaConfig` but ``domain`` (``--domain``) and ``train.seed``
    (``--seed``): the optimiser's as ``--NAME`` (``--iterations``, ``--lr``), the architecture's as
    ``--generator.NAME`` (the ablation switches: ``--no-generator.skips``), A's as ``--augment.NAME`` (a range as
    ``LO,HI``). Each overrides the ``--preset``; the help shows the cpu preset's rgb values."""
    from recog.synda.config import AugmentConfig, GeneratorConfig, synda_preset
    shown = synda_preset("cpu", "rgb")
    add_config_flags(p, SyndaTrainConfig, "train.", flag_prefix="", exclude=("seed",), defaults=shown.train)
    add_config_flags(p, GeneratorConfig, "generator.", aliases=FLAG_ALIASES, defaults=shown.generator)
    add_config_flags(p, AugmentConfig, "augment.", defaults=shown.augment)


def register(parser: argparse.ArgumentParser) -> None:
    sub = add_group(parser)
    p = sub.add_parser("train", help="simulate views of the objects and train the generator",
                       description="Render clean views of every object (and, for --domain depth, measure them with "
                                   "the sensor's physical pipeline under randomised parameters), then train h_G on "
                                   "the online augmentation A. Killed runs continue when re-run.")
    p.add_argument("--objects", required=True, help="a folder of .ply/.obj models, a comma list of files, or "
                                                    "'chairs' (the three embedded office chairs)")
    p.add_argument("--domain", required=True, choices=("rgb", "depth"),
                   help="input domain: rgb (colour renders, the thesis) or depth (measured depth patches)")
    add_shared(p, "--out", "the generator file", required=True, metavar="GEN")
    p.add_argument("--preset", default="cpu", choices=("cpu", "gpu"),
                   help="size: cpu = narrow U-Net, batch 16, 3000 steps; gpu = the thesis' size, batch 64, 20000 "
                        "steps; the configuration flags below override it")
    p.add_argument("--sensor", default="kinect_v1", help="sensor preset of the training views (default kinect_v1)")
    p.add_argument("--subdivisions", type=int, help="icosahedron subdivisions of the viewpoints (default 2)")
    p.add_argument("--draws", type=int, default=2, help="measured draws per view, depth domain (default 2)")
    p.add_argument("--scale", type=float, help="file units -> metres (default: guessed; 0.001 for millimetre CAD)")
    p.add_argument("--threads", type=positive_int("--threads"), default=1,
                   help="torch threads (default 1: measured fastest on a busy 2-core machine)")
    p.add_argument("--checkpoint-every", type=positive_int("--checkpoint-every"), default=100, metavar="N",
                   help="training checkpoint every N steps (default 100)")
    p.add_argument("--work", help="folder for the simulated views and the checkpoint (default GEN.work)")
    p.add_argument("--keep-work", action="store_true", help="keep the work folder at the end")
    p.add_argument("--init", metavar="GEN", help="start from this generator's weights (same architecture and domain; "
                                                 "fine-tuning) instead of random ones")
    add_synda_flags(p)
    add_shared(p, "--workers", "processes simulating views (default 2)", default=2)
    add_shared(p, "--seed", "of views, weights and augmentation (default 0)", default=0)
    add_shared(p, "--overwrite", "a generator already at GEN")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_train, on_interrupt=RESUMES)
    register_views(sub)


def _log(msg: str) -> None:
    print(f"realgap: {msg}", file=sys.stderr)


def synda_configs(args):
    """(SyndaConfig, DataConfig) of ``synda train`` arguments."""
    import dataclasses

    from recog.data import DataConfig
    from recog.synda.config import synda_preset
    from data_tools.config import config_replace
    cfg = synda_preset(args.preset, args.domain)
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, seed=args.seed))
    cfg = config_replace(cfg, config_overrides(args), "synda train").validate()
    vo = {"subdivisions": args.subdivisions} if args.subdivisions is not None else {}
    views = DataConfig(variant="physical", preset=args.sensor, seed=args.seed, draws=args.draws, **vo).validate()
    return cfg, views


def _train(args) -> int:
    from recog.synda.run import train_synda
    from recog.synda.train import pick_threads
    pick_threads(args.threads)
    cfg, views = synda_configs(args)
    command = current_command()
    gen, info = train_synda(args.objects, args.out, cfg, views, work=args.work, scale=args.scale,
                            workers=args.workers, overwrite=args.overwrite, keep_work=args.keep_work,
                            progress=not args.no_progress, command=command, checkpoint_every=args.checkpoint_every,
                            log=_log, init=args.init)
    fl = info["final_losses"]
    print(f"{gen}: SynDA {cfg.domain} generator of {', '.join(info['object_names'])}; {info['training_views']} views, "
          f"{cfg.train.iterations} steps ({info['timings_s']['train_s']:.0f} s, views "
          f"{info['timings_s']['views_s']:.0f} s); final losses " + " ".join(f"{k} {v:.4f}" for k, v in fl.items()
                                                                              if k != "step"))
    return 0


def register_views(sub) -> None:
    """``synda map`` and ``synda augment``."""
    p = sub.add_parser("map", help="map inputs through a generator: every intermediate modality as a PNG",
                       description="Run h_G on each input and write every decoded modality (normals, depth, mask, "
                                   "lightness) and the final output as a PNG with a colour bar, one folder per "
                                   "input, plus contact_sheet.png (a row per input). Inputs: .npy arrays of "
                                   "normalised patches ((S,S), (N,S,S) or (N,C,S,S) in [-1, 1]), S x S PNGs (8-bit "
                                   "grey or RGB: 0..255 -> -1..1), or a 16-bit depth scan with --bbox (the patch "
                                   "is cut as the recogniser cuts it).")
    p.add_argument("gen", metavar="GEN")
    p.add_argument("inputs", metavar="INPUT", nargs="+")
    add_shared(p, "--out", "folder for the PNGs", required=True, metavar="DIR")
    p.add_argument("--bbox", help="x0,y0,x1,y1: the window of a 16-bit depth scan (depth generators)")
    p.add_argument("--camera", help="camera.json of a depth scan (default: next to it or in its parent folder)")
    add_shared(p, "--overwrite", "a contact sheet already in DIR")
    p.set_defaults(func=_map)

    p = sub.add_parser("augment", help="a contact sheet of augmented training samples (what A does)",
                       description="Simulate a few views of the objects as 'synda train' does and draw A on them: "
                                   "contact_sheet.png shows per sample the clean view, (depth: the measured draw), "
                                   "the augmented input and the targets; samples.npz holds the arrays.")
    p.add_argument("--objects", required=True, help="as for synda train")
    p.add_argument("--domain", required=True, choices=("rgb", "depth"), help="input domain")
    add_shared(p, "--out", "folder for contact_sheet.png and samples.npz", required=True, metavar="DIR")
    p.add_argument("--samples", type=positive_int("--samples"), default=12, help="samples to show (default 12)")
    p.add_argument("--sensor", default="kinect_v1", help="sensor preset of the views (default kinect_v1)")
    p.add_argument("--scale", type=float, help="file units -> metres (default: guessed)")
    add_shared(p, "--seed", "of the views and of A (default 0)", default=0)
    add_shared(p, "--overwrite", "a contact sheet already in DIR")
    p.set_defaults(func=_augment)
    register_testset(sub)


def register_testset(sub) -> None:
    """``synda testset``: a colour test set rendered unlike A."""
    p = sub.add_parser("testset", help="render a colour test set unlike A (image textures, lights, photos, 3D occluders)",
                       description="Render labelled colour scans of the objects with VTK (PyVista, off screen): image "
                                   "textures on the mesh, Phong or physically based materials under 1-3 coloured "
                                   "lights, 3D occluders, photographs behind; plus the rendered depth. The folder is "
                                   "a recog test set with an rgb/ image per scan: 'realgap recog eval MODEL TESTSET "
                                   "--synda RGB_GEN' maps each colour patch to depth for the recogniser.")
    p.add_argument("--objects", required=True, help="as for synda train")
    add_shared(p, "--out", "the test set folder", required=True, metavar="TESTSET")
    p.add_argument("--per-object", type=positive_int("--per-object"), default=10, help="scans per object (default 10)")
    p.add_argument("--backgrounds", default="skimage",
                   help="folder of background photographs, searched recursively (default skimage: scikit-image's "
                        "samples, which A also uses; give another folder for backgrounds A never saw)")
    p.add_argument("--textures", default="skimage", help="folder of texture images (default skimage)")
    p.add_argument("--max-occluders", type=int, default=3, help="occluding solids per scan, 0..N (default 3)")
    p.add_argument("--scale", type=float, help="file units -> metres (default: guessed)")
    add_shared(p, "--seed", "(default 3000)", default=3000)
    add_shared(p, "--overwrite", "a test set already in TESTSET")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_testset)

    p = sub.add_parser("reindex", help="a recogniser with its database rebuilt from object-only clean views",
                       description="Keep a depth recogniser's network and rebuild its database from the clean "
                                   "renderer's views of its own view grid with every pixel outside the object at "
                                   "+1: what an rgb generator writes (it cannot know the ground and clutter behind "
                                   "a photographed object). Use the result with 'recog eval ... --synda RGB_GEN'.")
    p.add_argument("model", metavar="MODEL", help="a recogniser folder (realgap recog train)")
    add_shared(p, "--out", "the new recogniser folder", required=True, metavar="MODEL2")
    p.add_argument("--work", help="folder for the clean views (default MODEL2/views, removed at the end; a kept "
                                  "folder is reused)")
    add_shared(p, "--workers", "processes simulating views (default 1)", default=1)
    add_shared(p, "--overwrite", "a recogniser already in MODEL2")
    add_shared(p, "--no-progress")
    p.set_defaults(func=_reindex)


def _reindex(args) -> int:
    import shutil
    from pathlib import Path

    from data_tools.outputs import check_output_dir
    from recog.model import Recogniser
    from recog.synda.evaluate import object_only_database
    out = check_output_dir(args.out, finished="recogniser.json", overwrite=args.overwrite)
    model = Recogniser.load(args.model)
    work = Path(args.work) if args.work else out / "views"
    object_only_database(model, work, workers=args.workers, progress=not args.no_progress)
    model.info["reindexed"].update({"from": str(args.model),
                                    "command": current_command()})
    model.save(out)
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)
    print(f"{out}: {len(model.db)} object-only database entries, network of {args.model} "
          f"({model.info['reindexed']['seconds']:.0f} s)")
    return 0


def _map(args) -> int:
    from app.synda_figures import map_figures
    from data_tools.outputs import check_output_dir
    from recog.synda.inputs import read_inputs
    from recog.synda.io import load_generator
    out = check_output_dir(args.out, finished="contact_sheet.png", overwrite=args.overwrite)
    _, cfg, info = load_generator(args.gen)
    names, x = read_inputs(args.inputs, cfg, info, bbox=args.bbox, camera=args.camera, gen_path=args.gen)
    from recog.synda.run import modalities
    maps, meta = modalities(args.gen, x)
    n = map_figures(out, names, x, maps, meta)
    print(f"{out}: {len(names)} inputs mapped by the {cfg.domain} generator; {n} PNGs and contact_sheet.png")
    return 0


def _augment(args) -> int:
    from app.synda_figures import augment_sheet
    from data_tools.outputs import check_output_dir
    from recog.synda.inputs import augment_samples
    out = check_output_dir(args.out, finished="contact_sheet.png", overwrite=args.overwrite)
    samples = augment_samples(args.objects, args.domain, args.samples, args.seed, sensor=args.sensor,
                              scale=args.scale)
    augment_sheet(out, samples, args.domain)
    print(f"{out}: contact_sheet.png and samples.npz of {args.samples} {args.domain} samples of A")
    return 0


def _testset(args) -> int:
    from app.colour_render import PyVistaRenderer
    from recog.objects import load_objects
    from recog.synda.colour_testset import ColourTestsetConfig, image_files, make_colour_testset
    cfg = ColourTestsetConfig(per_object=args.per_object, backgrounds=args.backgrounds, textures=args.textures,
                              occluders=(0, args.max_occluders), seed=args.seed).validate()
    objs = load_objects(args.objects, args.scale)
    render = PyVistaRenderer(cfg, image_files(cfg.textures))
    command = current_command()
    n = make_colour_testset(objs, args.out, cfg, render, overwrite=args.overwrite, progress=not args.no_progress,
                            command=command)
    print(f"{args.out}: {n} colour scans (rgb/, depth/, labels.json) of {', '.join(o.name for o in objs)}")
    return 0
