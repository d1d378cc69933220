"""``realgap demo``: the story of realgap on embedded data, in one report (``demo_out/index.html``).

The lab names the effect a mystery sensor hides and the gap falls; a simulated room walk is registered
by icp and by the neural memory, with novel and hallucinated views; chairs scanned by another sensor are
recognised by a recogniser trained on simulation only (:mod:`app.demo.run`). Re-running resumes.
The options are generated from :class:`app.demo.config.DemoConfig`.
"""
from __future__ import annotations

import argparse
import dataclasses

NAME = "demo"
HELP = "the story of realgap on embedded data: lab, exploration, recognition -> demo_out/index.html"


def register(parser: argparse.ArgumentParser) -> None:
    from app.commands import RESUMES, add_shared
    from app.commands.flags import add_config_flags
    from app.demo.config import DEMO_PRESETS, DemoConfig
    add_shared(parser, "--out", "the demo folder (default demo_out)", default="demo_out")
    parser.add_argument("--preset", default="default", choices=sorted(DEMO_PRESETS),
                        help="named configuration (default: the full story; quick: a smaller one)")
    add_config_flags(parser, DemoConfig, underscore_alias=False, exclude=("align",))
    from app.commands import add_align       # the shared --align of eval and batch (same choices and help)
    add_align(parser, argparse.SUPPRESS, "default: auto").dest = "cfg:align"
    add_shared(parser, "--no-progress")
    add_shared(parser, "--overwrite", "a finished demo in --out: its parts are computed again (an interrupted demo "
                                      "is continued without it)")
    parser.set_defaults(func=run, on_interrupt=RESUMES)


def demo_config(args):
    """The DemoConfig of the command line: the preset with the given flags replaced."""
    from app.demo.config import DEMO_PRESETS
    over = {k[4:]: v for k, v in vars(args).items() if k.startswith("cfg:")}
    return dataclasses.replace(DEMO_PRESETS[args.preset], **over).validate()


def run(args) -> int:
    from app.demo.run import run_demo, summary_lines
    facts = run_demo(args.out, demo_config(args), progress=not args.no_progress, overwrite=args.overwrite)
    print()
    print("\n".join(summary_lines(args.out, facts)))
    return 0
