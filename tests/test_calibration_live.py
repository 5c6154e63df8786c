"""Live hand-eye capture (calibration/live.py, live_session.py): rest detection from joint samples, the
corners-still check, one capture per rest, the conditioning warnings; and end to end, a RealSense
recording with IR (written by the SDK's software device) + the RTDE test server through
``calibrate capture``, from which ``calibrate hand-eye`` recovers the true T_flange_camera."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.board import BoardDetector
from calibration.captures import CaptureWriter, read_captures
from calibration.live import CaptureRules, JointHistory, LiveCapturer, corners_still, rest_pose
from calibration.live_sim import RestMoveTrajectory
from calibration.simulator import BoardRenderer, SimulationConfig, make_scene, plan_captures

RATE = 500.0


def test_rest_needs_the_whole_window_still_and_sampled():
    t = np.arange(0, 2.0, 1 / RATE)
    q = np.zeros((len(t), 6))
    q[t < 1.0, 0] = 0.1 * (1.0 - t[t < 1.0])     # moving until 1.0 s, then still
    q += np.random.default_rng(0).normal(0, 3e-5, q.shape)   # encoder noise
    assert rest_pose(t, q, 1.4, 0.5, 2e-4) is None            # window reaches into the motion
    q_rest = rest_pose(t, q, 1.6, 0.5, 2e-4)
    assert q_rest is not None and np.abs(q_rest).max() < 2e-5  # the mean of the window
    assert rest_pose(t[t > 1.3], q[t > 1.3], 1.6, 0.5, 2e-4) is None     # samples do not span 0.5 s
    gap = (t < 1.5) | (t > 1.6)
    assert rest_pose(t[gap], q[gap], 1.9, 0.5, 2e-4) is None  # a 100 ms hole in the samples
    creep = q.copy()
    creep[:, 2] += 1e-3 * t                                    # 1 mrad/s creep: 0.5 mrad over the window
    assert rest_pose(t, creep, 1.9, 0.5, 2e-4) is None


class _FrameFeeder:
    """The calibration simulator's board images at a trajectory's stamps, with its joints in a JointHistory."""

    def __init__(self, n=6, seed=1, full_size=False, rest_s=1.0):
        K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1.0]])
        size = dict(width=320, height=240, K=K)
        if full_size:   # the D415's left imager at 640x480
            size = dict(width=640, height=480, K=np.array([[612.4, 0.0, 318.9], [0.0, 612.0, 241.3], [0.0, 0.0, 1.0]]))
        self.scene = make_scene(SimulationConfig(**size))
        self.traj = RestMoveTrajectory(plan_captures(self.scene, n, np.random.default_rng(seed)), rest_s=rest_s, move_s=0.5)
        self.renderer = BoardRenderer(self.scene.config)


def test_one_capture_per_rest_with_the_rest_pose_and_warnings_until_well_posed(tmp_path):
    from app.geometry.ur import UR_MODELS, forward_kinematics

    feed = _FrameFeeder()
    joints = JointHistory()
    t = np.arange(0, feed.traj.duration, 1 / RATE)
    joints.add(t, np.stack([feed.traj.at(s) for s in t]))
    messages = []
    with CaptureWriter(tmp_path / "cap") as writer:
        capturer = LiveCapturer(BoardDetector(feed.scene.config.board), writer, joints,
                                lambda q: forward_kinematics(UR_MODELS["ur5e"], q), CaptureRules(count=10))
        for s in np.arange(0.0, feed.traj.duration - 0.01, 1 / 15):
            image = feed.renderer.render(feed.scene.T_camera_board(feed.traj.at(s)))
            messages.append(capturer.on_frame(float(s), image))
    captures = read_captures(tmp_path / "cap").captures
    assert len(captures) == len(feed.traj.q_plan)                        # one per rest, none while moving
    for c, q in zip(captures, feed.traj.q_plan):
        np.testing.assert_allclose(c.q, q, atol=1e-9)
        assert (c.stamp % 1.5) >= 0.5 - 1e-9 and (c.stamp % 1.5) <= 1.0  # rested 0.5 s, before moving on
    first = [m for m in messages if m.startswith("capture")]
    assert "only 1 captures" in first[0] and first[-1].endswith("AX = XB well posed")


def test_a_manual_request_captures_the_next_frame_with_the_board(tmp_path):
    feed = _FrameFeeder(n=3)
    joints = JointHistory()
    t = np.arange(0, 3.0, 1 / RATE)
    joints.add(t, np.stack([feed.traj.at(s) for s in t]))
    with CaptureWriter(tmp_path / "cap") as writer:
        capturer = LiveCapturer(BoardDetector(feed.scene.config.board), writer, joints, lambda q: np.eye(4),
                                CaptureRules(auto=False))
        image = feed.renderer.render(feed.scene.T_camera_board(feed.traj.at(1.2)))
        assert not capturer.on_frame(1.2, image).startswith("capture")
        capturer.requested.set()
        assert capturer.on_frame(1.25, np.full_like(image, 255)).startswith("no board")   # request waits
        assert capturer.on_frame(1.3, image).startswith("capture 0 (1/15) (robot was moving)")


def test_corners_still():
    from calibration.board import Detection

    d = Detection(np.arange(10), np.random.default_rng(0).uniform(0, 300, (10, 2)), np.zeros((10, 3)))
    moved = Detection(d.ids, d.corners_px + [0.3, 0.2], d.points_board)
    assert corners_still(d, moved, 0.5) and not corners_still(d, Detection(d.ids, d.corners_px + 0.6, d.points_board), 0.5)
    assert not corners_still(d, Detection(d.ids[:5], d.corners_px[:5], d.points_board[:5]), 0.5)
    assert not corners_still(None, d, 0.5)


@pytest.mark.slow
def test_live_capture_from_a_realsense_ir_recording_and_the_rtde_server_recovers_the_hand_eye(tmp_path):
    """The issue's target: within 1 mm / 0.1 deg of the simulated T_flange_camera. The recording and the
    RTDE server play in real time (a live session's sources), so each rest must outlast the detector's
    work on the frames it shows: with 1 s rests (6 frames at 6 fps) 3, 9, 10 and 11 of 12 rests were
    captured in four runs on the 2-core sandbox (2026-11-25, at load 0.3 too); with 2 s rests 12 of 12
    in two runs beside a CI run."""
    pytest.importorskip("pyrealsense2")
    pytest.importorskip("rtde_receive")
    import yaml

    from app.cli import main
    from app.interfaces import SessionClock
    from calibration.handeye import read_hand_eye_yaml
    from calibration.live_session import run_live_capture
    from calibration.live_sim import write_ir_recording
    from plugins.realsense import recording_suffix
    from plugins.rtde_server import RTDEServerProcess

    feed = _FrameFeeder(n=12, seed=2, full_size=True, rest_s=2.0)
    rng = np.random.default_rng(3)
    path, _ = write_ir_recording(tmp_path / f"ir{recording_suffix()}", feed.scene, feed.traj, fps=6, rng=rng)
    clock = SessionClock(lead_in_s=1.0)
    feed.traj.anchor = clock.t0 + clock.lead_in_s
    with RTDEServerProcess(joints=feed.traj) as server:
        session = {"camera": {"plugin": "realsense", "params": {"recording": str(path), "streams": "depth,ir"}},
                   "robot": {"plugin": "ur", "params": {"host": server.host}, "model": "ur5e"}}
        (tmp_path / "s.yaml").write_text(yaml.safe_dump(session))
        n = run_live_capture(tmp_path / "s.yaml", tmp_path / "cap", count=12, rrd=False, clock=clock, report=print)
    assert n == 12
    assert main(["calibrate", "hand-eye", "--captures", str(tmp_path / "cap"), "--out", str(tmp_path / "he.yaml")]) == 0
    T = read_hand_eye_yaml(tmp_path / "he.yaml")
    T_true = feed.scene.config.T_flange_camera
    error_mm = 1e3 * np.linalg.norm(T[:3, 3] - T_true[:3, 3])
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1)))
    print(f"live capture hand-eye error: {error_mm:.3f} mm, {angle:.4f} deg")
    assert error_mm < 1.0 and angle < 0.1
