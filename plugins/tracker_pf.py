"""The particle-filter depth tracker as a session plugin (``tracker: particle_filter``).

A thin adapter over :class:`app.pipeline.tracker.DepthTracker`: ``params.config`` names a tracker
YAML (``app.config.load_config``; None = the defaults). Created on the loop thread, which owns
its GL context.
"""
from __future__ import annotations

import numpy as np


class ParticleFilterTracker:
    kind, name = "tracker", "particle_filter"

    def __init__(self, mesh, camera, T_flange_camera=None, config: str | None = None):
        from app.config import load_config
        from app.pipeline.tracker import DepthTracker

        self.tracker = DepthTracker(load_config(config), mesh, camera, T_flange_camera)

    def start(self, T_base_bone: np.ndarray) -> None:
        self.tracker.start(T_base_bone)

    def process(self, depth_m: np.ndarray, stamp: float, T_base_camera: np.ndarray | None):
        return self.tracker.process(depth_m, stamp, T_base_camera)

    def particle_positions(self) -> np.ndarray:
        return self.tracker.particle_positions()

    def release(self) -> None:
        self.tracker.release()
