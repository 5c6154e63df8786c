"""A knocked-off track whose wide search the test holds on the search worker, shared by
tests/test_recovery.py (the worker thread) and tests/test_search_process.py (the worker process).

:func:`knock` turns the whole track off the bone; :class:`HeldSearch` is the worker's own search, each
run held until an event is set; :func:`track_held_search` tracks a simulated trial, knocks the track
off, counts the frames processed while the search is held, releases it and records which frame took
its result and when the bone was found again; :func:`assert_found_after_the_hold` checks what both
tests expect of that run. No wall time: the held search waits for an event the
loop sets after counting frames, and the loop then waits for the worker's future.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app import metrics
from app.geometry import se3

KNOCK_RAD = np.array([0.0, 0.0, np.pi / 2])   # a quarter turn about the bone's centroid (base frame)


def knock(tracker, T_base_bone: np.ndarray, rotvec: np.ndarray = KNOCK_RAD, shift_m: np.ndarray | None = None) -> None:
    """Turn the whole track by ``rotvec`` about the bone's centroid (base frame), then shift it by
    ``shift_m`` (m, base frame): the cloud, the refinement's track and its static-bone prior's anchor.
    Knocking only the first two tests nothing since the prior (app/filter/static_prior.py): its anchor
    pulled the refined track back to the truth on the next frame (0.2 mm on crest_left_02)."""
    centre = se3.transform_points(T_base_bone, tracker.mesh_vertices.mean(axis=0)[None])[0]
    turn = se3.from_rotvec_trans(rotvec, centre - se3.from_rotvec_trans(rotvec, np.zeros(3))[:3, :3] @ centre)
    T_off = turn @ T_base_bone
    if shift_m is not None:
        T_off[:3, 3] += shift_m
    tracker.filter.shift_to(T_off, T_base_bone)
    track = tracker.refined_track
    if track is not None and track.T_base_bone is not None:
        track.T_base_bone = T_off
        if track.prior is not None and track.prior.active:
            track.prior.T_base_bone = T_off.copy()


class HeldSearch:
    """The worker's real search (``build()``, on the worker's thread or in its process), each run held
    until ``release`` (a threading or multiprocessing Event) is set."""

    def __init__(self, release, build):
        self.release, self.search = release, build()
        self.backend = self.search.backend

    def run(self, *args, **kw):
        self.release.wait()
        return self.search.run(*args, **kw)


@dataclass
class HeldRun:
    """What :func:`track_held_search` saw: ``held`` the (state, status) of each frame processed while the
    search was held; ``taken`` the first result after it (the frame that took the search's result);
    ``found`` s from the trial's start, the first frame from ``taken`` on within 2 mm ADD (None if none)."""

    held: list[tuple[str, str]]
    taken: object | None
    found: float | None


def track_held_search(tracker, reader, points: np.ndarray, release, held_frames: int, every: int,
                      knock_s: float) -> HeldRun:
    """Track ``reader``'s trial with the started ``tracker`` on every ``every``-th frame, knocked off
    (:func:`knock`) at ``knock_s`` s; the worker's search (a :class:`HeldSearch` waiting on ``release``)
    is released after ``held_frames`` frames processed while it searched, and the loop waits for it to
    finish, so the next frame takes its result. Asserts on every frame that none is ok more than 5 mm
    off (ADD over ``points``, (N, 3) m, the mesh's vertices), and while the search is held that the worker
    has no result (the frames did not wait for it). The tracker is released (and ``release`` set) on return."""
    runner = tracker.recovery_runner
    worker = runner.worker
    T_base_camera, valid = reader.camera_poses()
    held, taken, found, results, knocked = [], None, None, [], False
    try:
        for frame in reader.iter_frames():
            i = frame.index
            if i % every:
                continue
            t = frame.stamp - reader.stamps[0]
            if t >= knock_s and not knocked:
                knock(tracker, results[-1].T_base_bone)
                knocked = True
            result = tracker.process(frame.depth_m, frame.stamp, T_base_camera[i] if valid[i] else None)
            add = 1e3 * metrics.add(result.T_base_bone, reader.groundtruth[i], points)
            results.append(result)
            assert not (result.status == "ok" and add > 5.0)
            if runner.searching and taken is None:
                assert not worker.ready()                       # held on the worker: the frames did not wait
                held.append((result.state, result.status))
                if len(held) == held_frames:
                    release.set()
                    worker._future.result()                     # the worker finishes; the next frame takes it
            elif held and taken is None:
                taken = result
            if taken is not None and found is None and add < 2.0:
                found = t
    finally:
        release.set()
        tracker.release()
    return HeldRun(held, taken, found)


def assert_found_after_the_hold(run: HeldRun, tracker, held_frames: int, knock_s: float) -> dict:
    """The frames went on while the search was held (at least ``held_frames`` of them, each searching and
    not ok), the first frame after it took its result (a re-initialisation, confirming), and the bone was
    found again within 2 s of the knock at ``knock_s``, by a wide search. Returns the tracker's recovery
    report for the caller's own checks."""
    assert len(run.held) >= held_frames and all(state == "searching" and status != "ok" for state, status in run.held)
    assert run.taken is not None and run.taken.reinitialised and run.taken.state == "confirming"
    assert run.found is not None and run.found - knock_s <= 2.0
    report = tracker.report()["recovery"]
    assert report["events"][0]["kind"] == "search" and report["search"]["found"] >= 1
    return report
