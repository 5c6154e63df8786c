"""The wide search in a worker process (``recovery.search_worker: process``, auto in a live session;
app/tracking/search_worker.py): the frames go on while it runs, its result is taken on a later frame,
and a worker process that fails leaves the session searching inline. No wall time: the held search
waits for an event the test sets after counting frames, and the test waits for the worker's future."""
from __future__ import annotations

import multiprocessing
from dataclasses import replace
from functools import partial

import numpy as np
import pytest

from app.config import load_config
from tests.held_search import HeldSearch, assert_found_after_the_hold, track_held_search

EVERY = 3              # every 3rd frame of the 90 Hz trial
KNOCK_S = 1.2          # the track is knocked off here (ok well before)
HELD = 4               # frames processed while the search is held in the child


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    from app.sim.simulator import simulate

    out = tmp_path_factory.mktemp("search_process") / "trial"
    simulate(out, scenario_name="static_clear", seconds=3.4, seed=7)
    return out


def _config(worker: str):
    config = load_config(None)
    return replace(config, recovery=replace(config.recovery, enabled=True, search_worker=worker))


def _broken_build():
    raise RuntimeError("no likelihood backend in this process")


def test_process_is_chosen_by_name_and_auto_stays_a_thread_in_a_live_session(trial):
    from app.pipeline.tracker import DepthTracker
    from app.tracking.search_worker import search_worker_mode
    from app.trial.reader import open_trial

    assert search_worker_mode("auto", True) == "thread" and search_worker_mode("auto", False) == "inline"
    assert search_worker_mode("process", False) == "process"
    with pytest.raises(ValueError):
        search_worker_mode("fork", True)
    reader = open_trial(trial)
    mesh = reader.load_mesh()
    trackers = [DepthTracker(_config("process"), mesh, reader.meta.camera),
                DepthTracker(_config("auto"), mesh, reader.meta.camera, live=True),
                DepthTracker(_config("auto"), mesh, reader.meta.camera)]
    try:
        assert [t.recovery_runner.worker is not None and t.recovery_runner.worker.process for t in trackers] == \
            [True, False, False]
        assert trackers[2].recovery_runner.worker is None
    finally:
        for t in trackers:
            t.release()


def test_a_search_in_the_worker_process_never_stops_the_frames_and_its_result_is_taken_later(trial):
    """The due search goes to the child process; the frames go on, searching and never ok, while the
    child holds it (HELD frames counted); released, its result is taken on the first frame after it
    is ready and finds the knocked-off track again (the child's own search and generator)."""
    from app.pipeline.tracker import DepthTracker
    from app.tracking.search_worker import SearchWorker
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    mesh = reader.load_mesh()
    points = np.asarray(mesh.vertices)
    tracker = DepthTracker(_config("process"), mesh, reader.meta.camera)
    runner = tracker.recovery_runner
    real = runner.worker
    assert real.process and real.safe()
    release = multiprocessing.get_context("spawn").Event()
    runner.worker = SearchWorker(partial(HeldSearch, release, real._build), real.rng, process=True)
    real.close()
    worker = runner.worker
    worker.prepare()
    tracker.start(reader.meta.initial_pose)
    run = track_held_search(tracker, reader, points, release, HELD, EVERY, KNOCK_S)
    report = assert_found_after_the_hold(run, tracker, HELD, KNOCK_S)
    assert report["search"]["cpu_s"] > 0.0                      # the child's CPU seconds came back with it


def test_a_worker_process_that_fails_counts_as_nothing_found_and_the_searches_go_inline(trial):
    """The child cannot build its search: the first search handed over raises there, is logged and
    counts as one that found nothing; the worker is marked failed and later searches run inline."""
    from app.pipeline.tracker import DepthTracker
    from app.tracking.search_worker import SearchWorker
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    tracker = DepthTracker(_config("process"), reader.load_mesh(), reader.meta.camera)
    runner = tracker.recovery_runner
    runner.worker.close()
    worker = runner.worker = SearchWorker(_broken_build, np.random.default_rng(0), process=True)
    tracker.start(reader.meta.initial_pose)
    T_base_camera, valid = reader.camera_poses()
    frames = [f for f in reader.iter_frames() if f.index % EVERY == 0][:3]
    try:
        tracker.recovery.pending = "a test"
        tracker.process(frames[0].depth_m, frames[0].stamp, T_base_camera[frames[0].index])
        assert worker.in_flight
        worker._future.exception()                              # the child's search has raised
        tracker.process(frames[1].depth_m, frames[1].stamp, T_base_camera[frames[1].index])
        assert worker.failed and not worker.in_flight and runner.work["searches"] == 1
        tracker.recovery.pending = "another test"
        tracker.process(frames[2].depth_m, frames[2].stamp, T_base_camera[frames[2].index])
        assert not worker.in_flight and runner.work["searches"] == 2    # inline, on this frame
    finally:
        tracker.release()
