"""Where bench runs execute: on this machine (:class:`LocalExecutor`) or on a Ray cluster
(:class:`app.bench.ray_executor.RayExecutor`), behind one interface.

An executor's ``run(tasks, progress, on_row)`` takes :func:`app.bench.runs.bench_tasks`'s tasks
(one per trial and configuration) and returns one row per task (:func:`app.bench.runs.run_one`),
in any order; ``on_row(rows)`` is called with the rows so far after each finished run.
"""
from __future__ import annotations

import logging

from app.errors import ConfigError

EXECUTORS = ("local", "ray")


class LocalExecutor:
    """The runs one after another in this process (a per-frame progress bar), or in ``jobs`` spawned
    processes (each opens its own GL context; frames/s then measure a shared CPU)."""

    name = "local"

    def __init__(self, jobs: int = 1):
        self.jobs = jobs

    def describe(self) -> str:
        return f"{self.jobs} process(es)"

    def run(self, tasks: list[dict], progress: bool = True, on_row=None) -> list[dict]:
        weights = [max(t["trial"].max_frames or t["trial"].frames, 1) for t in tasks]
        if self.jobs <= 1:
            return _run_serial(tasks, weights, progress, on_row)
        from app.bench.parallel import pmap

        rows = []
        for row in pmap(_run_task, tasks, self.jobs, desc="bench", unit="frame", progress=progress, weights=weights):
            rows.append(row)
            if on_row:
                on_row(rows)
        return rows

    def close(self) -> None:
        """Nothing to release."""


def _run_task(task: dict) -> dict:
    """Worker entry point (spawned process: its own GL context)."""
    from app.bench.runs import run_one

    logging.basicConfig(level=logging.WARNING)
    return run_one(task["config"], task["trial"], task.get("out_dir"), with_vsd=task.get("with_vsd", True))


def _run_serial(tasks, weights, progress: bool, on_row=None) -> list[dict]:
    from tqdm import tqdm

    from app.bench.runs import run_one

    rows = []
    with tqdm(total=sum(weights), desc="bench", unit="frame", disable=not progress, dynamic_ncols=True) as bar:
        for task, w in zip(tasks, weights):
            bar.set_postfix_str(f"{task['config'].name} on {task['trial'].name}")
            done = [0]

            def step(i, total, done=done):
                bar.update(i - done[0])
                done[0] = i

            rows.append(run_one(task["config"], task["trial"], task["out_dir"], progress=step, with_vsd=task["with_vsd"]))
            if on_row:
                on_row(rows)
            bar.update(w - done[0])
    return rows


def make_executor(name: str = "local", jobs: int = 1, address: str | None = None, task_memory_gb: float | None = None):
    """The executor called ``name`` (:data:`EXECUTORS`); ConfigError naming the option when the
    options do not fit it or when Ray is not installed (with the command that installs it)."""
    if name not in EXECUTORS:
        raise ConfigError("--executor", f"unknown executor '{name}'; valid: {', '.join(EXECUTORS)}")
    if name == "local":
        if address is not None:
            raise ConfigError("--address", "applies to --executor ray only (the Ray cluster to run on)")
        if task_memory_gb is not None:
            raise ConfigError("--task-memory", "applies to --executor ray only (the memory Ray reserves per run)")
        return LocalExecutor(jobs)
    if jobs != 1:
        raise ConfigError("--jobs", "applies to --executor local only; on Ray every run is one task of 1 CPU and "
                          "the cluster's CPUs set how many run at once")
    from app.bench.ray_executor import DEFAULT_TASK_MEMORY_GB, RayExecutor

    return RayExecutor(address, task_memory_gb=DEFAULT_TASK_MEMORY_GB if task_memory_gb is None else task_memory_gb)
