"""``osteonav view TRIAL [--save FILE.rrd]``: a recorded trial in rerun.

Logs the camera (pinhole and depth image), the flange path, the bone mesh at the ground truth and
the simulator's occlusion fraction when present, on timelines ``stamp`` and ``frame``, with the
default blueprint. Without ``--save`` it spawns the viewer.
"""
from __future__ import annotations

from app.commands.outdir import add_overwrite_argument, prepare_file


def register(subparsers) -> None:
    p = subparsers.add_parser("view", help="log a recorded trial to rerun (viewer or .rrd file)")
    p.add_argument("trial", help="trial directory")
    p.add_argument("--save", metavar="FILE.rrd", help="write a .rrd file instead of spawning the viewer")
    p.add_argument("--every", type=int, default=1, help="log every n-th depth image (default 1)")
    add_overwrite_argument(p, "an existing --save file")
    p.set_defaults(func=run)


def run(args) -> int:
    from app.errors import OsteonavError
    from app.trial.reader import open_trial
    from app.viz.trial_view import log_trial, viewer_executable

    if args.every < 1:
        raise OsteonavError(f"--every must be at least 1, got {args.every}")
    open_trial(args.trial)
    if args.save:
        if not str(args.save).endswith(".rrd"):
            raise OsteonavError(f"--save {args.save}: expected a .rrd file name")
        prepare_file(args.save, args.overwrite, "--save")
    else:
        viewer_executable()   # a one-line error when no viewer or no display, before any work
    frames = log_trial(args.trial, save=args.save, every=args.every)
    if args.save:
        print(f"wrote {frames} frames to {args.save}; open it with: rerun {args.save}")
    return 0
