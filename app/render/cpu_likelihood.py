"""CPU likelihood backend: exact z-buffer rasterisation fused with the pixel term, in numba.

Implements :class:`app.filter.observation.LikelihoodBackend` with the observation model of
:func:`app.filter.likelihood_ref.log_likelihood` and the GL renderer's rasterisation conventions
(the kernels and their conventions: :mod:`app.render.cpu_raster`). Without a GPU it replaces
:class:`app.render.likelihood.GLLikelihoodBackend`, whose llvmpipe pipeline pushes N x ~1,000 mostly
sub-pixel triangles through a full GL pipeline (issue 13; BENCHMARKS.md §1).

Usage::

    backend = CPULikelihoodBackend(mesh_vertices, mesh_faces, camera_160x120, params=params)
    log_lik = backend.log_likelihood(T_camera_bone, depth_160x120)   # (N,) float64
    depth = backend.render_depth(T_camera_bone[:1])                   # (1, 120, 160) float32
"""
from __future__ import annotations

import logging
import time

import numba
import numpy as np

from app.filter.likelihood_ref import INLIER_SIGMAS, LikelihoodParams
from app.filter.observation import Evidence, depth_evidence, has_valid_depth
from app.geometry.camera import PinholeCamera
from app.render import cpu_raster
from app.render.batched import DEFAULT_FAR, DEFAULT_NEAR

log = logging.getLogger(__name__)

CHUNKS_PER_THREAD = 4   # z-buffers per numba thread (cpu_raster.batch: the chunks take the hypotheses one at a time)
_first_call_s: float | None = None


def first_call_seconds() -> float | None:
    """Seconds the process's first kernel calls took (numba compile, or loading its cache)."""
    return _first_call_s


class CPULikelihoodBackend:
    """Render N pose hypotheses and score them against one measured depth image, on the CPU.

    Parameters
    ----------
    vertices, faces : the decimated tracking mesh, bone frame, metres
    camera : PinholeCamera at the filter resolution (the measured image must have its size)
    capacity : the particle count it is built for (kept for the backend contract; any N works)
    params : LikelihoodParams
    near, far : clip planes, metres (as the GL renderer's)
    cull_back_faces : skip triangles facing away from the camera; only valid for a mesh wound
        counter-clockwise seen from outside (:func:`app.mesh.outward_wound`)
    """

    name = "cpu"

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, camera: PinholeCamera, capacity: int = 1,
                 params: LikelihoodParams | None = None, near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR,
                 cull_back_faces: bool = False, profile: bool = False):
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"expected vertices (V, 3) and faces (F, 3), got {vertices.shape} and {faces.shape}")
        if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise ValueError(f"face indices must lie in [0, {len(vertices)}); got [{faces.min()}, {faces.max()}]")
        if not 0 < near < far:
            raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
        self.vertices, self.faces, self.camera = vertices, faces, camera
        self.capacity = int(capacity)
        self.params = params or LikelihoodParams()
        self.prm = cpu_raster.pack_params(self.params)
        self.cam = np.array([camera.fx, camera.fy, camera.cx, camera.cy, near, far], dtype=np.float64)
        self.cull = bool(cull_back_faces)
        self.profile = profile   # accepted for symmetry with the GL backend: the CPU stages are always exact
        self.chunks = max(1, numba.get_num_threads() * CHUNKS_PER_THREAD)
        self.zbufs = np.zeros((self.chunks, camera.height, camera.width), dtype=np.float64)
        p = self.params
        self._evidence_params = np.array([p.z_max, p.occluder_margin, p.k, p.sigma_base, INLIER_SIGMAS], np.float64)
        self._vertex_scratch = np.empty((len(vertices), 6))
        self._box = np.empty(4, np.int64)
        self.timings: dict[str, float] = {}
        self._warm_up()

    def describe(self) -> str:
        """One line for summaries and logs: which backend ran and on how many threads."""
        return f"cpu backend (numba {numba.__version__}, {numba.get_num_threads()} threads, exact z-buffer)"

    def _warm_up(self) -> None:
        """Compile (or load from numba's cache) the kernels once per process; time it."""
        global _first_call_s
        if _first_call_s is not None:
            return
        t0 = time.perf_counter()
        T = np.eye(4)[None].copy()
        T[0, 2, 3] = 1.0
        self.render_depth(T)
        empty = np.zeros((self.camera.height, self.camera.width), np.float32)
        self.log_likelihood(T, empty)
        self.evidence(T[0], empty, 1)
        _first_call_s = time.perf_counter() - t0
        self.timings = {}
        log.info("cpu backend: first kernel calls took %.2f s (numba compile or cache load)", _first_call_s)

    def _poses(self, T_camera_bone: np.ndarray) -> np.ndarray:
        T = np.ascontiguousarray(T_camera_bone, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"poses must be (N, 4, 4), got {T.shape}")
        return T

    def log_likelihood(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray) -> np.ndarray:
        """(N,) float64 log p(z | x_j) for the N poses ``T_camera_bone`` (N, 4, 4).

        ``depth_meas`` : (h, w) float32 metres at the filter resolution; 0 or non-finite = invalid.
        """
        h, w = np.shape(depth_meas)
        if (w, h) != (self.camera.width, self.camera.height):
            raise ValueError(f"measured image is {w}x{h}, the backend was built for {self.camera.width}x{self.camera.height}")
        t0 = time.perf_counter()
        T = self._poses(T_camera_bone)
        depth = np.ascontiguousarray(depth_meas, dtype=np.float32)
        out = np.empty(len(T), dtype=np.float64)
        t1 = time.perf_counter()
        cpu_raster.log_likelihood_batch(T, self.vertices, self.faces, self.cam, self.cull, depth, self.prm,
                                        self.zbufs, out)
        t2 = time.perf_counter()
        self.timings = {"prepare": t1 - t0, "raster_likelihood": t2 - t1}
        return out

    def render_depth(self, T_camera_bone: np.ndarray) -> np.ndarray:
        """(N, h, w) float32 rendered linear depth of the poses (image row order, 0 = not covered)."""
        T = self._poses(T_camera_bone)
        out = np.empty((len(T), self.camera.height, self.camera.width), dtype=np.float32)
        cpu_raster.render_batch(T, self.vertices, self.faces, self.cam, self.cull, self.zbufs, out)
        return out

    def resized(self, camera: PinholeCamera, vertices: np.ndarray | None = None, faces: np.ndarray | None = None,
                cull_back_faces: bool | None = None) -> "CPULikelihoodBackend":
        """The same likelihood and clip planes at another camera, optionally with another mesh (a
        coarser one; ``cull_back_faces`` then says whether it is wound outwards): the one-point
        initialiser's coarse levels (:func:`app.filter.smc_init.levels.make_levels`)."""
        same = vertices is None
        return CPULikelihoodBackend(self.vertices if same else vertices, self.faces if same else faces, camera,
                                    self.capacity, self.params, near=float(self.cam[4]), far=float(self.cam[5]),
                                    cull_back_faces=self.cull if cull_back_faces is None else cull_back_faces)

    def sync(self) -> None:
        """Nothing to wait for: the kernels return when done (the GL backend's ``sync`` waits)."""

    def release(self) -> None:
        """Nothing to free but memory (kept for the backend contract)."""
        self.zbufs = np.zeros((0, 0, 0))

    def has_measurement(self, depth_meas: np.ndarray) -> bool:
        """Whether any pixel is a valid measurement (:class:`app.filter.observation.ObservationModel`)."""
        return has_valid_depth(depth_meas, self.params)

    def evidence(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray, min_covered_pixels: int) -> Evidence:
        """The pose's covered pixels and inliers (:func:`app.filter.observation.depth_evidence`):
        counted in one numba pass over the pose's pixel box (:func:`cpu_raster.evidence_counts`,
        the same counts) for a float32 image of the backend's size, by depth_evidence otherwise."""
        T = np.asarray(T_camera_bone, dtype=np.float64)
        if (getattr(depth_meas, "dtype", None) != np.float32 or T.shape != (4, 4)
                or np.shape(depth_meas) != (self.camera.height, self.camera.width)):
            return depth_evidence(self.render_depth, T_camera_bone, depth_meas, self.params, min_covered_pixels)
        covered, inliers = cpu_raster.evidence_counts(
            np.ascontiguousarray(T), self.vertices, self.faces, self.cam, self.cull,
            np.ascontiguousarray(depth_meas), self._evidence_params, self.zbufs[0], self._vertex_scratch, self._box)
        return Evidence(int(covered), int(inliers), covered < min_covered_pixels)
