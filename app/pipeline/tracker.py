"""The depth tracker: the particle filter wired to the GL likelihood at the filter's resolution.

One object per session: it owns the GL resources (created on the calling thread), the
tracking mesh (decimated to ``config.mesh_triangles``) and the filter. ``process`` is the per-frame
entry point used by ``replay`` and ``track``: full-resolution depth in, estimate and status out.
"""
from __future__ import annotations

import logging
from collections import defaultdict

import numpy as np
import trimesh

from app.config import TrackerConfig
from app.depth_image import downsample_nearest
from app.filter.particle_filter import FilterOutput, ParticleFilter
from app.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)


class DepthTracker:
    """Track ``T_base_bone`` from depth frames and camera poses.

    Parameters
    ----------
    config : TrackerConfig
    mesh : the bone mesh (bone frame, metres), decimated here for tracking
    camera : the depth camera's full-resolution PinholeCamera
    T_flange_camera : hand-eye (4, 4), only used for logging the flange
    """

    def __init__(self, config: TrackerConfig, mesh: trimesh.Trimesh, camera: PinholeCamera,
                 T_flange_camera: np.ndarray | None = None):
        from app.mesh import outward_wound, prepare_mesh
        from app.render.context import describe, shared_context
        from app.render.likelihood import GLLikelihoodBackend

        self.config = config
        self.T_flange_camera = T_flange_camera
        tracking_mesh = prepare_mesh(mesh, max_triangles=config.mesh_triangles, center=False)
        self.mesh_vertices = np.asarray(tracking_mesh.vertices)
        self.mesh_faces = np.asarray(tracking_mesh.faces)
        width, height = config.resolution
        self.camera = camera.resized(width, height)
        ctx = shared_context()
        self.gl_description = describe(ctx)
        cull = config.cull_back_faces and outward_wound(tracking_mesh)
        if config.cull_back_faces and not cull:
            log.warning("the mesh's triangles are not consistently wound outwards: back-face culling disabled (slower)")
        self.backend = GLLikelihoodBackend(ctx, self.mesh_vertices, self.mesh_faces, self.camera, config.particles,
                                           config.likelihood, near=config.near, far=config.far, cull_back_faces=cull)
        self.filter = ParticleFilter(config, self.backend, np.random.default_rng(config.seed))
        self._timings: dict[str, float] = defaultdict(float)
        self._frames = 0

    def start(self, T_base_bone: np.ndarray) -> None:
        """Spread the particles around a coarse initial pose (the surgeon's alignment)."""
        self.filter.initialise(T_base_bone)

    def process(self, depth_m: np.ndarray, stamp: float, T_base_camera: np.ndarray | None) -> FilterOutput:
        """One frame: full-resolution depth (H, W) metres, its stamp (s) and camera pose (None = unknown)."""
        width, height = self.config.resolution
        depth_small = downsample_nearest(depth_m, width, height)
        result = self.filter.step(depth_small, stamp, T_base_camera)
        for stage, seconds in result.timings.items():
            self._timings[stage] += seconds
        for stage, seconds in self.backend.timings.items():
            self._timings[f"gl_{stage}"] += seconds
        self._frames += 1
        return result

    def particle_positions(self) -> np.ndarray:
        """(N, 3) particle positions in the base frame (metres)."""
        return self.filter.state.p

    def mean_timings_ms(self) -> dict[str, float]:
        return {k: 1e3 * v / max(self._frames, 1) for k, v in self._timings.items()}

    def release(self) -> None:
        self.backend.release()
