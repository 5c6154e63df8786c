"""The speed of the tracked bone, from the history of its estimates, for the status's motion rule.

Import as ``from app.filter.motion_gate import MotionGate``. While the surgeon repositions the
pelvis the filter's estimate lags the bone by millimetres, and along the crest's own length the
image barely tells: the rendered crest slides along itself with most of its pixels still inliers.
Nobody cuts while the bone is being moved, so the status treats a moving bone as uncertain
(app/filter/status.py) and the projector shows no template until it has settled.

Speeds are finite differences of the *estimate* in the base frame over a window of
``window_s`` (0.2 s: long enough that the estimate's frame-to-frame jitter, ~1 mm and ~1°, reads
as a few mm/s and deg/s, short enough to react within a few frames):

    v = |p_t - p_{t-W}| / W,    ω = angle(R_{t-W}ᵀ R_t) / W

``seconds_since_motion`` is the time since the last frame whose speeds exceeded the thresholds,
or since the start (the filter converging from its coarse initial pose is motion too): the
status stays uncertain for ``settle_s`` after the bone stops, and after the start.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from app.geometry import se3


class MotionGate:
    """Speeds of the estimate over a sliding window and the time since it last moved.

    Parameters
    ----------
    window_s : s, the finite-difference window W
    speed_threshold : m/s; angular_speed_threshold : rad/s, above either the bone is moving
    """

    def __init__(self, window_s: float, speed_threshold: float, angular_speed_threshold: float):
        self.window_s = window_s
        self.speed_threshold = speed_threshold
        self.angular_speed_threshold = angular_speed_threshold
        self._history: deque[tuple[float, np.ndarray]] = deque()
        self._last_motion: float | None = None

    def reset(self) -> None:
        self._history.clear()
        self._last_motion = None

    def update(self, stamp: float, T_base_bone: np.ndarray) -> tuple[float, float, float]:
        """Add an estimate; return (speed m/s, angular speed rad/s, seconds since motion).

        The first estimate after a (re)start counts as motion: the cloud is still converging from
        the coarse initial pose, so the status cannot be ok before ``settle_s`` has passed.
        """
        if not self._history:
            self._last_motion = stamp
        self._history.append((stamp, np.asarray(T_base_bone, dtype=float).copy()))
        while len(self._history) > 2 and stamp - self._history[1][0] >= self.window_s:
            self._history.popleft()
        t0, T0 = self._history[0]
        dt = stamp - t0
        if dt <= 0:
            speed = angular_speed = 0.0
        else:
            speed = float(np.linalg.norm(T_base_bone[:3, 3] - T0[:3, 3])) / dt
            angular_speed = float(se3.rotation_angle(T0, T_base_bone)) / dt
        if speed > self.speed_threshold or angular_speed > self.angular_speed_threshold:
            self._last_motion = stamp
        since = math.inf if self._last_motion is None else stamp - self._last_motion
        return speed, angular_speed, since
