"""A robot that holds still: fixed joint angles streamed at a rate (``robot: static``).

For a camera on a robot that did not move while recording (a ``.bag`` taken with the arm locked),
or a camera on a tripod whose pose is given as joints of the session's robot model.
"""
from __future__ import annotations

import numpy as np

from app.errors import ConfigError
from app.interfaces import JointSamples, SessionClock
from plugins._base import ThreadedSource


class StaticRobot(ThreadedSource):
    kind, name = "robot", "static"

    def __init__(self, q: list[float], rate_hz: float = 125.0):
        super().__init__()
        q = np.asarray(q, float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ConfigError("robot.params.q", f"expected 6 finite joint angles in radians, got {q.tolist()}")
        if not rate_hz > 0:
            raise ConfigError("robot.params.rate_hz", f"must be > 0, got {rate_hz}")
        self.q = q
        self.rate_hz = float(rate_hz)

    def open(self, clock: SessionClock, event) -> None:
        self._bind(clock, event)

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        t = self.clock.now()
        while not self._stop.is_set():
            self._push(JointSamples(np.array([t]), self.q[None].copy()))
            t += period
            if not self._sleep_until(t):
                return
