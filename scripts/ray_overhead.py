"""Ray's overhead per task for bench sweeps (BENCHMARKS.md, "Sweeps on a Ray cluster").

Usage (a cluster started with ``ray start --head --num-cpus 1``, from the repository root)::

    .venv/bin/python scripts/ray_overhead.py TRIAL [--config osteonav_default] [--runs 4]

Prints a no-op task's round trip (one at a time, then 500 in flight), then, for ``--runs`` runs of
``--config`` on ``TRIAL`` (a trial folder), the driver's round trip of the bench's run task minus
the run's time inside the worker: what Ray adds to a run. The first run pays the new worker's start.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    import ray

    from app.bench import bench, bundles
    from app.bench.ray_executor import TASK_CPUS, run_remote, runtime_env

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trial")
    parser.add_argument("--config", default="osteonav_default")
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--address", default="auto", help="auto, HOST:PORT, or local (a Ray instance started here)")
    args = parser.parse_args()
    ray.init(address=None if args.address == "local" else args.address, log_to_driver=False,
             runtime_env=runtime_env())

    @ray.remote(num_cpus=TASK_CPUS)
    def noop(x):
        return x

    @ray.remote(num_cpus=TASK_CPUS)
    def timed(task, key):
        t = time.perf_counter()
        out = run_remote(task, key)
        return out, time.perf_counter() - t

    payload = {"row": "x" * 20000}   # about a row's size
    ray.get([noop.remote(1) for _ in range(5)])
    lat = []
    for _ in range(200):
        t = time.perf_counter()
        ray.get(noop.remote(payload))
        lat.append(time.perf_counter() - t)
    lat.sort()
    print(f"no-op round trip, one at a time: median {1e3 * statistics.median(lat):.2f} ms, p90 {1e3 * lat[179]:.2f} ms")
    t = time.perf_counter()
    ray.get([noop.remote(payload) for _ in range(500)])
    print(f"no-op, 500 in flight: {1e3 * (time.perf_counter() - t) / 500:.2f} ms per task")

    config = bench.resolve_configs([args.config])[0]
    trial = bench.recorded_trials([args.trial])[0]
    trial.path = str(Path(trial.path).resolve())
    task = {"config": config, "trial": trial, "out_dir": None, "with_vsd": False}
    key = bundles.fingerprint(trial.path)
    for i in range(args.runs):
        t = time.perf_counter()
        out, inner = ray.get(timed.remote(task, key))
        rt = time.perf_counter() - t
        print(f"run {i}: round trip {rt:.3f} s, in the worker {inner:.3f} s, Ray's overhead {1e3 * (rt - inner):.1f} ms "
              f"({100 * (rt - inner) / inner:.2f} %)")


if __name__ == "__main__":
    main()
