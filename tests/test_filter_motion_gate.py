"""The motion gate's speed is the template points' largest displacement over its window (closed forms; issue 32:
one speed instead of a position speed and an angular speed)."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from app.filter.motion_gate import MotionGate, template_speed
from app.geometry import quaternion as quat
from app.geometry import se3

POINTS = np.array([[0.0, 0.0, 0.0], [0.08, 0.0, 0.0], [0.0, 0.05, 0.0]])   # 80 mm and 50 mm from the origin


def pose(angle_z, x):
    return se3.from_quat_trans(quat.exp_map(np.array([0.0, 0.0, angle_z])), np.array([x, 0.0, 0.0]))


def test_constant_motion_gives_its_speed_and_a_static_pose_gives_zero():
    gate = MotionGate(window_s=0.2, speed_threshold=0.03)
    for k in range(40):   # 5 cm/s at 100 Hz
        speed, since = gate.update(k / 100, pose(0.0, 0.05 * k / 100))
    assert speed == pytest.approx(0.05, rel=1e-9)
    assert since == 0.0
    for k in range(40, 100):
        speed, since = gate.update(k / 100, pose(0.0, 0.05 * 0.39))
    assert speed == 0.0
    # the 0.2 s window still spans the motion until its mean speed drops to 30 mm/s: k = 46
    # (0.05 m/s * (59 - k) / 20 frames >= 0.03 m/s, the boundary frame k = 47 within rounding),
    # so at k = 99: 0.52-0.53 s
    assert since == pytest.approx(0.525, abs=0.0051)


def test_a_turn_moves_the_farthest_template_point_at_its_chord_speed():
    """20 deg/s about z over 0.2 s: the point 80 mm out moves the chord 2 r sin(θ/2) = 27.8 mm/s, under 30 mm/s;
    30 deg/s moves it 41.6 mm/s, over it. With only the origin as its point the turn is not seen at all."""
    for rate, moving in ((math.radians(20.0), False), (math.radians(30.0), True)):
        expected = 2 * 0.08 * math.sin(rate * 0.2 / 2) / 0.2
        assert template_speed(pose(0.0, 0.0), pose(rate * 0.2, 0.0), POINTS, 0.2) == pytest.approx(expected, rel=1e-9)
        gate = MotionGate(0.2, 0.03, POINTS)
        for k in range(41):
            speed, since = gate.update(k / 100, pose(rate * k / 100, 0.0))
        assert speed == pytest.approx(expected, rel=1e-6) and (since == 0.0) == moving
    assert template_speed(pose(0.0, 0.0), pose(0.1, 0.0), np.zeros((1, 3)), 0.2) == pytest.approx(0.0, abs=1e-12)
    assert template_speed(pose(0.0, 0.0), pose(0.1, 0.0), POINTS, 0.0) == 0.0


def test_a_static_estimate_counts_from_the_start_and_reset_forgets():
    gate = MotionGate(0.2, 0.03)
    assert gate.update(0.0, pose(0.0, 0.0))[1] == 0.0          # the start is motion (converging)
    for k in range(1, 10):
        _, since = gate.update(k / 90, pose(0.0, 0.0))
    assert since == pytest.approx(9 / 90)
    gate.update(0.2, pose(0.0, 0.1))
    assert gate.update(0.21, pose(0.0, 0.1))[1] < 0.1
    gate.reset()
    assert gate.update(0.3, pose(0.0, 0.5))[0] == 0.0


def test_a_failed_held_test_restarts_the_settle_of_the_steady_test():
    """The held test (the image's fit contradicts the static prior's held pose) says the bone started to move:
    the tracker's steady test restarts its settle there (status.settle_s), so the frames after the prior
    releases are not ok while the estimate, still slow over the window, catches up (or_fast_reposition
    crest_right_03 seed 3: two frames ok at 1.5 and 2.6 mm off after a release)."""
    from app.config import TrackerConfig
    from app.filter.particle_filter import FilterOutput
    from app.filter.status import Reason, TrackingStatus
    from app.pipeline.tracker import DepthTracker

    config = TrackerConfig()
    st = config.status
    tracker = SimpleNamespace(motion_gate=MotionGate(st.motion_window_s, st.uncertain_speed), config=config)

    def frame(stamp, reasons=()):
        status = TrackingStatus.UNCERTAIN if reasons else TrackingStatus.OK
        out = FilterOutput(T_base_bone=np.eye(4), position_spread=0.001, rotation_spread=0.01, ess=50.0,
                           ess_ratio=0.25, log_likelihood_max=0.0, status=status, inlier_fraction=0.9,
                           covered_pixels=400, n_nan=0, resampled=False, dt=0.011, weighed=True, timings={},
                           reasons=tuple(reasons))
        return DepthTracker._steady(tracker, out, stamp)

    period = 1.0 / 90
    stamps = [k * period for k in range(200)]
    outs = [frame(t) for t in stamps[:60]]                      # at rest: ok once the start's settle has passed
    assert outs[-1].status == TrackingStatus.OK
    held = Reason("held", "the image's own fit contradicts the held pose")
    assert frame(stamps[60], [held]).status == TrackingStatus.UNCERTAIN
    after = [frame(t) for t in stamps[61:120]]                 # the pose still (the prior released onto the fit)
    settle = [o.status for o in after]
    first_ok = settle.index(TrackingStatus.OK)
    assert st.settle_s <= stamps[61 + first_ok] - stamps[60] <= st.settle_s + 1.5 * period   # settle_s after it
    assert all("moving" in [r.code for r in o.reasons] for o in after[:first_ok])


def test_the_reach_is_kept_with_the_points():
    """MotionGate.reach (template_spread's max |x|) follows every assignment of points_bone."""
    gate = MotionGate(0.2, 0.03)
    assert gate.reach == 0.0
    gate.points_bone = POINTS.tolist()
    assert gate.points_bone.shape == (3, 3) and gate.reach == pytest.approx(0.08, abs=1e-15)
    gate.points_bone = 2.0 * POINTS
    assert gate.reach == pytest.approx(0.16, abs=1e-15)
