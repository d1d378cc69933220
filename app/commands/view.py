"""``realgap view``: the PyVista desktop viewer (a sequence and its runs, a sensor-lab folder, or a
recognition evaluation), interactive or off-screen (``--screenshot``, ``--movie``)."""
from __future__ import annotations

import argparse

from app.commands import add_shared

NAME = "view"
HELP = "PyVista viewer: a sequence with its runs, a sensor-lab folder (--lab) or recognition results (--recog)"
DESCRIPTION = ("Explore a sequence and its registrations (trajectories coloured by error, failed frames, "
               "TSDF mesh, RGB and depth panes - measured, and simulated when a simulation of the sequence is "
               "given too - novel views of a virtual camera), a sensor-lab folder "
               "(measured vs simulated depth, residual map, effects switched on/off) or a recognition "
               "evaluation (CAD model at the estimated pose over the measured points). Press h in the "
               "window for the keys. --screenshot/--movie render off-screen and exit.")


def register(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="*", metavar="SEQ_OR_RUN",
                        help="a sequence folder and/or SLAM run folders; a second sequence folder is a simulation "
                             "of the first (sensor simulate / synth sequence --sensor): its depth and the residual "
                             "are shown beside the measured depth")
    parser.add_argument("--lab", metavar="LABDIR", help="a sensor-lab folder (realgap sensor compare --out)")
    parser.add_argument("--recog", nargs=2, metavar=("EVAL_DIR", "TESTSET"),
                        help="a recognition evaluation (realgap recog eval --out) and its test set")
    parser.add_argument("--frame", type=int, default=0, metavar="N", help="frame (or scan) to show first (default 0)")
    parser.add_argument("--camera", metavar="POSE", help='virtual camera "tx ty tz qx qy qz qw" (camera-to-world, '
                                                         "ground-truth frame) for the novel views")
    parser.add_argument("--screenshot", metavar="OUT.png", help="render off-screen to this PNG and exit")
    parser.add_argument("--movie", metavar="OUT.gif|mp4", help="render a fly-through off-screen and exit")
    parser.add_argument("--size", default="1600x900", help="window size WxH in pixels (default 1600x900)")
    add_shared(parser, "--overwrite", "an existing --screenshot / --movie file")
    parser.set_defaults(func=_run, _io_allow_inside=("SEQ_OR_RUN", "--lab", "--recog"))  # screenshots of a folder may live in it


def _run(args) -> int:
    from app.viewer.run import open_viewer
    written = open_viewer(args.paths, lab=args.lab, recog=args.recog, frame=args.frame, camera=args.camera,
                          screenshot=args.screenshot, movie=args.movie, size=args.size, overwrite=args.overwrite)
    for path, what in written:
        print(f"{path}: {what}")
    return 0
