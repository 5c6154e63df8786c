"""The particle-filter depth tracker as a session plugin (``tracker: particle_filter``).

The :class:`app.pipeline.engine_tracker.EngineTracker` of :class:`app.pipeline.tracker.DepthTracker`: ``params.config`` names a tracker
YAML (``app.config.load_config``; None = the defaults). Created on the loop thread, which owns
its GL context.
"""
from __future__ import annotations

from app.pipeline.engine_tracker import EngineTracker


class ParticleFilterTracker(EngineTracker):
    kind, name = "tracker", "particle_filter"

    def __init__(self, mesh, camera, T_flange_camera=None, config: str | None = None):
        from app.config import load_config
        from app.pipeline.tracker import DepthTracker

        super().__init__(DepthTracker(load_config(config), mesh, camera, T_flange_camera, live=True))

