"""The motion gate's speeds are finite differences over its window (closed forms)."""
import math

import numpy as np
import pytest

from app.filter.motion_gate import MotionGate
from app.geometry import quaternion as quat
from app.geometry import se3


def pose(angle_z, x):
    return se3.from_quat_trans(quat.exp_map(np.array([0.0, 0.0, angle_z])), np.array([x, 0.0, 0.0]))


def test_constant_motion_gives_its_speed_and_a_static_pose_gives_zero():
    gate = MotionGate(window_s=0.2, speed_threshold=0.03, angular_speed_threshold=math.radians(20))
    for k in range(40):   # 5 cm/s and 10 deg/s at 100 Hz
        speed, w, since = gate.update(k / 100, pose(math.radians(10) * k / 100, 0.05 * k / 100))
    assert speed == pytest.approx(0.05, rel=1e-9) and w == pytest.approx(math.radians(10), rel=1e-6)
    assert since == 0.0
    for k in range(40, 100):
        speed, w, since = gate.update(k / 100, pose(math.radians(10) * 0.39, 0.05 * 0.39))
    assert speed == 0.0 and w == pytest.approx(0.0, abs=1e-9)
    # the 0.2 s window still spans the motion until its mean speed drops to 30 mm/s: k = 46
    # (0.05 m/s * (59 - k) / 20 frames >= 0.03 m/s, the boundary frame k = 47 within rounding),
    # so at k = 99: 0.52-0.53 s
    assert since == pytest.approx(0.525, abs=0.0051)


def test_a_static_estimate_counts_from_the_start_and_reset_forgets():
    gate = MotionGate(0.2, 0.03, 0.3)
    assert gate.update(0.0, pose(0.0, 0.0))[2] == 0.0          # the start is motion (converging)
    for k in range(1, 10):
        *_, since = gate.update(k / 90, pose(0.0, 0.0))
    assert since == pytest.approx(9 / 90)
    gate.update(0.2, pose(0.0, 0.1))
    assert gate.update(0.21, pose(0.0, 0.1))[2] < 0.1
    gate.reset()
    assert gate.update(0.3, pose(0.0, 0.5))[:2] == (0.0, 0.0)
