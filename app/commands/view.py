"""``osteonav view TRIAL [--rrd FILE.rrd]``: a recorded trial in rerun.

Logs the camera (pinhole, depth image, and the infrared and colour images of a 1.1 trial), the flange path, the bone mesh at the ground truth and
the simulator's occlusion fraction when present, on timelines ``stamp`` and ``frame``, with the
default blueprint. Without ``--rrd`` it spawns the viewer (``--save`` is the deprecated spelling of ``--rrd``).
"""
from __future__ import annotations

from app.cli_types import deprecated_alias, positive_int

from app.commands.outdir import add_overwrite_argument, prepare_file


def register(subparsers) -> None:
    p = subparsers.add_parser("view", help="log a recorded trial to rerun (viewer or .rrd file)")
    p.add_argument("trial", help="trial directory")
    p.add_argument("--rrd", metavar="FILE.rrd", help="write a .rrd file instead of spawning the viewer (default: "
                   "spawn the viewer)")
    deprecated_alias(p, "--save", "--rrd")
    p.add_argument("--every", type=positive_int, default=1, help="log every n-th depth image, n >= 1 (default 1)")
    add_overwrite_argument(p, "an existing --rrd file")
    p.set_defaults(func=run)


def run(args) -> int:
    from app.errors import OsteonavError
    from app.trial.reader import open_trial
    from app.viz.trial_view import log_trial, viewer_executable

    open_trial(args.trial)
    if args.rrd:
        if not str(args.rrd).endswith(".rrd"):
            raise OsteonavError(f"--rrd {args.rrd}: expected a .rrd file name")
        prepare_file(args.rrd, args.overwrite, "--rrd")
    else:
        viewer_executable()   # a one-line error when no viewer or no display, before any work
    frames = log_trial(args.trial, save=args.rrd, every=args.every)
    if args.rrd:
        print(f"wrote {frames} frames to {args.rrd}; open it with: rerun {args.rrd}")
    return 0
