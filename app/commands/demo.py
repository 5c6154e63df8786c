"""``osteonav demo``: simulate the default trial (cached), replay it, print the summary.

The README's main command. The trial lives in ``recordings/demo/trial`` and is simulated once;
the replay's outputs (estimate, status, summary, ``log.rrd``) go to ``recordings/demo/replay``.
Each run replaces the demo's own earlier outputs there, and nothing else (app/outputs.py: a folder
holding other files is refused, by name).
"""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DEMO_DIR = REPO / "recordings" / "demo"


def register(subparsers) -> None:
    from app.cli_types import positive_seconds
    from app.sim.scenarios import DEFAULT_SCENARIO, SCENARIOS

    p = subparsers.add_parser("demo", help="simulate the default trial (cached), track it, summarise")
    p.add_argument("--scenario", default=None, choices=list(SCENARIOS), metavar="NAME",
                   help=f"simulation scenario, one of: {', '.join(SCENARIOS)} (default {DEFAULT_SCENARIO})")
    p.add_argument("--seconds", type=positive_seconds, default=None,
                   help="duration of the simulated trial, s > 0 (default: the scenario's)")
    p.add_argument("--config", help="tracker YAML (default: configs/default.yaml's values)")
    p.add_argument("--dir", default=str(DEMO_DIR), help=f"demo folder (default {DEMO_DIR})")
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from app.commands.outdir import prepare_dir
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.pipeline.report import print_summary
    from app.sim.scenarios import DEFAULT_SCENARIO
    from app.sim.simulator import simulate

    scenario = args.scenario or DEFAULT_SCENARIO
    base = Path(args.dir)
    trial = base / f"trial_{scenario}" if args.seconds is None else base / f"trial_{scenario}_{args.seconds:g}s"
    if not (trial / "trial.yaml").exists() or (trial / ".recording-in-progress").exists():
        prepare_dir(trial, True, "--dir")
        bar = tqdm(desc=f"simulating {scenario}", unit="frame")
        simulate(trial, scenario_name=scenario, seconds=args.seconds, seed=0, overwrite=True,
                 progress=lambda done, total: (setattr(bar, "total", total), bar.update(done - bar.n)))
        bar.close()
    else:
        print(f"using the cached trial {trial}")
    out = prepare_dir(base / f"replay_{scenario}", True, "--dir")
    bar = tqdm(desc="tracking", unit="frame")
    result = replay(trial, out, load_config(args.config),
                    progress=lambda done, total: (setattr(bar, "total", total), bar.update(done - bar.n)))
    bar.close()
    print(f"\nosteonav demo: scenario '{scenario}' ({trial})")
    print_summary(result.summary)
    rrd = out / "log.rrd"
    print("\nthe projector's view (the planned outline when the status is ok, a red warning frame otherwise)"
          " is the 'Projector' panel of the recording")
    print(f"\nrerun recording: {rrd}\n  open it with:  {Path(__file__).resolve().parents[2] / '.venv/bin/rerun'} {rrd}"
          "\n  (or `rerun` with rerun-sdk installed; the viewer needs a display)")
    return 0
