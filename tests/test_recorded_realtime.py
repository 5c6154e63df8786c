"""Recorded sources play in real time and drop, never queue (issue 35, Deliver 4).

The RealSense recording (``camera: realsense`` with ``recording:``, the README's ``bag_replay.yaml``)
reads its frames through the SDK's playback, one after the other. On a busy host (the tracker's
CPU, the GIL) a read can take longer than a frame period; the plugin then skips the stale frames
and seeks the playback forward, so every frame it pushes is the one due now and the whole
recording plays in its own duration. Before, it pushed every frame, each later than the last: the
issue's 6 s bag took 18 s with the latency growing to a 6.8 s median.

Time is a :class:`tests.clocks.ManualClock` that the fake SDK advances per read, so every figure
follows from the counts, not from the machine's load. The SDK is a fake with the playback's
contract (frames in order, positions in the file's write time, ``seek``); the real SDK's reading
is covered by tests/test_plugins_realsense.py.
"""
from __future__ import annotations

import datetime
import threading
import types

import numpy as np
import pytest
import trimesh

from app import plugins_registry as registry
from app.geometry.camera import PinholeCamera
from app.interfaces import DepthFrame
from app.session import parse_session, run_session
from tests.clocks import ManualClock

W, H = 16, 12
CAMERA = PinholeCamera(np.array([[15.0, 0, 7.5], [0, 15.0, 5.5], [0, 0, 1]]), W, H)
FPS = 90.0
PERIOD = 1 / FPS


class FakePlayback:
    """``n`` frames at ``FPS`` stamped from 100 s, written ``write_ratio`` times faster than real time
    (positions: ns of write time, as :func:`plugins.realsense.write_recording` makes them)."""

    def __init__(self, clock: ManualClock, n: int, read_s: float, write_ratio: float = 0.07, can_seek: bool = True):
        self.clock, self.n, self.read_s, self.can_seek = clock, n, read_s, can_seek
        self.stamps_ms = 1e5 + 1e3 * np.arange(n) / FPS
        self.positions = (np.arange(n) / FPS * write_ratio * 1e9).astype(np.int64)
        self.next = 0           # the next frame to read
        self.position = 0
        self.reads = 0
        self.seeks: list[int] = []

    # rs.pipeline
    def try_wait_for_frames(self, timeout_ms: int):
        self.clock.advance(self.read_s(self.reads) if callable(self.read_s) else self.read_s)   # a busy host
        if self.next >= self.n:
            return False, None
        k, self.next = self.next, self.next + 1
        self.position = int(self.positions[k])
        self.reads += 1
        depth = types.SimpleNamespace(get_timestamp=lambda: float(self.stamps_ms[k]), get_frame_number=lambda: k,
                                      get_data=lambda: np.full((H, W), 1000 + k, np.uint16))
        return True, types.SimpleNamespace(get_depth_frame=lambda: depth)

    def stop(self) -> None:
        pass

    # rs.playback
    def get_position(self) -> int:
        return self.position

    def get_duration(self) -> datetime.timedelta:
        return datetime.timedelta(microseconds=int(self.positions[-1]) / 1e3)

    def seek(self, when: datetime.timedelta) -> None:
        if not self.can_seek:
            raise RuntimeError("seek not supported")
        target = int(when.total_seconds() * 1e9)
        self.seeks.append(target)
        self.next = max(self.next, int(np.searchsorted(self.positions, target)))
        self.position = target


def play(monkeypatch, n: int, read_s: float, can_seek: bool = True):
    """Run the RealSense plugin's playback loop over a fake recording; (camera, playback, pushed frames)."""
    import plugins.realsense as plugin

    monkeypatch.setattr(plugin, "_rs", lambda: None)   # the loop needs the SDK only to restart a live device
    clock = ManualClock(lead_in_s=0.0)
    playback = FakePlayback(clock, n, read_s, can_seek=can_seek)
    camera = plugin.RealSenseCamera(recording="unused.bag")
    camera._bind(clock, lambda *a: None)
    camera._pipeline = camera._playback = playback
    camera._period_s, camera.depth_scale = PERIOD, 1e-4
    monkeypatch.setattr(camera, "_stop_pipeline", lambda: None)
    pushed: list[DepthFrame] = []
    camera._push = pushed.append
    camera._run()
    return camera, playback, pushed


def test_a_recording_read_slower_than_its_rate_stays_on_schedule(monkeypatch):
    """Each read costs three frame periods (the tracker has the CPU): the plugin pushes only frames
    that are due now, and the 2 s recording plays in about 2 s instead of 6."""
    n, read_s = 180, 3 * PERIOD
    camera, playback, pushed = play(monkeypatch, n, read_s)
    delay = np.array([f.arrival - f.stamp for f in pushed])
    # never stale: a pushed frame's successor was not due yet, from the first frame to the last
    assert delay.max() < PERIOD
    # the whole recording in its own duration (plus the last reads), not n reads' worth of time
    assert pushed[-1].stamp - pushed[0].stamp >= (n - 1) * PERIOD - 4 * read_s
    assert pushed[-1].arrival - pushed[0].arrival <= (n - 1) * PERIOD + read_s
    # it got there by seeking over frames it never read, and skipping the stale ones it did read
    assert camera.seeks == len(playback.seeks) > 0 and playback.reads < n / 2
    # every frame is pushed or counted as skipped (the summary's frames_skipped_by_camera)
    assert camera.skipped > 0 and len(pushed) + camera.skipped == n
    ids = [f.frame_id for f in pushed]
    assert ids == sorted(set(ids)) and ids[0] == 0
    assert pushed[-1].depth_m[0, 0] == pytest.approx((1000 + ids[-1]) * 1e-4)   # the frame read, converted


def test_a_recording_read_within_its_rate_pushes_every_frame(monkeypatch):
    camera, playback, pushed = play(monkeypatch, 90, read_s=0.3 * PERIOD)
    assert [f.frame_id for f in pushed] == list(range(90))
    assert camera.skipped == camera.seeks == 0
    assert max(f.arrival - f.stamp for f in pushed) < PERIOD


def test_a_playback_that_cannot_seek_skips_stale_frames_only_while_it_reads_faster_than_its_rate(monkeypatch):
    """No seek. Reads at half a period, but the 30th takes ten periods (a hiccup): the frames that
    were due meanwhile are skipped until the reader is back on schedule, then every frame is pushed."""
    camera, playback, pushed = play(monkeypatch, 180, lambda k: 10 * PERIOD if k == 30 else 0.5 * PERIOD,
                                    can_seek=False)
    assert camera.seeks == 0 and playback.reads == 180
    assert 5 <= camera.skipped <= 20 and len(pushed) + camera.skipped == 180
    assert max(f.arrival - f.stamp for f in pushed) < PERIOD
    assert [f.frame_id for f in pushed][-100:] == list(range(80, 180))


def test_a_playback_that_cannot_seek_and_reads_slower_than_its_rate_still_pushes_its_frames(monkeypatch):
    """Skipping without seeking would skip every frame of a reader that cannot keep up: it pushes them
    (each the newest it has), late; only a playback that seeks can keep to the schedule."""
    camera, playback, pushed = play(monkeypatch, 60, read_s=1.5 * PERIOD, can_seek=False)
    assert camera.skipped == 0 and len(pushed) == 60
