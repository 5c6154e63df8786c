"""The or_fast_reposition recovery matrix (BENCHMARKS.md, "Recovery: a moved bone found again") in one
process pool: simulation and replays together, one configuration (filter seed) after the other.

Simulates each trial with the CLI (`python -m app.cli simulate --out TRIALS/<crest>/or_fast_reposition_seedN
--mesh MESH --scenario or_fast_reposition --seed N --seconds 7`, §6o's command) and replays it with
app.bench.runs.run_one (what `osteonav bench --trials ... --no-vsd` runs per trial), the
configurations in the order given (filter seed 0 first), and writes one JSON line per finished
run to --out (the row of `osteonav bench --json`, the series cut to t, add_mm and status). A replay
waits for its trial's simulation; the pool keeps every worker busy (one `osteonav bench` per seed
idles its workers at each seed's tail). With --deadline (seconds since the epoch) the pool is
stopped then: the runs finished so far are in --out, whole seeds first. Summarise with
scripts/recovery_summary.py.

    for n in 0 1 2 3; do printf "filter:\n  particles: 200\n  seed: $n\nrender:\n  backend: cpu\n" > fseed$n.yaml; done
    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 .venv/bin/python scripts/recovery_matrix.py \
        --meshes ../shared/data/pelvis/crest_*.ply --seeds 0 1 2 3 4 5 --configs fseed0.yaml fseed1.yaml fseed2.yaml fseed3.yaml \
        --trials /tmp/rp --jobs 15 --out matrix.jsonl [--deadline $(( $(date +%s) + 400 ))]
    .venv/bin/python scripts/recovery_summary.py matrix.jsonl
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import subprocess
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))   # the repository's app package, in the spawned workers too

KEEP_SERIES = ("t", "add_mm", "status")


def simulate(mesh: str, seed: int, out: str, seconds: float) -> dict:
    """One trial through the CLI (an existing one, with its trial.yaml, is reused); writes ``<out>.done``
    (the exit code) for the replays waiting on it."""
    t0 = time.time()
    if (Path(out) / "trial.yaml").exists():                     # simulated by an earlier run: reused as it is
        Path(f"{out}.done").write_text("0")
        return {"kind": "sim", "trial": out, "rc": 0, "wall_s": 0.0, "tail": "", "reused": True}
    log = Path(out).parent / f"{Path(out).name}.log"
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "app.cli", "simulate", "--out", out, "--mesh", mesh, "--scenario",
           "or_fast_reposition", "--seed", str(seed), "--seconds", f"{seconds:g}"]
    with open(log, "w") as f:
        rc = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=REPO)
    Path(f"{out}.done").write_text(str(rc))
    tail = "" if rc == 0 else log.read_text()[-1500:]
    return {"kind": "sim", "trial": out, "rc": rc, "wall_s": time.time() - t0, "tail": tail}


def replay(config_path: str, trial_dir: str) -> dict:
    """The bench's row of one configuration on one trial, once the trial is simulated."""
    import logging

    while not Path(f"{trial_dir}.done").exists():
        time.sleep(0.2)
    if Path(f"{trial_dir}.done").read_text().strip() != "0":
        return {"kind": "run", "error": f"simulation of {trial_dir} failed", "config": Path(config_path).stem,
                "trial_path": trial_dir}
    from app.bench.configs import resolve_configs
    from app.bench.trials import recorded_trials
    from app.bench.runs import run_one

    logging.basicConfig(level=logging.WARNING)
    config = resolve_configs([config_path])[0]
    trial = recorded_trials([trial_dir])[0]
    t0, c0 = time.time(), time.process_time()
    try:
        row = run_one(config, trial, None, with_vsd=False)
    except Exception as exc:  # noqa: BLE001 - report and go on
        import traceback

        return {"kind": "run", "error": f"{type(exc).__name__}: {exc}", "tb": traceback.format_exc()[-2000:],
                "config": config.name, "trial_path": trial_dir}
    row["series"] = {k: row["series"][k] for k in KEEP_SERIES}
    row["kind"] = "run"
    row["worker_cpu_s"] = time.process_time() - c0
    row["worker_wall_s"] = time.time() - t0
    return row


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", nargs="+", required=True)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4, 5])
    ap.add_argument("--configs", nargs="+", required=True)
    ap.add_argument("--trials", required=True)
    ap.add_argument("--seconds", type=float, default=7.0)
    ap.add_argument("--jobs", type=int, default=15)
    ap.add_argument("--out", required=True)
    ap.add_argument("--deadline", type=float, default=float("inf"), help="stop at this time (s since the epoch)")
    args = ap.parse_args()

    trials = []
    for m in sorted(args.meshes):
        for n in args.seeds:
            trials.append((str(Path(m).resolve()), n, str(Path(args.trials).resolve() / Path(m).stem / f"or_fast_reposition_seed{n}")))
    out = open(args.out, "w")
    t_start = time.time()
    pool = ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn"))
    futures = {}
    for mesh, n, d in trials:
        futures[pool.submit(simulate, mesh, n, d, args.seconds)] = ("sim", d)
    for c in args.configs:
        for _, _, d in trials:
            futures[pool.submit(replay, c, d)] = (Path(c).stem, d)
    pending = set(futures)
    done_runs = {Path(c).stem: 0 for c in args.configs}
    stopped = False
    while pending:
        left = args.deadline - time.time()
        if left <= 0:
            stopped = True
            break
        done, pending = wait(pending, timeout=min(left, 10.0), return_when=FIRST_COMPLETED)
        for f in done:
            try:
                row = f.result()
            except Exception as exc:  # noqa: BLE001 - a worker died
                row = {"kind": "error", "what": futures[f], "error": f"{type(exc).__name__}: {exc}"}
            row["done_at_s"] = time.time() - t_start
            out.write(json.dumps(row) + "\n")
            out.flush()
            if row.get("kind") == "run" and "error" not in row:
                done_runs[row["config"]] += 1
            if row.get("kind") == "sim" and row["rc"] != 0:
                print(f"SIM FAILED {row['trial']}: {row['tail']}", flush=True)
            if row.get("error"):
                print(f"ERROR {row.get('config')} {row.get('trial_path')}: {row['error']}\n{row.get('tb', '')}", flush=True)
        print(f"[{time.time() - t_start:6.1f} s] runs done per config: {done_runs}, pending tasks {len(pending)}", flush=True)
    if stopped:
        print(f"DEADLINE: stopped with {len(pending)} tasks left; runs done per config: {done_runs}", flush=True)
        for p in list(getattr(pool, "_processes", {}).values()):
            try:
                p.kill()
            except Exception:  # noqa: BLE001
                pass
        pool.shutdown(wait=False, cancel_futures=True)
    else:
        pool.shutdown(wait=True)
    out.write(json.dumps({"kind": "end", "stopped": stopped, "elapsed_s": time.time() - t_start,
                          "runs_done": done_runs}) + "\n")
    out.close()
    print(f"matrix: {time.time() - t_start:.1f} s, runs done {done_runs}, stopped at deadline: {stopped}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
