"""Searches off the frame loop: a wide search runs on a worker (a process or a thread) while the track goes on.

Import as ``from app.tracking.search_worker import SearchWorker``. Issue 35, Deliver 3: a wide search
(1-4 s of CPU) blocked a live session's frame loop, with no estimate meanwhile. With
``recovery.search_worker`` ``thread`` (``auto``: in a live session, ``osteonav track``) or ``process``
the recovery hands the due search to this worker and the tracker goes on with its track, in the lifecycle's
``searching`` state (never ok); the result is taken on the first frame after it is ready and applied
there (app/pipeline/recovery_runner.py): a found pose is a base-frame pose, so the camera's motion
since the search's frame is already in it (the robot's encoders), and the bone is taken to have
stayed where the search saw it (the found pose then awaits its confirmation, as always). Replays and
benchmarks search inline (``auto``), so that a replay is reproducible frame for frame. A start
without a pose (the detector from a point, app/tracking/start.py) runs on the same worker: the frames
before it finds the bone are 'initialising' (lost) as when it searched inline, but they keep coming.

The worker owns its own likelihood backend and refiner, built on its thread at the first search
(a GL context belongs to the thread that made it; the tracker's are busy with the frames), and its
own random generator, drawn once from the tracker's; it is built when the tracker is (:meth:`prepare`).
The numba kernels release the GIL (app/render/cpu_raster.py ``_njit``) and the worker runs them on
one thread, so on two cores the search and the frames run side by side.
A search that raises is logged and counts as one that found nothing: the session goes on.

``process`` (issue 35): the worker is a child process (spawned, one numba thread, ``SEARCH_NICE`` lower
priority) that builds its own search from picklable parts (app/pipeline/tracker.py's
:func:`~app.pipeline.tracker.build_worker_search`) and keeps its own generator (the same one a thread
would have: drawn once from the tracker's). The search's Python parts (numpy between the kernels, the
refiner's association, scipy) then never hold the frame loop's GIL, and the operating system gives the
frame loop's threads the cores first: a thread of the same process could not be given a lower priority
without the loop waiting on a GIL held by a thread the scheduler keeps off the cores. Each job's
images are pickled to the child (about 1-2 MB, once per search) by the executor's own thread.
Measured on the shared 2-core sandbox (2026-11-28, BENCHMARKS.md "The search in a worker process"):
a frame beside a search cost what it costs without one (the thread had doubled it: 16.6 against
8.1 ms of CPU), and under other jobs' load (5-6.5) the session did better (latency p99 181-248
against 231-385 ms); but at load 2.4-2.8, the nearest to a dedicated machine, it did a little worse
(latency median 20.6-22.6 against 14.3-18.7 ms, 41-44 against 47-53 frames/s, three pairs), and the
niced search takes longer while the loop is busy (0.5-5 s against 0.5-3.8 s). The GIL itself was
3-4 % of the loop's wall time, the cores' share most of it. So ``auto`` stays ``thread``.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)
INLINE, THREAD, PROCESS, AUTO = "inline", "thread", "process", "auto"
MODES = (AUTO, INLINE, THREAD, PROCESS)
SEARCH_NICE = 5              # the search process's niceness above the frame loop's: the loop's threads get the
                             # cores first when both want them; the search still gets a share (weight 335
                             # against 1024 per nice-0 thread), so it is slowed, not starved, by the loop
SWITCH_INTERVAL_S = 0.0005   # the GIL handed over every 0.5 ms, not Python's 5: the frame loop's many short
                             # Python steps between GIL-free kernels each waited up to 5 ms for the worker


def search_worker_mode(choice: str, live: bool) -> str:
    """``recovery.search_worker`` resolved: ``auto`` is ``thread`` in a live session, else ``inline``."""
    if choice not in MODES:
        raise ValueError(f"recovery.search_worker must be one of {', '.join(MODES)}, got {choice!r}")
    return (THREAD if live else INLINE) if choice == AUTO else choice


@dataclass
class SearchJob:
    """One search's inputs, copied at the frame it was asked on: the images, the camera pose, the last
    ok pose, the track's poses, the incumbent (the track's estimate then) and the frame's stamp."""

    depth_small: np.ndarray
    depth_m: np.ndarray
    T_base_camera: np.ndarray
    T_base_bone_ok: np.ndarray
    track: list
    incumbent: np.ndarray | None
    stamp: float


@dataclass
class DetectJob:
    """A start's detection (app/tracking/start.py): the images, the camera pose, the point (or None:
    the whole image) and the frame's stamp, copied at the frame it was asked on."""

    depth_small: np.ndarray
    depth_m: np.ndarray
    T_base_camera: np.ndarray
    point: np.ndarray | None
    stamp: float
    start: object = None    # the detector's StartSearch (app/tracking/detector.py; None: its defaults)


@dataclass
class SearchOutcome:
    """The wide search's result with its cost: wall and CPU seconds on the worker's thread."""

    result: object
    wall_s: float
    cpu_s: float


class SearchWorker:
    """One search at a time on a worker thread, or in a worker process (``process``).

    Parameters
    ----------
    build : () -> WideSearch, called once on the worker's thread or in the worker process (its own backend
        and refiner); picklable with ``process`` (a module-level function, or a partial of one)
    rng : the worker's generator (with ``process`` a copy goes to the child, which draws from it)
    process : run the searches in a spawned child process (module docstring) instead of a thread
    """

    def __init__(self, build: Callable[[], object], rng: np.random.Generator, process: bool = False):
        self._build, self.rng, self.process = build, rng, process
        self._search = None
        if process:
            self._executor = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=_child_init, initargs=(build, rng, SEARCH_NICE))
        else:
            shorten_gil_switch()
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="osteonav-search")
        self._future: Future | None = None
        self.job: SearchJob | None = None
        self.failed = False                                 # a search raised: inline from then on (safe)

    @property
    def in_flight(self) -> bool:
        """A search was handed over and its outcome not taken yet."""
        return self._future is not None

    def ready(self) -> bool:
        """The search in flight has finished (its outcome can be taken)."""
        return self._future is not None and self._future.done()

    def safe(self) -> bool:
        """Whether the worker may take a search: it has not failed (a search that raised, e.g. its own
        backend could not be made on its thread), and two threads may run numba's parallel kernels at
        once (not under its ``workqueue`` threading layer: numba aborts the process). Otherwise the
        recovery and the start search inline, as in a replay."""
        if self.failed:
            return False
        if self.process:                                    # its own process: its own threading layer
            return True
        import numba

        try:
            return numba.threading_layer() != "workqueue"
        except ValueError:                                  # no parallel kernel ran yet: the layer is not chosen
            return True

    def submit(self, job: SearchJob | DetectJob) -> None:
        """Hand a search over (one at a time)."""
        if self._future is not None:
            raise RuntimeError("a search is already in flight")
        self.job = job
        try:
            self._future = self._executor.submit(_child_run if self.process else self._run, job)
        except Exception as exc:                            # e.g. the child process died: taken as a failed search
            self._future = Future()
            self._future.set_exception(exc)

    def take(self) -> tuple[SearchJob, SearchOutcome | None]:
        """The finished search's job and outcome (None when it raised: logged; it found nothing)."""
        future, job = self._future, self.job
        self._future = self.job = None
        try:
            return job, future.result()
        except Exception:                                   # a failed search must not end the session
            log.exception("the wide search on the worker failed; treated as one that found nothing, and "
                          "the searches run inline from now on")
            self.failed = True
            return job, None

    def _run(self, job: SearchJob | DetectJob) -> SearchOutcome:
        """The job on the worker's thread: the recovery's wide search, or a start's detection (the
        result then is (Detection or None, the detector's (evaluations, refinements)))."""
        self._built()
        return run_job(self._search, self.rng, job)

    def prepare(self) -> None:
        """Build the worker's search now, on its thread, before a search is due (the first search then
        does not pay for it while the frames wait for the GIL); a build that fails is retried by the
        first search, whose failure is then reported (:meth:`take`). A process is started here (its
        imports and numba's cache load then overlap the first frames)."""
        try:
            future = self._executor.submit(_child_prepare if self.process else self._built)
        except Exception:                                   # reported by the first search
            return
        future.add_done_callback(lambda f: f.exception())

    def _built(self) -> None:
        """The worker's search, built once; its numba kernels on one thread (numba's count is per
        thread): the other core stays with the frame loop."""
        if self._search is None:
            one_numba_thread()
            self._search = self._build()

    def close(self) -> None:
        """Wait for a search in flight, release the worker's backend on its own thread (a GL context's),
        and stop the thread."""
        try:
            self._executor.submit(_child_release if self.process else self._release).result()
        except Exception:                                   # a dead child has nothing left to release
            if not self.process:
                raise
        finally:
            self._executor.shutdown(wait=True, cancel_futures=True)

    def _release(self) -> None:
        backend = getattr(self._search, "backend", None)
        if backend is not None and hasattr(backend, "release"):
            backend.release()
        self._search = None


def run_job(search, rng: np.random.Generator, job: SearchJob | DetectJob) -> SearchOutcome:
    """One job with ``search`` and ``rng``: the recovery's wide search, or a start's detection (the result
    then is (Detection or None, the detector's (evaluations, refinements))); its wall and CPU seconds on
    the calling thread."""
    wall0, cpu0 = time.perf_counter(), time.thread_time()
    if isinstance(job, DetectJob):
        from app.tracking.detector import SearchDetector

        detector = SearchDetector(search, rng, job.start)
        found = detector.detect(job.depth_small, job.depth_m, job.T_base_camera, job.point)
        result = (found, detector.last_work)
    else:
        result = search.run(job.depth_small, job.depth_m, job.T_base_camera, job.T_base_bone_ok,
                            job.track, rng, incumbent=job.incumbent)
    return SearchOutcome(result, time.perf_counter() - wall0, time.thread_time() - cpu0)


# -- the worker process's side (``process``): its search and generator, built once --------------------
_CHILD: dict = {}


def _child_init(build: Callable[[], object], rng: np.random.Generator, nice: int) -> None:
    """The child's start: lower its priority (``nice``), one numba thread, remember how to build."""
    try:
        os.nice(nice)
    except (AttributeError, OSError):                       # not on this platform: the same priority
        pass
    one_numba_thread()
    _CHILD.update(build=build, rng=rng, search=None)


def _child_built():
    if _CHILD["search"] is None:
        _CHILD["search"] = _CHILD["build"]()
    return _CHILD["search"]


def _child_prepare() -> None:
    _child_built()                                          # nothing sent back: the search stays in the child


def _child_run(job: SearchJob | DetectJob) -> SearchOutcome:
    return run_job(_child_built(), _CHILD["rng"], job)


def _child_release() -> None:
    search = _CHILD.get("search")
    backend = getattr(search, "backend", None)
    if backend is not None and hasattr(backend, "release"):
        backend.release()
    _CHILD["search"] = None


def shorten_gil_switch() -> None:
    """Hand the GIL over every ``SWITCH_INTERVAL_S`` (never lengthen a shorter interval): a thread back
    from a GIL-free kernel waits less for the other (this worker, app/pipeline/stages.py's)."""
    if sys.getswitchinterval() > SWITCH_INTERVAL_S:
        sys.setswitchinterval(SWITCH_INTERVAL_S)


def one_numba_thread() -> None:
    """The calling thread's numba kernels on one thread (numba's count is per thread): a worker's
    parallel kernel would otherwise take the frame loop's cores."""
    import numba

    numba.set_num_threads(1)
