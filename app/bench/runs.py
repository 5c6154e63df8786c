"""Bench runs: one configuration replayed on one trial and scored (a JSON-ready row), and all of them."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from app.bench.configs import BenchConfig
from app.bench.scoring import after_rest, in_view_share, jitter, refound, static_pairs, vsd_series
from app.bench.template import template_scores
from app.bench.trials import TrialSpec
from app.metrics import DANGEROUS_ADD_MM, LOST_ADD_MM


def run_one(config: BenchConfig, trial: TrialSpec, out_dir: str | Path | None = None, progress=None,
            with_vsd: bool = True) -> dict:
    """Replay ``trial`` with ``config`` and score it; a JSON-ready row (module docstring's columns)."""
    from app import metrics
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.trial.reader import open_trial

    make_tracker, tracker_config = None, config.tracker
    if config.kind == "icp":
        from app.baselines.icp import ICPTracker

        params = config.icp
        make_tracker = lambda mesh, camera: ICPTracker(params, mesh, camera)  # noqa: E731
        tracker_config = load_config(None)
    trial.ensure()
    t0 = time.perf_counter()
    result = _replay_into(out_dir, lambda: replay(trial.path, out_dir, tracker_config, rrd=False, progress=progress,
                                                  max_frames=trial.max_frames, make_tracker=make_tracker))
    wall = time.perf_counter() - t0
    reader = open_trial(trial.path)
    n = len(result.stamps)
    T_gt = np.asarray(reader.groundtruth[:n])
    T_est = result.T_base_bone
    points = np.asarray(reader.load_mesh().vertices)
    add_s, mdd_s = metrics.symmetric_errors(T_est, T_gt, points)
    add_mm = result.errors["add_mm"]
    statuses = np.array(result.statuses)
    ok = statuses == "ok"
    vsd = vsd_series(trial.path, T_est, n) if with_vsd else np.full(n, np.nan)
    t_rel = result.stamps - result.stamps[0]
    in_view = in_view_share(reader.camera_poses()[0][:n], T_gt, points, reader.meta.camera)
    found = refound(T_gt, t_rel, add_mm, in_view)
    row = {
        "config": config.name, "config_description": config.describe(), "config_source": config.source,
        "tracker": config.kind, "trial": trial.name, "trial_path": trial.path, "mesh": trial.mesh,
        "scenario": trial.scenario, "seed": trial.seed, "sensor": trial.sensor, "frames": n,
        "fps": result.summary["processing_rate_hz"], "wall_s": wall, "gl": result.summary.get("gl"),
        "timings_ms": result.summary.get("timings_ms", {}),
        "add_mm": metrics.summarise(add_mm), "add_s_mm": metrics.summarise(1e3 * add_s),
        "mdd_s_mm": metrics.summarise(1e3 * mdd_s), "translation_mm": metrics.summarise(result.errors["trans_mm"]),
        "rotation_deg": metrics.summarise(result.errors["rot_deg"]),
        "vsd": metrics.summarise(vsd), "vsd_recall": metrics.vsd_recall(vsd[np.isfinite(vsd)]) if with_vsd else float("nan"),
        "lost_pct": float(100 * np.mean(add_mm > LOST_ADD_MM)),
        "status_pct": {s: float(100 * np.mean(statuses == s)) for s in ("ok", "uncertain", "lost")},
        "dangerous_frames": int(np.sum(ok & (add_mm > DANGEROUS_ADD_MM))),
        "jitter": jitter(T_est, static_pairs(T_gt, result.stamps)),
        "after_rest": after_rest(T_gt, t_rel, add_mm),
        "refound": found, "refound_s": None if found is None else found["refound_s"],
        "recovery": result.summary.get("recovery"),
        "template": template_scores(reader, T_est, result.statuses, n),
        "series": {"t": t_rel.round(4).tolist(), "add_mm": np.round(add_mm, 4).tolist(),
                   "rot_deg": np.round(result.errors["rot_deg"], 4).tolist(),
                   "vsd": [None if not np.isfinite(v) else round(float(v), 4) for v in vsd],
                   "status": result.statuses},
    }
    return row


def _replay_into(out_dir, run):
    """``run()`` with ``out_dir`` (when given) open as an output folder of its own (app/outputs.py),
    listed in the bench's ``--out`` folder: in a worker process too."""
    if out_dir is None:
        return run()
    from app.outputs import close_folder, open_folder

    open_folder(out_dir, overwrite=False, flag="--out")
    try:
        return run()
    finally:
        close_folder(out_dir)


def bench_tasks(configs: list[BenchConfig], trials: list[TrialSpec], out_dir: str | Path | None = None,
                with_vsd: bool = True) -> list[dict]:
    """One task per (trial, configuration), trial-major: ``{config, trial, out_dir, with_vsd}``; the
    tasks of one trial share its :class:`TrialSpec` (a lazy trial is simulated once)."""
    tasks = []
    for trial in trials:
        for config in configs:
            task_out = str(Path(out_dir) / config.name / trial.name) if out_dir else None
            tasks.append({"config": config, "trial": trial, "out_dir": task_out, "with_vsd": with_vsd})
    return tasks


def run_bench(configs: list[BenchConfig], trials: list[TrialSpec], jobs: int = 1, out_dir: str | Path | None = None,
              with_vsd: bool = True, progress: bool = True, on_row=None, executor=None) -> list[dict]:
    """Every configuration on every trial; rows ordered by trial, then configuration.

    ``on_row(rows)`` is called with the rows so far after each run (to write a partial matrix).
    ``executor`` runs the tasks (:mod:`app.bench.executors`; default a :class:`LocalExecutor` of
    ``jobs`` processes). With ``jobs`` > 1 the runs go to a spawned process pool (each process opens
    its own GL context); frames/s then measure a shared CPU. ``out_dir`` keeps each run's
    estimate.txt and status.csv under ``<out_dir>/<config>/<mesh>/<scenario>``, each listed in the
    bench's ``--out`` folder before it runs (a worker process cannot list it).
    """
    from app.bench.executors import LocalExecutor
    from app.outputs import wrote

    tasks = bench_tasks(configs, trials, out_dir, with_vsd)
    for task in tasks:
        if task["out_dir"]:
            wrote(task["out_dir"], folder=True)
    rows = (executor or LocalExecutor(jobs)).run(tasks, progress=progress, on_row=on_row)
    order = {(t["trial"].name, t["config"].name): k for k, t in enumerate(tasks)}
    return sorted(rows, key=lambda r: order[(r["trial"], r["config"])])
