"""Recorded sources play in real time and drop, never queue (issue 35, Deliver 4).

The RealSense recording (``camera: realsense`` with ``recording:``, the README's ``bag_replay.yaml``)
reads its frames through the SDK's playback, one after the other, and pushes each to the bus from
its own thread: converted to metres, validated, handed to the sinks (the recorder, rerun). On a busy
host that push can take longer than a frame period. Before, the plugin pushed every frame, each
later than the last: the issue's 6 s bag took 18 s with the latency growing to a 6.8 s median.
Now a frame read after its successor was due is skipped (a read, no push), so the reader catches up
and every frame it pushes is the one due now. The trial player (``camera: recorded``) decodes the
frame that will be due once decoded.

Time is a :class:`tests.clocks.ManualClock` (the plugin alone) or a :class:`tests.clocks.PacedClock`
(the session, with a slow tracker), so every figure follows from the counts, not from the machine's
load. The SDK is a fake with the playback's contract (frames in order); the real SDK's reading is
covered by tests/test_plugins_realsense.py.
"""
from __future__ import annotations

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
    """The SDK pipeline over a recording of ``n`` frames at ``FPS`` stamped from 100 s; each read takes
    ``read_s`` (or ``read_s(k)`` for the k-th read) on the clock, through ``sleep``."""

    def __init__(self, clock: ManualClock, n: int, read_s, sleep=None):
        self.clock, self.n, self.read_s = clock, n, read_s
        self.sleep = sleep or clock.advance
        self.stamps_ms = 1e5 + 1e3 * np.arange(n) / FPS
        self.reads = 0

    def try_wait_for_frames(self, timeout_ms: int):
        self.sleep(self.read_s(self.reads) if callable(self.read_s) else self.read_s)
        if self.reads >= self.n:
            return False, None
        k, self.reads = self.reads, self.reads + 1
        depth = types.SimpleNamespace(get_timestamp=lambda: float(self.stamps_ms[k]), get_frame_number=lambda: k,
                                      get_data=lambda: np.full((H, W), 1000 + k, np.uint16))
        return True, types.SimpleNamespace(get_depth_frame=lambda: depth)

    def stop(self) -> None:
        pass


def play(monkeypatch, n: int, read_s, push_s: float = 0.0):
    """Run the RealSense plugin's playback loop over a fake recording whose reads take ``read_s`` and
    whose pushes (conversion, the bus, the sinks) take ``push_s``; (camera, playback, pushed frames)."""
    import plugins.realsense as plugin

    monkeypatch.setattr(plugin, "_rs", lambda: None)   # the loop needs the SDK only to restart a live device
    clock = ManualClock(lead_in_s=0.0)
    playback = FakePlayback(clock, n, read_s)
    camera = plugin.RealSenseCamera(recording="unused.bag")
    camera._bind(clock, lambda *a: None)
    camera._pipeline, camera.depth_scale = playback, 1e-4
    monkeypatch.setattr(camera, "_stop_pipeline", lambda: None)
    pushed: list[DepthFrame] = []

    def push(frame):
        pushed.append(frame)
        clock.advance(push_s)

    camera._push = push
    camera._run()
    return camera, playback, pushed


def test_a_recording_whose_pushes_take_longer_than_its_rate_stays_on_schedule(monkeypatch):
    """Reads take 0.3 frame periods, pushes 2.5 (the sinks of a loaded host): the plugin skips the
    frames that went stale meanwhile and the 2 s recording plays in 2 s, never more than a period
    late; before, it pushed all 180, the last 2.8 s late (the 2 s in 5.1 s)."""
    n = 180
    camera, playback, pushed = play(monkeypatch, n, read_s=0.3 * PERIOD, push_s=2.5 * PERIOD)
    delay = np.array([f.arrival - f.stamp for f in pushed])
    assert delay.max() < PERIOD                                   # never stale, first frame to last
    assert pushed[-1].stamp - pushed[0].stamp >= (n - 4) * PERIOD     # to the end of the recording
    assert playback.reads == n and len(pushed) + camera.skipped == n  # every frame pushed or counted
    assert n / 4 <= len(pushed) <= n / 2
    ids = [f.frame_id for f in pushed]
    assert ids == sorted(set(ids)) and ids[0] == 0
    assert pushed[-1].depth_m[0, 0] == pytest.approx((1000 + ids[-1]) * 1e-4)   # the frame read, converted


def test_a_recording_read_within_its_rate_pushes_every_frame(monkeypatch):
    camera, playback, pushed = play(monkeypatch, 90, read_s=0.3 * PERIOD, push_s=0.3 * PERIOD)
    assert [f.frame_id for f in pushed] == list(range(90))
    assert camera.skipped == 0
    assert max(f.arrival - f.stamp for f in pushed) < PERIOD


def test_after_a_hiccup_the_reader_skips_the_stale_frames_and_is_back_on_schedule(monkeypatch):
    """Reads at half a period, but the 30th takes ten periods: the frames due meanwhile are skipped
    until the reader is back on schedule, then every frame is pushed."""
    camera, playback, pushed = play(monkeypatch, 180, lambda k: 10 * PERIOD if k == 30 else 0.5 * PERIOD)
    assert playback.reads == 180
    assert 5 <= camera.skipped <= 20 and len(pushed) + camera.skipped == 180
    assert max(f.arrival - f.stamp for f in pushed) < PERIOD
    assert [f.frame_id for f in pushed][-100:] == list(range(80, 180))


def test_a_reader_slower_than_its_rate_still_pushes_its_frames(monkeypatch):
    """Skipping would skip every frame of a reader that cannot keep up: it pushes them (each the
    newest it has), late; nothing faster is possible without reading fewer frames."""
    camera, playback, pushed = play(monkeypatch, 60, read_s=1.5 * PERIOD)
    assert camera.skipped == 0 and len(pushed) == 60


def test_the_trial_player_decodes_the_frame_due_once_decoded(monkeypatch):
    """Decodes take three frame periods: the player decodes the frame that will be due when the decode
    ends, so it pushes it within its period (before: the frame due when the decode began, pushed four
    periods after its stamp)."""
    clock = ManualClock(lead_in_s=0.0)
    camera = RecordedCamera("unused")
    camera._bind(clock, lambda *a: None)
    camera.reader = FakeTrial(180, lambda: clock.advance(3 * PERIOD))
    pushed: list[DepthFrame] = []
    camera._push = pushed.append
    camera._run()
    delay = np.array([f.arrival - f.stamp for f in pushed])
    assert delay[2:].max() <= PERIOD + 1e-9    # after two decodes timed, each frame pushed within its period
    assert delay.max() <= 3 * PERIOD + 1e-9    # the second: decoded before a decode's time was known
    assert camera.pushed + camera.skipped == 180 and 50 <= camera.pushed <= 65


def test_the_trial_player_never_pushes_a_frame_the_host_overslept(monkeypatch):
    """Decodes take 0.2 periods; the 20th sleep wakes 2.5 periods late (a busy host): the player
    decodes the frame due then instead of pushing the one it slept for; every frame pushed within its
    period, the ones passed over counted (as before this change: a guard for it)."""
    class LateClock(ManualClock):
        sleeps = 0

        def wait_until(self, t, stop):
            self.sleeps += 1
            return super().wait_until(t + (2.5 * PERIOD if self.sleeps == 20 else 0.0), stop)

    clock = LateClock(lead_in_s=0.0)
    camera = RecordedCamera("unused")
    camera._bind(clock, lambda *a: None)
    camera.reader = FakeTrial(90, lambda: clock.advance(0.2 * PERIOD))
    pushed: list[DepthFrame] = []
    camera._push = pushed.append
    camera._run()
    assert max(f.arrival - f.stamp for f in pushed) < PERIOD
    assert camera.skipped == 2 and camera.pushed == 88 and len(pushed) == 88   # the two due at the wake-up


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
    """Register the ``fakebag`` and ``faketrial`` cameras, a ``held`` robot and a ``slow`` tracker;
    the sessions run on a :class:`tests.clocks.PacedClock`."""
    import plugins.realsense as plugin
    from tests.clocks import paced_sessions

    clocks = paced_sessions(monkeypatch)
    monkeypatch.setattr(plugin, "_rs", lambda: None)
    made: dict = {"cameras": [], "trackers": []}

    class FakeBagCamera(plugin.RealSenseCamera):
        """The RealSense plugin over a :class:`FakePlayback` whose reads take ``read_s`` and whose
        pushes (conversion, the bus's checks, the sinks) take ``push_s`` on the session clock."""

        def __init__(self, n: int = 360, read_s: float = 0.3 * PERIOD, push_s: float = 2.5 * PERIOD):
            super().__init__(recording="unused.bag")
            self.n, self.read_s, self.push_s = n, read_s, push_s
            made["cameras"].append(self)

        def open(self, clock, event):
            self._bind(clock, event)
            self._pipeline = FakePlayback(clock, self.n, self.read_s, sleep=self._take)
            self.depth_scale, self.camera = 1e-4, CAMERA
            return CAMERA

        def _take(self, seconds: float) -> None:
            self.clock.wait_until(self.clock.now() + seconds, self._stop)

        def start(self, push):
            super().start(lambda frame: (self._take(self.push_s), push(frame)))

        def _stop_pipeline(self):
            pass

    class FakeTrialCamera(RecordedCamera):
        """The trial player (``camera: recorded``) over a trial whose frame decodes take ``read_s``."""

        def __init__(self, n: int = 360, read_s: float = 1.5 * PERIOD):
            super().__init__(trial="unused")
            self.n, self.read_s, self.push_s = n, read_s, 0.0
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
    """The issue's bag flow, and the trial player's: the tracker takes four frame periods a frame over a
    4 s recording at 90 Hz; the RealSense reader's pushes take 2.5 periods (its sinks, on a loaded
    host), the trial player's decodes 1.5. Each processed frame is at most the camera's own work on it
    and two periods old when the tracker starts on it, over the whole recording; every frame the
    tracker did not see is counted, by the camera (stale) or by the tracker's queue. Before, the bag
    flow pushed every frame, later and later (the trial player pushed frames stale after decoding)."""
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
    # a frame is fresh when the camera takes it (its successor not due), then the camera works on it
    # (decode, push): it is queued at most a period and that work old, and the next one is queued at
    # most a period and that work later. So the tracker starts on frames at most twice (work +
    # period) old, then works: first frame to last (before, the bag flow's grew to seconds)
    camera_s = camera.read_s + camera.push_s
    assert lat["max"] <= 1e3 * (2 * (camera_s + PERIOD) + work_s) + 1e-6
    # the 4 s recording took about 4 s of session time, not n frames' worth of the camera's work
    assert summary["seconds"] <= n * PERIOD + 1.0
    # every recorded frame is processed or counted as dropped: by the camera, or in the tracker's queue
    assert summary["frames_skipped_by_camera"] == camera.skipped > 0
    accepted = summary["frames"]["frames_accepted"]
    assert accepted + camera.skipped == n
    assert accepted - summary["processed"] - summary["frames_skipped_by_tracker"] in (0, 1)


def test_a_looped_trials_frame_ids_run_on_across_laps():
    """A looped recorded camera's ids continue from lap to lap (last + 1), keeping the trial's own gaps: the
    recorder counts an id jump as frames the camera dropped (it was + 10,000,000 a lap, ~390 million "dropped")."""
    from plugins.trial_player import lap_frame_id

    ids = [3, 4, 6, 7]                                    # one frame (5) missing in the trial itself
    laps = [lap_frame_id(ids, j, lap) for lap in range(3) for j in range(len(ids))]
    assert laps == [3, 4, 6, 7, 8, 9, 11, 12, 13, 14, 16, 17]
    gaps = sum(b - a - 1 for a, b in zip(laps, laps[1:]))
    assert gaps == 3                                      # the trial's own gap, once a lap, and nothing more
