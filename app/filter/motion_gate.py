"""The speed of the template's points, from the history of the bone's estimates, for the status's motion rule.

Import as ``from app.filter.motion_gate import MotionGate``. While the surgeon repositions the
pelvis the filter's estimate lags the bone by millimetres, and along the crest's own length the
image barely tells: the rendered crest slides along itself with most of its pixels still inliers.
Nobody cuts while the bone is being moved, so the status treats a moving bone as uncertain
(app/filter/status.py) and the projector shows no template until it has settled.

One speed (issue 32; it was a position speed and an angular speed, 30 mm/s and 20 deg/s): the
largest speed of the template's points x_k (bone frame) between the estimates a window of
``window_s`` apart (0.2 s: long enough that the estimate's frame-to-frame jitter reads as a few mm/s,
short enough to react within a few frames), finite differences in the base frame:

    v = max_k |T_t x_k - T_{t-W} x_k| / W        (app/metrics.py ``mdd`` over W)

A lagging estimate misplaces the template by about its speed times the lag, so the template's points
are what the test watches: on the CT crests (vertices up to 80-90 mm from the centroid) 30 mm/s is a
translation of 30 mm/s or a turn of about 20 deg/s about the centroid.

``seconds_since_motion`` is the time since the last frame whose speed exceeded the threshold,
or since the start (the filter converging from its coarse initial pose is motion too): the
status stays uncertain for ``settle_s`` after the bone stops, and after the start.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from app import metrics


class MotionGate:
    """The template points' largest speed over a sliding window and the time since it last moved.

    Parameters
    ----------
    window_s : s, the finite-difference window W
    speed_threshold : m/s, above it the bone is moving
    points_bone : (N, 3) float, m, bone frame: the template's points (default: the bone frame's origin;
        the tracker sets the template's, :attr:`points_bone`)

    Attributes
    ----------
    reach : m, the largest distance of a template point from the bone frame's origin, kept with
        :attr:`points_bone` (the filter's lost spread bound, :func:`app.filter.estimate.template_spread`)
    """

    def __init__(self, window_s: float, speed_threshold: float, points_bone: np.ndarray | None = None):
        self.window_s = window_s
        self.speed_threshold = speed_threshold
        self.points_bone = np.zeros((1, 3)) if points_bone is None else points_bone
        self._history: deque[tuple[float, np.ndarray]] = deque()
        self._last_motion: float | None = None

    @property
    def points_bone(self) -> np.ndarray:
        """(N, 3) float, m, bone frame: the template's points."""
        return self._points_bone

    @points_bone.setter
    def points_bone(self, points_bone: np.ndarray) -> None:
        self._points_bone = np.asarray(points_bone, float).reshape(-1, 3)
        self.reach = float(np.max(np.linalg.norm(self._points_bone, axis=1)))     # once, not every frame

    def mark(self, stamp: float) -> None:
        """Another test saw the bone move at ``stamp`` (the held test: the image's own fit contradicts the
        pose the static prior held): the settle restarts there, as after a speed above the threshold."""
        self._last_motion = float(stamp)

    def reset(self) -> None:
        self._history.clear()
        self._last_motion = None

    def update(self, stamp: float, T_base_bone: np.ndarray) -> tuple[float, float]:
        """Add an estimate; return (speed m/s of the fastest template point, seconds since motion).

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
        speed = template_speed(T0, T_base_bone, self.points_bone, dt)
        if speed > self.speed_threshold:
            self._last_motion = stamp
        since = math.inf if self._last_motion is None else stamp - self._last_motion
        return speed, since


def template_speed(T_base_bone_0: np.ndarray, T_base_bone_1: np.ndarray, points_bone: np.ndarray, dt: float) -> float:
    """m/s, the largest displacement of ``points_bone`` (N, 3, bone frame) between two poses over ``dt`` s (0
    when dt <= 0)."""
    if dt <= 0:
        return 0.0
    return metrics.mdd(T_base_bone_1, T_base_bone_0, points_bone) / dt
