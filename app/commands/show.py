"""``realgap show RESULT...``: result files side by side (like evo_res).

RESULT is any result JSON of realgap (``metrics.json``, ``diagnosis.json``, a fitted model,
``stats.json`` of a SLAM run, the JSON of ``eval ate|rpe|run``, ``results.json`` of ``batch``) or
the folder holding one. The table has one column per result and one row per metric of their
common header (:mod:`data_tools.results`), and a unit column: every number has its unit
(:func:`data_tools.results.metric_unit`; a fitted model's parameters take theirs from the
effect registry).
"""
from __future__ import annotations

import argparse
import json

NAME = "show"
HELP = "print one or several result files side by side (metrics of their common header)"


def register(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("results", nargs="+", metavar="RESULT",
                        help="result JSON files or folders holding one (sensor compare/diagnose/fit, slam run, "
                             "eval ate/rpe/run, batch)")
    from app.commands import add_shared
    add_shared(parser, "--json", "the result headers")
    parser.set_defaults(func=run)


def run(args) -> int:
    from data_tools.errors import FormatError
    from data_tools.outputs import incomplete_text, read_incomplete
    from data_tools.results import format_table, read_result, results_table
    for p in args.results:
        marker = read_incomplete(p)
        if marker is not None:  # a folder a killed or running command left: say so, not "no result"
            raise FormatError(p, f"{incomplete_text(marker)}: no finished result yet")
    results = [read_result(p) for p in args.results]
    for r in results:
        _parameter_units(r)
    if args.json:
        print(json.dumps([{"path": str(r.path), "header": r.header, "metrics": r.metrics} for r in results], indent=2))
        return 0
    print(format_table(*results_table(results)))
    return 0


def _parameter_units(result) -> None:
    """Give the ``param.EFFECT.NAME`` metrics of a fitted model their unit from the effect registry."""
    params = [k for k in result.metrics if k.startswith("param.")]
    if not params:
        return
    from synth.sensor import catalog
    units = dict(result.header.get("units") or {})
    for key in params:
        effect, _, name = key.removeprefix("param.").rpartition(".")
        try:
            entry = catalog.effect_catalog(effect)[0]
        except Exception:       # an effect this installation does not know: leave the unit unknown
            continue
        for p in entry.get("parameters", []):
            if p.get("name") == name:
                units[key] = p.get("unit") or "1"
    result.header["units"] = units
