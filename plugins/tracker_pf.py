"""The particle-filter depth tracker as a session plugin (``tracker: particle_filter``).

A thin adapter over :class:`app.pipeline.tracker.DepthTracker`: ``params.config`` names a tracker
YAML (``app.config.load_config``; None = the defaults). Created on the loop thread, which owns
its GL context.
"""
from __future__ import annotations

from plugins._tracker_adapter import TrackerAdapter


class ParticleFilterTracker(TrackerAdapter):
    kind, name = "tracker", "particle_filter"

    def __init__(self, mesh, camera, T_flange_camera=None, config: str | None = None):
        from app.config import load_config
        from app.pipeline.tracker import DepthTracker

        self.tracker = DepthTracker(load_config(config), mesh, camera, T_flange_camera)

