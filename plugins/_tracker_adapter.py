"""The session's view of a depth tracker: a plugin that wraps one and hands every call on.

The tracker plugins (``particle_filter``, ``icp``) differ only in how they build their tracker;
the calls the loop makes (:class:`app.interfaces.Tracker`) go to ``self.tracker`` unchanged.
"""
from __future__ import annotations

import numpy as np


class TrackerAdapter:
    """Hands ``start``/``process``/``particle_positions``/``release`` to ``self.tracker``."""

    tracker = None

    def start(self, T_base_bone: np.ndarray) -> None:
        self.tracker.start(T_base_bone)

    def process(self, depth_m: np.ndarray, stamp: float, T_base_camera: np.ndarray | None):
        return self.tracker.process(depth_m, stamp, T_base_camera)

    def particle_positions(self) -> np.ndarray:
        return self.tracker.particle_positions()

    def release(self) -> None:
        self.tracker.release()
