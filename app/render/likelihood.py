"""GL likelihood backend: batched rendering + per-particle log-likelihood in a compute shader.

Implements the :class:`app.filter.observation.LikelihoodBackend` protocol with the same
observation model as the numpy reference :func:`app.filter.likelihood_ref.log_likelihood`
(DESIGN.md "Observation"; (B) eq. 4.33 smooth occlusion, 4.34-4.39 pixel classification with L0,
4.37 pixel-count regularisation). ``likelihood.comp.glsl`` runs one work group per particle with a
shared-memory reduction; only N floats come back.

Usage::

    backend = GLLikelihoodBackend(ctx, mesh_vertices, mesh_faces, camera_80x60, capacity=200, params=params)
    log_lik = backend.log_likelihood(T_camera_bone, depth_80x60)   # (N,) float64
"""
from __future__ import annotations

import logging
import time

import moderngl
import numpy as np

from app.filter.likelihood_ref import LOG_FLOOR, LikelihoodParams
from app.filter.observation import Evidence, depth_evidence, has_valid_depth
from app.geometry.camera import PinholeCamera
from app.render import shaders
from app.render.batched import DEFAULT_FAR, DEFAULT_NEAR, BatchedDepthRenderer

log = logging.getLogger(__name__)

LOCAL_SIZE = 64  # invocations per work group (one group per particle)


class GLLikelihoodBackend:
    """Render N pose hypotheses and score them against one measured depth image, on the GPU.

    Parameters
    ----------
    ctx : moderngl.Context (GL >= 4.3)
    vertices, faces : the decimated tracking mesh, bone frame, metres
    camera : PinholeCamera at the filter resolution (the measured image must have its size)
    capacity : maximum number of particles per call
    params : LikelihoodParams
    profile : if True, wait for the GPU after each stage so ``timings`` splits render /
        likelihood / read-back (slower; for benchmarks)
    """

    name = "gl"

    def __init__(
        self,
        ctx: moderngl.Context,
        vertices: np.ndarray,
        faces: np.ndarray,
        camera: PinholeCamera,
        capacity: int,
        params: LikelihoodParams,
        near: float = DEFAULT_NEAR,
        far: float = DEFAULT_FAR,
        profile: bool = False,
        cull_back_faces: bool = False,
    ):
        self.ctx = ctx
        self.camera = camera
        self.params = params
        self.profile = profile
        self.renderer = BatchedDepthRenderer(ctx, vertices, faces, camera, capacity, near, far, cull_back_faces)
        defines = {
            "LOCAL_SIZE": LOCAL_SIZE,
            "TILE_W": camera.width,
            "TILE_H": camera.height,
            "GRID_X": self.renderer.grid[0],
            "SMOOTH_OCCLUSION": int(params.occlusion == "smooth_exponential"),
            "CLASSIFICATION": int(bool(params.classification)),
            "BACKGROUND_RATIO": int(bool(params.background_ratio)),
            "LOG_FLOOR": f"{LOG_FLOOR:.9e}",
        }
        self.shader = shaders.compute_shader(ctx, "likelihood.comp.glsl", defines)
        self._set_uniforms(params)
        self.measured = ctx.texture((camera.width, camera.height), 1, dtype="f4")
        self.measured.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.output = ctx.buffer(reserve=4 * capacity)
        self.boxes = ctx.buffer(reserve=16 * capacity)
        self.corners_bone = bounding_box_corners(vertices)
        self.timings: dict[str, float] = {}

    def _set_uniforms(self, p: LikelihoodParams) -> None:
        values = {
            "z_max": p.z_max, "lam": p.lam, "w_u": p.w_u, "w_e": p.w_e, "w_n": p.w_n,
            "k_noise": p.k, "sigma_base": p.sigma_base, "l0_weight": p.l0_weight, "c_reg": p.pixel_count_reg,
            "pixel_weight": p.pixel_weight, "occluder_margin": p.occluder_margin,
        }
        for name, value in values.items():
            if name in self.shader:
                self.shader[name].value = float(value)
        if "rendered" in self.shader:
            self.shader["rendered"].value = 0
        if "measured" in self.shader:
            self.shader["measured"].value = 1

    @property
    def capacity(self) -> int:
        return self.renderer.capacity

    def _mark(self, stage: str, t0: float) -> float:
        if self.profile:
            self.ctx.finish()
        t1 = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + (t1 - t0)
        return t1

    def log_likelihood(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray) -> np.ndarray:
        """(N,) float64 log p(z | x_j) for the N poses ``T_camera_bone`` (N, 4, 4).

        ``depth_meas`` : (h, w) float32 metres at the filter resolution; 0 or non-finite = invalid.
        """
        h, w = depth_meas.shape
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(f"measured image is {w}x{h}, the backend was built for {self.camera.width}x{self.camera.height}")
        n = len(T_camera_bone)
        self.timings = {}
        t = time.perf_counter()
        self.renderer.render(T_camera_bone)
        t = self._mark("render", t)
        measured = np.where(np.isfinite(depth_meas), depth_meas, 0.0).astype(np.float32)
        self.measured.write(measured.tobytes())
        self.renderer.depth_texture.use(location=0)
        self.measured.use(location=1)
        self.output.bind_to_storage_buffer(2)
        self.boxes.write(image_boxes(self.camera, T_camera_bone, self.corners_bone).tobytes())
        self.boxes.bind_to_storage_buffer(3)
        self.shader.run(group_x=n)
        t = self._mark("likelihood", t)
        values = np.frombuffer(self.output.read(size=4 * n), dtype=np.float32).astype(np.float64)
        self._mark("readback", t)
        return values

    def describe(self) -> str:
        """One line for summaries and logs: which backend ran, on which GL renderer."""
        from app.render.context import describe

        return f"gl backend on {describe(self.ctx)}"

    def sync(self) -> None:
        """Wait for the GL commands issued so far (benchmarks time whole frames with it)."""
        self.ctx.finish()

    def render_depth(self, T_camera_bone: np.ndarray) -> np.ndarray:
        """(N, h, w) float32 rendered linear depth of the poses (image row order)."""
        self.renderer.render(T_camera_bone)
        return self.renderer.read_depth(len(T_camera_bone))

    def release(self) -> None:
        self.renderer.release()
        for obj in (self.shader, self.measured, self.output, self.boxes):
            obj.release()

    def has_measurement(self, depth_meas: np.ndarray) -> bool:
        """Whether any pixel is a valid measurement (:class:`app.filter.observation.ObservationModel`)."""
        return has_valid_depth(depth_meas, self.params)

    def evidence(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray, min_covered_pixels: int) -> Evidence:
        """The pose's covered pixels and inliers (:func:`app.filter.observation.depth_evidence`)."""
        return depth_evidence(self.render_depth, T_camera_bone, depth_meas, self.params, min_covered_pixels)



def bounding_box_corners(vertices: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the axis-aligned bounding box of the mesh (bone frame)."""
    lo, hi = np.min(vertices, axis=0), np.max(vertices, axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def image_boxes(camera: PinholeCamera, T_camera_bone: np.ndarray, corners_bone: np.ndarray,
                min_depth: float = 1e-3) -> np.ndarray:
    """(N, 4) int32 pixel boxes (u0, v0, u1, v1), inclusive, holding each pose's whole rendering.

    The projection of the bounding box's corners bounds the mesh's projection when every corner is
    in front of the camera; otherwise the box is the whole image (conservative). Empty boxes
    (u1 < u0) mean the pose covers no pixel.
    """
    p = np.einsum("nij,kj->nki", T_camera_bone[:, :3, :3], corners_bone) + T_camera_bone[:, None, :3, 3]
    z = p[..., 2]
    in_front = np.all(z > min_depth, axis=1)
    zs = np.where(z > min_depth, z, 1.0)
    u = camera.fx * p[..., 0] / zs + camera.cx
    v = camera.fy * p[..., 1] / zs + camera.cy
    boxes = np.stack([np.floor(u.min(1)), np.floor(v.min(1)), np.ceil(u.max(1)), np.ceil(v.max(1))], axis=1)
    boxes[~in_front] = [0, 0, camera.width - 1, camera.height - 1]
    lo = np.array([0, 0, 0, 0])
    hi = np.array([camera.width - 1, camera.height - 1, camera.width - 1, camera.height - 1])
    boxes = np.clip(boxes, lo - 1, hi + 1)
    boxes[:, :2] = np.maximum(boxes[:, :2], 0)
    boxes[:, 2:] = np.minimum(boxes[:, 2:], hi[2:])
    all_behind = np.all(z <= min_depth, axis=1)
    boxes[all_behind] = [0, 0, -1, -1]
    return np.ascontiguousarray(boxes.astype(np.int32))
