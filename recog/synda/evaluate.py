"""SynDA's evaluation (thesis Tables 5.2-5.4): a recogniser alone or reading h_G's output on the same test
scans, the architecture ablation's generators, and a recogniser re-indexed on object-only views.

* :func:`table_row` - one row of Tables 5.2/5.3: the descriptor's own k-NN vote accuracy and the symmetry-aware
  rotation error of its nearest database pose before ICP (median over the scans the vote gets right), and
  optionally the full pipeline's (CAD verification + ICP on the measured depth) accuracy and errors after ICP.
* :data:`ABLATIONS`, :func:`ablation_config`, :func:`train_ablation`, :func:`evaluate_ablation` - Table 5.4:
  the cpu preset with one architecture switch changed per variant, every variant trained on the same views with
  the same seed and steps, then read by one recogniser.
* :func:`object_only_database` - keeps a recogniser's network and rebuilds its database from clean views with
  every pixel outside the object at +1, which is what an rgb generator writes (it cannot know the ground and
  clutter behind a photographed object; the thesis' recogniser is trained on renders of the object alone).

``benchmarks/bench_synda.py`` runs these and prints the tables; ``realgap synda reindex`` makes the
object-only recogniser.
"""
from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np

from data_tools.errors import FormatError, RealgapError
from recog.synda.config import SyndaConfig, synda_preset

ABLATIONS = {
    "full": {},
    "no_aux_decoders": {"decoders": ("TARGET",)},
    "no_distillation": {"distillation": False},
    "no_attention": {"attention": False},
    "no_skips": {"skips": False},
    "with_triplet": {"triplet": True},
}
"""Table 5.4's switches (:class:`~recog.synda.config.GeneratorConfig` overrides); ``TARGET`` stands for the
generator's final output (``no_aux_decoders`` keeps only its decoder)."""


def table_row(model_path: str | os.PathLike, testset: str | os.PathLike, generator: str | os.PathLike | None,
              icp: bool = False, max_scans: int | None = None) -> dict:
    """One recogniser on one test set, reading the measured patch (``generator`` None) or h_G's mapping of it.

    Keys: ``reads`` (depth, rgb, synda-depth, synda-rgb), ``n_scans``, ``vote_accuracy`` (0-1),
    ``rot_err_deg_median_before_icp``, ``rot_within_20deg_before_icp`` (0-1), ``seconds_no_icp``; with ``icp``
    also ``accuracy_full``, ``rot_err_deg_median_after_icp``, ``trans_err_mm_median_after_icp``, ``seconds_icp``.
    """
    from recog.evaluate import evaluate
    from recog.model import Recogniser
    model = Recogniser.load(model_path)
    reads = model.input
    if generator:
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


def ablation_config(name: str, domain: str, target: str, iterations: int, seed: int) -> SyndaConfig:
    """The cpu preset of ``domain`` decoding ``target``, with variant ``name``'s switch (validated)."""
    if name not in ABLATIONS:
        raise RealgapError(f"unknown ablation variant {name!r}; choose from {', '.join(ABLATIONS)}")
    cfg = synda_preset("cpu", domain)
    over = {k: tuple(target if m == "TARGET" else m for m in v) if k == "decoders" else v
            for k, v in ABLATIONS[name].items()}
    gen_cfg = dataclasses.replace(cfg.generator, target=target, **over)
    return dataclasses.replace(cfg, generator=gen_cfg, train=dataclasses.replace(
        cfg.train, iterations=iterations, seed=seed)).validate()


def train_ablation(objects_spec, out: str | os.PathLike, variants: list[str] | None = None, *, domain: str = "depth",
                   target: str = "depth", iterations: int = 3000, seed: int = 0, subdivisions: int = 1,
                   progress: bool = True, log=print) -> dict:
    """Train the Table 5.4 generators ``variants`` (default all) on the same views (``OUT/work/data``, simulated
    once) into ``OUT/ablation_NAME.pt``. A file already there is kept, so a killed run continues with the
    variant it was on (its checkpoint) and then the next. Returns {name: {"train_s": s} or {"error": line}}."""
    from recog.data import DataConfig
    from recog.synda.run import train_synda
    names = list(ABLATIONS) if variants is None else list(variants)
    cfgs = {n: ablation_config(n, domain, target, iterations, seed) for n in names}     # every name checked first
    out = Path(out)
    views = DataConfig(variant="physical", seed=seed, subdivisions=subdivisions)
    res = {}
    for name, cfg in cfgs.items():
        gen = ablation_file(out, name)
        t0 = time.perf_counter()
        if not gen.is_file():
            log(f"ablation {name}: training {iterations} steps")
            try:
                train_synda(objects_spec, gen, cfg, views, work=out / "work", keep_work=True, progress=progress,
                            command=f"ablation {name} ({domain}, target {target}, {iterations} steps, seed {seed})")
            except RealgapError as e:
                res[name] = {"error": str(e)}
            # the variant ended (trained or failed): the views are shared, the checkpoint is this variant's and
            # the next one would resume it; an interrupted variant keeps it, to continue
            (out / "work" / "checkpoint.pt").unlink(missing_ok=True)
            if name in res:
                continue
        res[name] = {"train_s": round(time.perf_counter() - t0, 1)}
    return res


def ablation_file(out: str | os.PathLike, name: str) -> Path:
    """Where :func:`train_ablation` writes variant ``name``'s generator."""
    return Path(out) / f"ablation_{name}.pt"


def evaluate_ablation(trained: dict, model_path: str | os.PathLike, testsets: dict[str, str],
                      out: str | os.PathLike, max_scans: int | None = None, log=print) -> dict:
    """Each trained variant's generator in front of ``model_path`` on every test set (:func:`table_row`, no ICP)."""
    res = {}
    for name, r in trained.items():
        res[name] = dict(r)
        if "error" not in r:
            res[name].update({ts: table_row(model_path, path, ablation_file(out, name), False, max_scans)
                              for ts, path in testsets.items()})
        log(f"ablation {name}: {res[name]}")
    return res


def object_only_database(model, work: str | os.PathLike, workers: int = 1, progress: bool = False):
    """``model`` (a :class:`recog.model.Recogniser`, changed in place and returned) with its database rebuilt from
    the clean renderer's views of its own view grid, every pixel outside the object at +1 (the chunks' object
    ``mask``). The network is not retrained; ``info["reindexed"]`` says how the database was made. The clean
    views are simulated into ``work`` (kept chunks are reused)."""
    from recog.data import generate_training_data, load_training_data
    from recog.database import DescriptorDB
    if model.input != "depth":
        raise RealgapError(f"the recogniser reads {model.input}; an object-only database is of depth patches")
    objs = [model.object(k) for k in range(len(model.names))]
    views = dataclasses.replace(model.data, variant="clean")
    t0 = time.perf_counter()
    generate_training_data(objs, views, model.patch, work, workers=workers, progress=progress)
    td = load_training_data(objs, views, work)
    if td.mask is None:
        raise FormatError(work, "the simulated views hold no object masks (made by an older version: remove them)")
    patches = np.where(td.mask, td.patches[:, 0].astype(np.float32), 1.0).astype(np.float32)
    desc = model.describe(patches)
    model.db = DescriptorDB(desc, td.obj, td.R_local, td.offset[:, 0], td.view, "auto")
    model.info = {**model.info, "reindexed": {"views": "clean, object only (+1 elsewhere)", "entries": int(len(desc)),
                                              "seconds": round(time.perf_counter() - t0, 1)}}
    return model
