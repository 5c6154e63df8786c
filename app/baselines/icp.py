"""Baseline tracker: frame-to-model point-to-plane ICP with Open3D.

What a user would otherwise pick. Each frame: the measured depth is back-projected (camera frame),
moved into the base frame with ``T_base_camera``, cropped to a sphere around the last estimate and
voxel-downsampled; Open3D's point-to-plane ICP (coarse then fine correspondence distance) aligns
it to the model's surface samples (with normals) placed at the last estimate. The correction
``T_delta`` maps scene points onto the model, so the new estimate is ``T_delta^-1 @ T_base_bone``.

Status: ``ok`` when the fitness (fraction of scene points with a correspondence) and the inlier
RMSE are good, ``uncertain`` when mediocre, ``lost`` otherwise or when too few points remain.
It has the same ``start`` / ``process`` / ``release`` interface as
:class:`app.pipeline.tracker.DepthTracker`, so replay and bench run both.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from app.depth_image import downsample_nearest
from app.geometry import se3
from app.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)


@dataclass
class ICPParams:
    resolution: tuple[int, int] = (160, 120)   # depth is reduced by nearest neighbour first
    voxel: float = 0.002                       # m
    crop_margin: float = 0.02                  # m beyond the model's bounding sphere
    max_distance_coarse: float = 0.010         # m
    max_distance_fine: float = 0.003           # m
    iterations: int = 30
    model_samples: int = 4000
    min_points: int = 50
    ok_fitness: float = 0.5
    ok_rmse: float = 0.002
    uncertain_fitness: float = 0.2


@dataclass
class ICPResult:
    T_base_bone: np.ndarray
    status: str
    fitness: float
    rmse: float
    position_spread: float = float("nan")
    rotation_spread: float = float("nan")
    ess_ratio: float = float("nan")
    log_likelihood_max: float = float("nan")
    timings: dict = field(default_factory=dict)


class ICPTracker:
    """Point-to-plane ICP tracker of ``T_base_bone`` (see the module docstring)."""

    def __init__(self, params: ICPParams, mesh, camera: PinholeCamera):
        import open3d as o3d

        self.o3d = o3d
        self.params = params
        self.camera = camera.resized(*params.resolution)
        points, face_index = _sample_surface(mesh, params.model_samples)
        self.model_points = points
        self.model_normals = np.asarray(mesh.face_normals)[face_index]
        self.radius = float(np.max(np.linalg.norm(points - points.mean(0), axis=1)))
        self.centre_bone = points.mean(0)
        self.T_base_bone = None
        self.gl_description = "Open3D ICP (CPU)"
        self.mesh_vertices = np.asarray(mesh.vertices)
        self.mesh_faces = np.asarray(mesh.faces)
        self.T_flange_camera = None
        self._timings: dict[str, float] = {}
        self._frames = 0

    def start(self, T_base_bone: np.ndarray) -> None:
        self.T_base_bone = np.asarray(T_base_bone, dtype=float).copy()

    def process(self, depth_m: np.ndarray, stamp: float, T_base_camera: np.ndarray | None) -> ICPResult:
        t0 = time.perf_counter()
        if T_base_camera is None:
            return self._result("uncertain", 0.0, float("nan"), t0)
        depth = downsample_nearest(depth_m, *self.params.resolution)
        p_camera, _ = self.camera.backproject(depth)
        p_base = se3.transform_points(T_base_camera, p_camera)
        centre_base = se3.transform_points(self.T_base_bone, self.centre_bone[None])[0]
        near = np.linalg.norm(p_base - centre_base, axis=1) < self.radius + self.params.crop_margin
        scene = self.o3d.geometry.PointCloud(self.o3d.utility.Vector3dVector(p_base[near]))
        scene = scene.voxel_down_sample(self.params.voxel)
        if len(scene.points) < self.params.min_points:
            return self._result("lost", 0.0, float("nan"), t0)
        model = self.o3d.geometry.PointCloud(self.o3d.utility.Vector3dVector(se3.transform_points(self.T_base_bone, self.model_points)))
        model.normals = self.o3d.utility.Vector3dVector(self.model_normals @ self.T_base_bone[:3, :3].T)
        reg = self.o3d.pipelines.registration
        estimation = reg.TransformationEstimationPointToPlane()
        criteria = reg.ICPConvergenceCriteria(max_iteration=self.params.iterations)
        T_delta = np.eye(4)
        for distance in (self.params.max_distance_coarse, self.params.max_distance_fine):
            result = reg.registration_icp(scene, model, distance, T_delta, estimation, criteria)
            T_delta = np.asarray(result.transformation)
        if np.all(np.isfinite(T_delta)):
            self.T_base_bone = se3.inverse(T_delta) @ self.T_base_bone
        fitness, rmse = float(result.fitness), float(result.inlier_rmse)
        if fitness >= self.params.ok_fitness and rmse <= self.params.ok_rmse:
            status = "ok"
        elif fitness >= self.params.uncertain_fitness:
            status = "uncertain"
        else:
            status = "lost"
        return self._result(status, fitness, rmse, t0)

    def _result(self, status: str, fitness: float, rmse: float, t0: float) -> ICPResult:
        seconds = time.perf_counter() - t0
        self._timings["icp"] = self._timings.get("icp", 0.0) + seconds
        self._frames += 1
        return ICPResult(self.T_base_bone.copy(), status, fitness, rmse, timings={"icp": seconds})

    def particle_positions(self) -> np.ndarray:
        return self.T_base_bone[None, :3, 3]

    def mean_timings_ms(self) -> dict[str, float]:
        return {k: 1e3 * v / max(self._frames, 1) for k, v in self._timings.items()}

    def release(self) -> None:
        pass


def _sample_surface(mesh, count: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    points, face_index = trimesh.sample.sample_surface_even(mesh, count, seed=0)
    return np.asarray(points), np.asarray(face_index)
