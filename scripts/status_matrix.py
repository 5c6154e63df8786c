"""Simulate (cached) and replay the status's evaluation matrix: crests x scenarios x sensor models.

    nice .venv/bin/python scripts/status_matrix.py --label main --crests crest_left_03 crest_right_04 \\
        --scenarios static_clear static_far or_deep_tissue --sensors independent stereo tof --seconds 3 \\
        --cache /tmp/status/trials --out /tmp/status/out
    .venv/bin/python scripts/status_eval.py /tmp/status/out

Trials go to ``CACHE/<sensor>/<crest>/<scenario>`` (simulated once, seed ``--seed``), the replays to
``OUT/<label>/<crest>/<scenario>@<sensor>`` (skipped when their summary.json exists: a killed matrix
resumes). One process, one run at a time (the replay's own rate is not what is measured here).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
PELVIS = REPO.parent / "shared" / "data" / "pelvis"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True)
    ap.add_argument("--crests", nargs="+", required=True)
    ap.add_argument("--scenarios", nargs="+", required=True)
    ap.add_argument("--sensors", nargs="+", default=["independent"])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cache", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--config", type=Path, help="tracker YAML (default: configs/default.yaml)")
    args = ap.parse_args(argv)

    from app.config import load_config
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate

    config = load_config(args.config)

    for sensor in args.sensors:
        for scenario in args.scenarios:
            for crest in args.crests:
                trial = args.cache / sensor / crest / scenario
                if not (trial / "trial.yaml").is_file():
                    simulate(trial, mesh_path=PELVIS / f"{crest}.ply", scenario_name=scenario, seconds=args.seconds,
                             seed=args.seed, sensor=sensor)
                out = args.out / args.label / crest / f"{scenario}@{sensor}"
                if (out / "summary.json").is_file():
                    continue
                out.mkdir(parents=True, exist_ok=True)
                result = replay(trial, out, config, rrd=False)
                print(f"{crest}/{scenario}@{sensor}: ok {100 * result.summary['status_fraction']['ok']:.0f} %",
                      flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
