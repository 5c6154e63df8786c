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
from app.interfaces import DepthFrame, JointSamples
from app.session import parse_session, run_session
from plugins.trial_player import RecordedCamera
from tests.clocks import ManualClock

W, H = 16, 12
CAMERA = PinholeCamera(np.array([[15.0, 0, 7.5], [0, 15.0, 5.5], [0, 0, 1]]), W, H)
FPS = 90.0
PERIOD = 1 / FPS


class FakePlayback:
    """``n`` frames at ``FPS`` stamped from 100 s, written ``write_ratio`` times faster than real time
    (positions: ns of write time, as :func:`plugins.realsense.write_recording` makes them)."""

    def __init__(self, clock: ManualClock, n: int, read_s, write_ratio: float = 0.07, can_seek: bool = True,
                 sleep=None):
        self.clock, self.n, self.read_s, self.can_seek = clock, n, read_s, can_seek
        self.sleep = sleep or clock.advance     # how a read takes its time on the clock
        self.stamps_ms = 1e5 + 1e3 * np.arange(n) / FPS
        self.positions = (np.arange(n) / FPS * write_ratio * 1e9).astype(np.int64)
        self.next = 0           # the next frame to read
        self.position = 0
        self.reads = 0
        self.seeks: list[int] = []

    # rs.pipeline
    def try_wait_for_frames(self, timeout_ms: int):
        self.sleep(self.read_s(self.reads) if callable(self.read_s) else self.read_s)   # the read, on a busy host
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


# ------------------------------------------------------------------------------------------------
# the session: a tracker four frame periods slow over the recording
# ------------------------------------------------------------------------------------------------
HOME_Q = [0.0, -1.6, 1.6, -1.57, -1.57, 0.0]


class FakeTrial:
    """A trial reader (the player's view of it) of ``n`` frames at ``FPS`` whose depth decode calls ``read``."""

    def __init__(self, n: int, read):
        self.stamps = 100.0 + np.arange(n) / FPS
        self.joint_stamps = self.stamps.copy()
        self.frame_ids = np.arange(n)
        self.read = read

    def read_depth(self, index: int) -> np.ndarray:
        self.read()
        return np.full((H, W), 0.1, np.float32)

    def read_infrared(self, index: int) -> None:
        return None

    def read_color(self, index: int) -> None:
        return None


class SlowTracker:
    """Every frame costs ``work_s`` of the session clock (:meth:`tests.clocks.PacedClock.work`)."""

    description = "slow tracker"

    def __init__(self, clocks, work_s: float):
        self.clocks, self.work_s, self.calls = clocks, work_s, 0

    def start(self, T_base_bone):
        self.T = np.asarray(T_base_bone, float)

    def process(self, frame, T_base_camera):
        self.calls += 1
        self.clocks[-1].work(self.work_s)
        return types.SimpleNamespace(T_base_bone=self.T, status="ok")

    def particle_positions(self):
        return self.T[None, :3, 3]

    def mean_timings_ms(self):
        return {}

    def release(self):
        pass


@pytest.fixture
def bag_session(tmp_path, monkeypatch):
    """Register a ``fakebag`` camera (the RealSense plugin over a :class:`FakePlayback` whose reads take
    ``read_s`` on the session clock) and a ``slow`` tracker; the sessions run on a PacedClock."""
    import plugins.realsense as plugin
    from tests.clocks import paced_sessions

    clocks = paced_sessions(monkeypatch)
    monkeypatch.setattr(plugin, "_rs", lambda: None)
    made: dict = {"cameras": [], "trackers": []}

    class FakeBagCamera(plugin.RealSenseCamera):
        def __init__(self, n: int = 360, read_s: float = 1.5 * PERIOD):
            super().__init__(recording="unused.bag")
            self.n, self.read_s = n, read_s
            made["cameras"].append(self)

        def open(self, clock, event):
            self._bind(clock, event)
            playback = FakePlayback(clock, self.n, self.read_s, sleep=lambda s: clock.wait_until(clock.now() + s,
                                                                                                 self._stop))
            self._pipeline = self._playback = playback
            self._period_s, self.depth_scale, self.camera = PERIOD, 1e-4, CAMERA
            return CAMERA

        def _stop_pipeline(self):
            pass

    class FakeTrialCamera(RecordedCamera):
        """The trial player (``camera: recorded``) over a trial whose frame decodes take ``read_s``."""

        def __init__(self, n: int = 360, read_s: float = 1.5 * PERIOD):
            super().__init__(trial="unused")
            self.n, self.read_s = n, read_s
            made["cameras"].append(self)

        def open(self, clock, event):
            self._bind(clock, event)
            self.reader = FakeTrial(self.n, lambda: clock.wait_until(clock.now() + self.read_s, self._stop))
            return CAMERA

        def session_defaults(self) -> dict:
            return {}

    class HeldRobot:
        """A robot held still whose joints for the next 9 s come at once (it never sleeps on the clock,
        so the camera alone paces the session: the same run on any machine)."""

        kind, name = "robot", "held"

        def __init__(self):
            self.finished = threading.Event()

        def open(self, clock, event):
            self.clock = clock

        def start(self, push):
            stamps = self.clock.now() + np.arange(-0.5, 9.0, 0.02)
            push(JointSamples(stamps, np.tile(HOME_Q, (len(stamps), 1))))

        def stop(self):
            pass

        def session_defaults(self) -> dict:
            return {"robot": {"model": "ur5e"}}

    def tracker_factory(work_s=4 * PERIOD, **_):
        made["trackers"].append(SlowTracker(clocks, work_s))
        return made["trackers"][-1]

    registry.register("camera", "fakebag", FakeBagCamera)
    registry.register("camera", "faketrial", FakeTrialCamera)
    registry.register("robot", "held", HeldRobot)
    registry.register("tracker", "slow", tracker_factory)
    mesh_path = tmp_path / "bone.ply"
    trimesh.creation.box((0.05, 0.02, 0.01)).export(mesh_path)
    yield made, mesh_path
    registry.unregister("camera", "fakebag")
    registry.unregister("camera", "faketrial")
    registry.unregister("robot", "held")
    registry.unregister("tracker", "slow")


@pytest.mark.parametrize("camera_plugin", ["fakebag", "faketrial"])
def test_a_slow_tracker_over_a_recording_keeps_a_flat_latency_and_counts_the_drops(tmp_path, bag_session,
                                                                                   camera_plugin):
    """The issue's bag flow (and the trial player's): reads 1.5 frame periods each (the tracker has
    the CPU), the tracker four periods a frame, over a 4 s recording at 90 Hz. Each processed frame is
    at most two periods old when the tracker starts on it, over the whole recording; every frame the
    tracker did not see is counted, by the camera (stale or never read) or by the tracker's queue.
    Before the fix the bag flow pushed every frame, later and later: 12 s max, the 4 s in 16 s."""
    made, mesh_path = bag_session
    n, work_s = 360, 4 * PERIOD
    config = parse_session({
        "camera": {"plugin": camera_plugin, "params": {"n": n}},
        "robot": {"plugin": "held", "model": "ur5e"},
        "tracker": {"plugin": "slow", "params": {"work_s": work_s}},
        "calibration": {"hand_eye": np.eye(4).tolist()},
        "bone": {"mesh": str(mesh_path), "initial_pose": np.eye(4).tolist()},
        "out": str(tmp_path / "out"),
    }, tmp_path)
    summary = run_session(config).summary
    camera, tracker = made["cameras"][0], made["trackers"][0]

    lat = summary["latency_ms"]
    assert lat["n"] == summary["processed"] == tracker.calls > 0
    # a frame is fresh when pushed (its successor not due), and a newer one comes at most a read and
    # a period later (the read lands within a period of the frame it aimed at): at most a read and
    # two periods old when popped, then the tracker's time; first frame to last
    read_s = camera.read_s
    assert lat["max"] <= 1e3 * (read_s + 2 * PERIOD + work_s) + 1e-6
    assert abs(summary["latency_last_ms"]["p99"] - summary["latency_first_ms"]["p99"]) <= 1e3 * PERIOD
    # the 4 s recording took about 4 s of session time, not n reads' worth (6 s)
    assert summary["seconds"] <= n * PERIOD + 1.0
    # every recorded frame is processed or counted as dropped: by the camera, or in the tracker's queue
    assert summary["frames_skipped_by_camera"] == camera.skipped > 0
    assert camera_plugin != "fakebag" or camera.seeks > 0
    accepted = summary["frames"]["frames_accepted"]
    assert accepted + camera.skipped == n
    assert accepted - summary["processed"] - summary["frames_skipped_by_tracker"] in (0, 1)
