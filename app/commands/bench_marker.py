"""``osteonav bench-marker``: marker-only, IMU-only and fused tracking on the simulator (see
:mod:`app.marker.bench`): mean absolute inclination / anteversion errors and update rates."""
from __future__ import annotations

from app.cli_types import finite_float, finite_positive_float, seconds_over, seed

from app.commands.outdir import add_overwrite_argument, results_file


def register(subparsers) -> None:
    p = subparsers.add_parser("bench-marker", help="marker + IMU (publication C): errors and rates of marker-only, "
                                                   "IMU-only and fused tracking on simulated sequences")
    p.add_argument("--seconds", type=seconds_over(5.0, "registration and transfer take the first 3 s"), default=60.0,
                   help="length of each simulated sequence, s; must exceed 5 (registration and transfer take the "
                        "first 3 s; default %(default)s)")
    p.add_argument("--seeds", type=seed, nargs="+", default=[0],
                   help="one sequence per seed, integers >= 0; the table averages them (default 0)")
    p.add_argument("--camera-fps", type=finite_positive_float, default=10.0,
                   help="camera (marker) rate, Hz > 0 (default %(default)s)")
    p.add_argument("--imu-rate", type=finite_positive_float, default=100.0, help="IMU rate, Hz > 0 (default %(default)s)")
    p.add_argument("--yaw-drift", type=finite_float, default=None, help="IMU yaw drift, deg/s (default: the simulator's)")
    p.add_argument("--json", help="where to write the results (an existing file needs --overwrite; default: "
                   "recordings/bench_marker.json, or a dated name beside it when that exists)")
    add_overwrite_argument(p, "the --json file")
    p.set_defaults(func=run)


def run(args) -> int:
    args.json = str(results_file(args.json, "recordings/bench_marker.json", args.overwrite))
    import json
    from pathlib import Path

    import numpy as np

    from app.marker import bench

    extra = {} if args.yaw_drift is None else {"yaw_drift_deg_s": args.yaw_drift}
    runs = []
    for seed in args.seeds:
        print(f"seed {seed}:", flush=True)
        runs.append(bench.run(args.seconds, seed, args.camera_fps, args.imu_rate,
                              progress=lambda m: print(f"  {m}", flush=True), **extra))
    mean = {"methods": {}}
    for m in bench.METHODS:
        mean["methods"][m] = {k: float(np.mean([r["methods"][m][k] for r in runs]))
                              for k, v in runs[0]["methods"][m].items() if isinstance(v, (int, float))}
    print()
    print(bench.table(mean))
    fused = runs[-1]["methods"]["fused"]
    print(f"\nfused: marker found by region {fused['paths']['roi']}, by the whole image {fused['paths']['full']}, "
          f"not found {fused['paths']['none']}; calibration error "
          f"{np.mean([r['calibration']['error_deg'] for r in runs]):.2f} deg")
    Path(args.json).write_text(json.dumps({"mean": mean, "runs": runs}, indent=2, default=str))
    print(f"wrote {args.json}")
    return 0
