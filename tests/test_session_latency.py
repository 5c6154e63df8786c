"""Live latency: the loop always processes the newest frame, however slow the tracker or the host.

Time is a manual clock (:class:`ManualClock`): it moves only when a test's fake tracker or a
player's frame decode "works", so every figure below follows from the counts, never from how
loaded the machine running the tests is.
"""
from __future__ import annotations

import threading

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
HOME_Q = [0.0, -1.6, 1.6, -1.57, -1.57, 0.0]


# ------------------------------------------------------------------------------------------------
# the trial player never delivers stale frames
# ------------------------------------------------------------------------------------------------
class SlowReader:
    """A 1 s trial at 90 Hz whose every frame decode costs ``decode_s`` of the session clock."""

    def __init__(self, clock: ManualClock, decode_s: float, fps: float = 90.0, n: int = 90):
        self.clock, self.decode_s = clock, decode_s
        self.stamps = 50.0 + np.arange(n) / fps
        self.joint_stamps = self.stamps.copy()
        self.frame_ids = np.arange(n)
        self.decoded = 0

    def read_depth(self, index: int) -> np.ndarray:
        self.clock.advance(self.decode_s)
        self.decoded += 1
        return np.ones((H, W), np.float32)

    def read_infrared(self, index: int) -> None:   # a depth-only trial (TrialReader's contract)
        return None

    def read_color(self, index: int) -> None:
        return None


def test_a_player_behind_its_schedule_skips_to_the_newest_due_frame_on_the_session_clock():
    fps, decode_s = 90.0, 3 / 90.0           # the host needs three frame periods per frame
    clock = ManualClock()
    camera = RecordedCamera("unused")
    camera._bind(clock, lambda *a: None)
    camera.reader = SlowReader(clock, decode_s, fps)
    clock.advance(30.0)                       # opening took 30 s (a simulated trial is simulated first)
    pushed: list[DepthFrame] = []
    camera._push = pushed.append
    t_start = clock.now()
    camera._run()

    stamps = np.array([f.stamp for f in pushed])
    delay = np.array([f.arrival - f.stamp for f in pushed])
    # stamps on the session clock: the first frame is due lead_in after the player started, not
    # 30 s in the past (the replay anchor is the first stamp's mapping, not the clock's creation)
    assert t_start <= stamps[0] <= t_start + clock.lead_in_s + 1e-9
    # a frame is chosen less than one period after it was due (the next one was not due yet) and
    # then decoded: arrival - stamp <= 1/fps + decode_s, for every frame, first to last
    assert delay.max() <= 1 / fps + decode_s + 1e-9
    # the player kept up by skipping: each decode spans three periods, so about two of three skip
    assert camera.pushed + camera.skipped == 90 and camera.reader.decoded >= camera.pushed
    assert 25 <= camera.pushed <= 35
    assert np.all(np.diff(stamps) > 0)


def test_a_player_that_keeps_up_pushes_every_frame():
    clock = ManualClock()
    camera = RecordedCamera("unused")
    camera._bind(clock, lambda *a: None)
    camera.reader = SlowReader(clock, decode_s=0.2 / 90.0)   # decode well inside one period
    pushed: list[DepthFrame] = []
    camera._push = pushed.append
    camera._run()
    assert camera.skipped == 0 and len(pushed) == 90
    assert max(f.arrival - f.stamp for f in pushed) == 0.0   # each decoded ahead of its time


# ------------------------------------------------------------------------------------------------
# the loop: a 30 s session with a tracker three frame periods slow
# ------------------------------------------------------------------------------------------------
class World:
    """A 30 Hz camera and a 500 Hz robot that deliver everything due on the clock; a frame arrives
    ``transfer_s`` after its capture (by then the joints around its stamp are in)."""

    def __init__(self, clock: ManualClock, fps: float = 30.0, joint_hz: float = 500.0, transfer_s: float = 0.005):
        self.clock, self.fps, self.joint_hz, self.transfer_s = clock, fps, joint_hz, transfer_s
        self.push_frame = self.push_joints = None
        self.next_frame = self.next_joint = None
        self.frames = 0

    def emit_due(self) -> None:
        now = self.clock.now()
        if self.push_joints is not None:
            stamps = []
            while self.next_joint <= now:
                stamps.append(self.next_joint)
                self.next_joint += 1 / self.joint_hz
            if stamps:
                self.push_joints(JointSamples(np.array(stamps), np.tile(HOME_Q, (len(stamps), 1))))
        if self.push_frame is not None:
            while self.next_frame + self.transfer_s <= now:
                self.push_frame(DepthFrame(self.frames, self.next_frame, np.ones((H, W), np.float32),
                                           self.next_frame + self.transfer_s))
                self.frames += 1
                self.next_frame += 1 / self.fps


class TickSource:
    def __init__(self, world: World, kind: str):
        self.world, self.kind, self.name = world, kind, "tick"
        self.finished = threading.Event()

    def open(self, clock, event):
        return CAMERA if self.kind == "camera" else None

    def start(self, push) -> None:
        if self.kind == "camera":
            self.world.push_frame, self.world.next_frame = push, self.world.clock.now() - self.world.transfer_s
        else:
            self.world.push_joints, self.world.next_joint = push, self.world.clock.now() - 0.01
        self.world.emit_due()

    def stop(self) -> None:
        pass

    def session_defaults(self) -> dict:
        return {"robot": {"model": "ur5e"}}


class SlowTracker:
    """Every frame costs ``work_s`` of the clock, during which the sources keep delivering."""

    def __init__(self, world: World, work_s: float):
        self.world, self.work_s, self.calls = world, work_s, 0

    def start(self, T_base_bone):
        self.T = np.asarray(T_base_bone, float)

    description = "slow tracker"

    def process(self, frame, T_base_camera):
        self.calls += 1
        self.world.clock.advance(self.work_s)
        self.world.emit_due()
        return type("Result", (), {"T_base_bone": self.T, "status": "ok"})()

    def particle_positions(self):
        return self.T[None, :3, 3]

    def mean_timings_ms(self):
        return {}

    def release(self):
        pass


@pytest.fixture
def slow_world(tmp_path):
    clock = ManualClock()
    world = World(clock)
    trackers: list[SlowTracker] = []

    def tracker_factory(work_s=0.1, **_):
        trackers.append(SlowTracker(world, work_s))
        return trackers[-1]

    registry.register("camera", "tick", lambda **kw: TickSource(world, "camera"))
    registry.register("robot", "tick", lambda **kw: TickSource(world, "robot"))
    registry.register("tracker", "slow", tracker_factory)
    mesh_path = tmp_path / "bone.ply"
    trimesh.creation.box((0.05, 0.02, 0.01)).export(mesh_path)
    yield clock, world, trackers, mesh_path
    for kind, name in (("camera", "tick"), ("robot", "tick"), ("tracker", "slow")):
        registry.unregister(kind, name)


def test_latency_stays_flat_and_near_one_tracker_step_over_a_30_s_session(tmp_path, slow_world):
    clock, world, trackers, mesh_path = slow_world
    work_s, seconds = 0.1, 30.0
    config = parse_session({
        "camera": {"plugin": "tick"}, "robot": {"plugin": "tick", "model": "ur5e"},
        "tracker": {"plugin": "slow", "params": {"work_s": work_s}},
        "calibration": {"hand_eye": np.eye(4).tolist()},
        "bone": {"mesh": str(mesh_path), "initial_pose": np.eye(4).tolist()},
        "out": str(tmp_path / "out"), "loop": {"duration_s": seconds},
    }, tmp_path)
    summary = run_session(config, clock=clock).summary

    lat = summary["latency_ms"]
    # the newest frame is never older than one camera period plus its transfer when popped, then
    # the tracker works: latency <= work_s + 1/fps + transfer_s = 138 ms, under 2 x work_s = 200 ms
    assert lat["p99"] <= 1e3 * (work_s + 1 / world.fps + world.transfer_s) + 1e-6 < 2e3 * work_s
    assert lat["median"] >= 1e3 * work_s
    # flat: the last ten seconds are no worse than the first ten (within one camera period)
    assert abs(summary["latency_last_ms"]["p99"] - summary["latency_first_ms"]["p99"]) <= 1e3 / world.fps
    stages = summary["latency_stages_ms"]
    assert stages["capture_to_arrival"]["max"] == pytest.approx(1e3 * world.transfer_s)
    assert stages["queue_wait"]["max"] <= 1e3 / world.fps + 1e-6
    # every frame had its camera pose: the robot's joints covered its stamp when it arrived
    assert summary["status_counts"] == {"ok": trackers[0].calls}
    assert stages["tracker"]["median"] == pytest.approx(1e3 * work_s, abs=1e-6)
    # one estimate per tracker step; every other frame dropped in the queue, and counted
    processed = trackers[0].calls
    assert summary["processed"] == processed == lat["n"]
    assert abs(processed - seconds / work_s) <= 2
    accepted = summary["frames"]["frames_accepted"]
    assert accepted == world.frames
    # the rate: one estimate per work_s, steady from the first ten seconds to the last
    assert summary["rate_hz"]["all"] == pytest.approx(1 / work_s)
    assert summary["rate_hz"]["first"] == pytest.approx(1 / work_s, abs=0.2)
    assert summary["rate_hz"]["last"] == pytest.approx(1 / work_s, abs=0.2)
    assert summary["rss_mb"]["start"] > 0 and summary["rss_mb"]["end"] > 0
    # every accepted frame was processed, dropped for a newer one, or still queued at the end (<= 2)
    assert 0 <= accepted - processed - summary["frames_skipped_by_tracker"] <= 2


def test_replay_anchor_is_fixed_by_the_first_mapping_and_scaled_by_the_replay_rate():
    """host = anchor + (t - origin) / rate, anchor = the clock at the first mapping + lead_in: two
    sources mapping the same recorded time get the same host time, whatever their own origin."""
    clock = ManualClock(start=10.0, lead_in_s=0.2)
    clock.replay_rate = 0.5
    clock.advance(30.0)                                          # the sources took 30 s to open
    assert clock.replay_to_host(100.0, 100.0) == pytest.approx(40.2)
    clock.advance(5.0)
    assert clock.replay_to_host(101.0, 99.0) == pytest.approx(42.2)   # origin kept: 1 s recorded = 2 s host
