"""Baseline tracker: frame-to-model point-to-plane ICP with Open3D.

What a user would otherwise pick, set up fairly for a bone in soft tissue. Each frame:

1. **Scene**: the measured depth, reduced to ``resolution`` by nearest neighbour, is cropped to the
   model's silhouette rendered at the last estimate (its camera-facing samples projected, the nearest
   depth per pixel, the outline grown by ``silhouette_px``), keeping the pixels whose depth lies
   within ``front_margin`` in front of and ``back_margin`` behind the rendered depth (tissue, hands and
   the table beyond that are not the bone), then to the bone's bounding sphere (+ ``crop_margin``)
   around its centre; back-projected, moved into the base frame with ``T_base_camera`` and
   voxel-downsampled.
2. **Model**: the surface samples (with normals) that face the camera, placed at the last estimate.
3. **Registration**: Open3D's point-to-plane ICP in ``passes`` passes whose correspondence distance
   decreases geometrically from ``max_distance_coarse`` to ``max_distance_fine`` (coarse to fine),
   ``iterations`` each. The correction ``T_delta`` maps scene points onto the model, so the new
   estimate is ``T_delta^-1 @ T_base_bone``.

Settings, measured on the eight CT crests (static_clear, 1.5 s, seeds 0 and 1; ADD = the mean distance
of the mesh's vertices from the truth): the former crop (a sphere 2 cm beyond the bone's radius,
which holds the tissue around the crest and the table) with 10 then 3 mm left the bone on the first
frames on every crest tried (crest_right_02: 82 mm after the first frame, 8,978 mm at the end;
crest_left_05: 328 mm). With these defaults every crest tracked on both seeds: ADD median 0.38-0.65 mm,
max 0.61-2.8 mm (the largest on the first frames, from the start 5 mm off), every frame ok. Grown by
2 px (5 mm at 0.42 m) the silhouette lets the tissue beside the crest in: crest_right_02 was lost
again (with a first distance of 6 or 4 mm) and crest_left_05 ended 8-10 mm off; without the depth
window crest_right_02 stayed near (median 1.7 mm, max 15.6) but was never ok.

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
from scipy import ndimage

from app.depth_image import downsample_nearest
from app.geometry import se3
from app.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)


@dataclass
class ICPParams:
    resolution: tuple[int, int] = (160, 120)   # depth is reduced by nearest neighbour first
    voxel: float = 0.002                       # m
    crop_margin: float = 0.002                 # m beyond the model's bounding sphere (around the last estimate)
    silhouette_px: int = 0                     # px (at ``resolution``): the model's rendered silhouette grown by this
    front_margin: float = 0.005                # m: measurements this far in front of the rendered model are left out
    back_margin: float = 0.010                 # m: ... and this far behind it
    max_distance_coarse: float = 0.006         # m, correspondence distance of the first pass
    max_distance_fine: float = 0.0015          # m, ... of the last pass
    passes: int = 4                            # passes, their distances geometric from coarse to fine
    iterations: int = 15                       # ICP iterations per pass
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
        p_base = self._scene(downsample_nearest(depth_m, *self.params.resolution), T_base_camera)
        scene = self.o3d.geometry.PointCloud(self.o3d.utility.Vector3dVector(p_base))
        scene = scene.voxel_down_sample(self.params.voxel)
        if len(scene.points) < self.params.min_points:
            return self._result("lost", 0.0, float("nan"), t0)
        facing = self._facing(T_base_camera)
        model = self.o3d.geometry.PointCloud(self.o3d.utility.Vector3dVector(
            se3.transform_points(self.T_base_bone, self.model_points[facing])))
        model.normals = self.o3d.utility.Vector3dVector(self.model_normals[facing] @ self.T_base_bone[:3, :3].T)
        reg = self.o3d.pipelines.registration
        estimation = reg.TransformationEstimationPointToPlane()
        criteria = reg.ICPConvergenceCriteria(max_iteration=self.params.iterations)
        T_delta = np.eye(4)
        for distance in self.distances():
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

    def distances(self) -> np.ndarray:
        """The passes' correspondence distances (m): geometric from ``max_distance_coarse`` to
        ``max_distance_fine`` over ``passes``."""
        prm = self.params
        if prm.passes <= 1:
            return np.array([prm.max_distance_fine])
        return np.geomspace(prm.max_distance_coarse, prm.max_distance_fine, prm.passes)

    def _facing(self, T_base_camera: np.ndarray) -> np.ndarray:
        """(S,) bool: the model samples that face the camera at the last estimate (the visible side's)."""
        T_camera_bone = se3.inverse(T_base_camera) @ self.T_base_bone
        p = se3.transform_points(T_camera_bone, self.model_points)
        n = self.model_normals @ T_camera_bone[:3, :3].T
        return (np.einsum("ij,ij->i", n, p) < 0) & (p[:, 2] > 0)

    def _scene(self, depth: np.ndarray, T_base_camera: np.ndarray) -> np.ndarray:
        """(M, 3) base-frame scene points: the measured pixels inside the model's silhouette rendered at
        the last estimate (its camera-facing samples, nearest depth per pixel, grown by ``silhouette_px``)
        whose depth lies within ``front_margin`` in front of / ``back_margin`` behind the rendered depth,
        and within the bone's bounding sphere (+ ``crop_margin``) of its centre."""
        prm, cam = self.params, self.camera
        T_camera_bone = se3.inverse(T_base_camera) @ self.T_base_bone
        facing = self._facing(T_base_camera)
        uv, z = cam.project(se3.transform_points(T_camera_bone, self.model_points[facing]))
        col, row = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        inside = (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height) & (z > 0)
        z_model = np.full((cam.height, cam.width), np.inf)
        np.minimum.at(z_model, (row[inside], col[inside]), z[inside])
        if prm.silhouette_px > 0:
            z_model = ndimage.minimum_filter(z_model, size=2 * prm.silhouette_px + 1, mode="constant", cval=np.inf)
        with np.errstate(invalid="ignore"):
            keep = (depth > 0) & np.isfinite(z_model) & (depth >= z_model - prm.front_margin) \
                & (depth <= z_model + prm.back_margin)
        p_camera, _ = cam.backproject(np.where(keep, depth, 0.0))
        p_base = se3.transform_points(T_base_camera, p_camera)
        centre_base = se3.transform_points(self.T_base_bone, self.centre_bone[None])[0]
        near = np.linalg.norm(p_base - centre_base, axis=1) < self.radius + prm.crop_margin
        return p_base[near]

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
