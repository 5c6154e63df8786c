"""Running bench tasks one after another or in a spawned process pool, with a progress bar."""
from __future__ import annotations


def pmap(fn, tasks: list, jobs: int, desc: str, unit: str, progress: bool = True, weights=None):
    """Yield fn(task) for each task (in completion order when parallel) with a tqdm bar."""
    from tqdm import tqdm

    weights = weights or [1] * len(tasks)
    with tqdm(total=sum(weights), desc=desc, unit=unit, disable=not progress, dynamic_ncols=True) as bar:
        if jobs <= 1 or len(tasks) <= 1:
            for task, w in zip(tasks, weights):
                yield fn(task)
                bar.update(w)
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(fn, task): w for task, w in zip(tasks, weights)}
            for future in as_completed(futures):
                yield future.result()
                bar.update(futures[future])
