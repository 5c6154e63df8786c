"""The tracker's stages over two cores (``filter.stages``; issue 35, Deliver 2).

Import as ``from app.pipeline.stages import StageWorker, stages_mode``. With the cpu backend the
likelihood's kernel already spreads the particles over numba's threads (app/render/cpu_raster.py,
``prange`` over chunks), but the refinement runs on one core, and on a CT crest it is half the
frame's CPU. What of it needs nothing of the filter's frame runs on a second thread
(:class:`StageWorker`, one worker) beside the filter's step, and the results are the serial ones,
bit for bit:

- **the track's refinement beside the filter's step.** On a frame after the first, the refined track
  refines from its own last pose (app/filter/refine_track.py, ``RefinedTrack.track_fit``): that needs
  the frame's depth and camera pose and the track, not the filter's estimate. The tracker hands it to
  the worker after the recovery (which may re-seed the track) and before the filter's step, and hands
  the fit to ``RefinedTrack.update``, which then does what depends on the filter (the refinement from
  the filter's estimate when the track's fitness is low or the estimate far, the choice, the static
  prior, feedback) as before. On a frame the filter does not weigh, the fit is dropped unused;
- **the nearby search's refinements two at a time** (app/filter/nearby_search.py, every
  ``refine.nearby_every`` frames: ``nearby_starts`` refinements from poses drawn first): independent
  fits, taken in their order, the search stopping at the same one as serially (a fit computed ahead
  of one that stops it is dropped). Only where ``refine.nearby_per_frame`` allows two on a frame (0, or
  2 and more: the default 2); at 1 the search's one refinement a frame runs on the calling thread.

The refiner (app/filter/refine.py) keeps no state between calls and its kernels release the GIL
(app/render/cpu_raster.py ``_njit``), so two refinements, or a refinement and the likelihood, run
at once on two cores. No random draw moves: the filter's generator is drawn only by the filter's step
on the calling thread, and the nearby search draws its starts before any fit. Nothing is copied per
frame: the worker reads the frame's arrays in place, and the caller waits for it before the frame
ends.

What does not overlap: the filter's step needs the last frame's feedback (the cloud shifted onto the
refined pose), so the likelihood of frame k+1 cannot run beside the refinement of frame k without
changing the results; the rest of the refinement (the choice, the static prior, the status) depends on
the filter's frame. Measured (BENCHMARKS.md "Filter rate and CPU"): ``osteonav bench-rate --whole``
prints serial and parallel side by side.

``auto`` is the default: ``parallel`` when the refinement is on and the process may run on two or
more cores, else ``serial``. On the idle 2-core sandbox parallel ran 1.11-1.12x serial's frames/s
(2026-11-27, BENCHMARKS.md "Filter rate and CPU"); on the same machine loaded by other jobs, which
gave the process about one core, 0.98-1.03x.
"""
from __future__ import annotations

import os
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Callable, Iterable, Iterator

AUTO, SERIAL, PARALLEL = "auto", "serial", "parallel"
MODES = (AUTO, SERIAL, PARALLEL)


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the platform tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def stages_mode(choice: str, refine: bool) -> str:
    """``filter.stages`` resolved: ``auto`` is ``parallel`` with the refinement on and two or more
    usable cores, else ``serial``; ``parallel`` without the refinement has nothing to overlap (serial)."""
    if choice not in MODES:
        raise ValueError(f"filter.stages must be one of {', '.join(MODES)}, got {choice!r}")
    if not refine:
        return SERIAL
    if choice == AUTO:
        return PARALLEL if usable_cores() >= 2 else SERIAL
    return choice


class StageWorker:
    """One worker thread for the stages that run beside the calling thread (module docstring)."""

    def __init__(self):
        from app.tracking.search_worker import one_numba_thread, shorten_gil_switch

        shorten_gil_switch()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="osteonav-stage")
        self._executor.submit(one_numba_thread).result()

    def submit(self, fn: Callable, *args) -> Future:
        """Run ``fn(*args)`` on the worker."""
        return self._executor.submit(fn, *args)

    def pairs(self, fn: Callable, items: Iterable) -> Iterator:
        """``fn(item)`` for each item, in order, two at a time (the next item's on the worker, this
        one's on the calling thread); as lazy as ``map`` per pair: a consumer that stops early leaves
        at most the pair's second result unused (waited for, not left running)."""
        items = list(items)
        for i in range(0, len(items), 2):
            ahead = self._executor.submit(fn, items[i + 1]) if i + 1 < len(items) else None
            try:
                first = fn(items[i])
            except BaseException:
                if ahead is not None:
                    wait([ahead])
                raise
            try:
                yield first
            finally:
                if ahead is not None:
                    wait([ahead])           # also when the consumer stopped: nothing runs on past the frame
            if ahead is not None:
                yield ahead.result()

    def close(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)

