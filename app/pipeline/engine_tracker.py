"""A tracking engine as a :class:`app.interfaces.Tracker`: the one adapter replay and the plugins share.

The engines (:class:`app.pipeline.tracker.DepthTracker`, the ICP baseline
:class:`app.baselines.icp.ICPTracker`) take ``process(depth_m, stamp, T_base_camera)``; the
contract takes the whole frame. :class:`EngineTracker` hands every call on; ``engine`` stays
reachable for what only some engines have (``start_from_point``, ``init_result``, ``backend_name``,
the tracking mesh).
"""
from __future__ import annotations

import numpy as np

from app.filter.status import LOST_NO_POSE_S
from app.interfaces import DepthFrame, TrackerResult


class EngineTracker:
    """:class:`app.interfaces.Tracker` over an engine; ``description`` is the engine's ``gl_description``."""

    def __init__(self, engine):
        self.engine = engine
        self.description = str(getattr(engine, "gl_description", type(engine).__name__))

    @property
    def lost_no_pose_s(self) -> float:
        """s without a camera pose before the status is lost: the engine's ``recovery.after_uncertain_s`` (its
        ``status.lost_no_pose_s``, tied by :class:`app.config.TrackerConfig`; the
        live loop's floor reads it, so a session has one missing-pose clock; issue 32)."""
        config = getattr(self.engine, "config", None)
        status = getattr(config, "status", None)
        return float(status.lost_no_pose_s) if status is not None else LOST_NO_POSE_S

    def start(self, T_base_bone: np.ndarray) -> None:
        self.engine.start(T_base_bone)

    def process(self, frame: DepthFrame, T_base_camera: np.ndarray | None) -> TrackerResult:
        return self.engine.process(frame.depth_m, frame.stamp, T_base_camera)

    def particle_positions(self) -> np.ndarray:
        return self.engine.particle_positions()

    def mean_timings_ms(self) -> dict[str, float]:
        return self.engine.mean_timings_ms()

    def release(self) -> None:
        self.engine.release()
