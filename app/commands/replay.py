"""``osteonav replay TRIAL --out DIR [--config FILE] [--realtime] [--overwrite]``: track a recorded trial.

The projector's plan (configs/projector.yaml) is checked against the trial's mesh; when it does not
fit, a plan of the same shape is placed on this mesh's ridge (one warning line; the summary names
the plan), or the projector is skipped when nothing fits: a valid trial always replays.
"""
from __future__ import annotations

from app.commands.outdir import add_overwrite_argument, prepare_dir


def register(subparsers) -> None:
    p = subparsers.add_parser("replay", help="run the tracker over a recorded trial and evaluate it")
    p.add_argument("trial", help="trial directory (RECORDING_FORMAT.md)")
    p.add_argument("--out", required=True, help="output directory: estimate.txt, status.csv, summary.json, log.rrd")
    p.add_argument("--config", help="tracker YAML (default: configs/default.yaml's values)")
    p.add_argument("--realtime", action="store_true", help="pace frames at their recorded stamps")
    p.add_argument("--no-rrd", action="store_true", help="do not write log.rrd")
    p.add_argument("--projector", help="projector and plan YAML (default: configs/projector.yaml)")
    p.add_argument("--no-projector", action="store_true", help="do not render the projector's template (the "
                   "tracking is the same: the plan's points still bound the status)")
    p.add_argument("--projector-images", action="store_true", help="also write the projector images to OUT/projector/")
    add_overwrite_argument(p, "OUT's replay outputs")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from app.config import load_config
    from app.outputs import OutputError, write_failure
    from app.pipeline.replay import replay
    from app.pipeline.report import print_summary

    from app.trial.reader import open_trial

    config = load_config(args.config)
    open_trial(args.trial).load_mesh()   # a broken trial or mesh is refused before OUT is touched
    prepare_dir(args.out, args.overwrite, inputs=[args.trial])
    bar = tqdm(desc="replay", unit="frame")

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    try:
        result = replay(args.trial, args.out, config, realtime=args.realtime, rrd=not args.no_rrd, progress=progress,
                        projector=not args.no_projector, projector_config=args.projector,
                        projector_images=args.projector_images)
    except OSError as exc:   # a write failed while frames were processed (a full disk)
        raise OutputError(write_failure(exc, f"--out {args.out}: the replay stopped at a failed write of "
                                             f"{Path(exc.filename).name if exc.filename else 'an output'}") +
                          "; estimate.txt and status.csv hold the frames before it, no summary.json") from None
    finally:
        bar.close()
    print_summary(result.summary)
    print(f"outputs in {args.out} (estimate.txt, status.csv, summary.json{', log.rrd' if not args.no_rrd else ''})")
    return 0
