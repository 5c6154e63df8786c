"""``osteonav record --config SESSION.yaml --out DIR``: record the session's sensors as a trial.

The same loop as ``osteonav track``; the sensors (every accepted depth frame, every joint sample)
are written to DIR in the trial format (RECORDING_FORMAT.md) as they arrive, by a background
writer, so a crash or kill leaves every frame written so far readable. By default nothing is
tracked (no mesh needed beyond the trial's ``mesh``); ``--track`` also runs the session's tracker.
``osteonav replay DIR`` reads the result.
"""
from __future__ import annotations

from app.commands.outdir import add_overwrite_argument


def register(subparsers) -> None:
    from app.commands.track import add_seconds_argument

    p = subparsers.add_parser("record", help="record a session's camera and robot streams as a trial")
    p.add_argument("--config", required=True, help="session YAML (see configs/sessions/)")
    p.add_argument("--out", required=True, help="trial directory to write")
    p.add_argument("--track", action="store_true", help="also run the tracker (estimates in --track-out)")
    p.add_argument("--track-out", help="directory for the tracker's outputs (with --track; default: the session file's out)")
    add_seconds_argument(p)
    add_overwrite_argument(p, "the trial in --out (and --track-out's outputs)")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from app.commands.track import naming_the_session_file, prepare_session_dirs, print_summary, recording_exit_code
    from app.session import load_session, run_session

    overrides = {"record": str(Path(args.out).resolve())}
    if not args.track:
        overrides["tracker"] = False
        overrides["out"] = None
    elif args.track_out:
        overrides["out"] = str(Path(args.track_out).resolve())
    config = load_session(args.config, overrides)
    if args.seconds is not None:
        config.loop.duration_s = args.seconds
    prepare_session_dirs(config, args.overwrite)
    with naming_the_session_file(args.config):
        result = run_session(config)
    print_summary(result.summary, tracked=args.track)
    code = recording_exit_code(result.summary)
    if code == 0:
        print(f"trial written to {args.out}")
    return code
