"""Geometry of the one-point initialiser: rotations between vectors, the measured normal at the
pointed point, rotations about it, and the mesh's half-turn self-symmetries (DESIGN.md
"Initialisation from one point"; the sampler: :mod:`app.filter.smc_init`).
"""
from __future__ import annotations

import hashlib

import numpy as np
from scipy.spatial import cKDTree

from app.geometry import quaternion as quat
from app.geometry import se3

_SYMMETRY_CACHE: dict[str, list[np.ndarray]] = {}


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) of the shortest rotations taking unit vectors a (N, 3) onto b (3,)."""
    b = np.broadcast_to(b, a.shape)
    w = 1.0 + np.sum(a * b, axis=1)
    xyz = np.cross(a, b)
    opposite = w < 1e-9   # a = -b: any axis orthogonal to a, by 180 degrees
    if opposite.any():
        ortho = np.cross(a[opposite], np.array([1.0, 0.0, 0.0]))
        small = np.linalg.norm(ortho, axis=1) < 1e-6
        ortho[small] = np.cross(a[opposite][small], np.array([0.0, 1.0, 0.0]))
        xyz[opposite], w[opposite] = ortho / np.linalg.norm(ortho, axis=1, keepdims=True), 0.0
    return quat.normalize(np.column_stack([w, xyz]))


def tangent_noise(normal: np.ndarray, sigma: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Rotation vectors (n, 3) ~ N(0, σ²) about axes orthogonal to ``normal``: tilts of the normal."""
    r = rng.normal(0.0, sigma, (n, 3))
    return r - np.outer(r @ normal, normal)


def rotate_about(point: np.ndarray, p: np.ndarray, q: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the rotations dq (N, 4) about ``point`` (3,) to poses (p, q): q' = dq ⊗ q, p' = point + R(dq)(p - point)."""
    return point[None] + quat.rotate(dq, p - point[None]), quat.normalize(quat.multiply(dq, q))


def measured_normal(depth: np.ndarray, camera, T_base_camera: np.ndarray, point_base: np.ndarray,
                    radius: float, min_points: int = 8) -> np.ndarray | None:
    """The surface normal (base frame, unit, facing the camera) of the measured points within ``radius``
    of ``point_base``: the smallest principal axis of their covariance; None with fewer than
    ``min_points`` such points (the pointed point hidden or unmeasured)."""
    T_camera_base = se3.inverse(np.asarray(T_base_camera, float))
    point_camera = T_camera_base[:3, :3] @ point_base + T_camera_base[:3, 3]
    points, _ = camera.backproject(np.where(np.isfinite(depth), depth, 0.0))
    near = points[np.linalg.norm(points - point_camera, axis=1) < radius]
    if len(near) < min_points:
        return None
    centred = near - near.mean(axis=0)
    normal = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    if normal @ point_camera > 0:   # face the camera (at the origin)
        normal = -normal
    return T_base_camera[:3, :3] @ normal


def mesh_symmetries(vertices: np.ndarray, faces: np.ndarray, max_residual: float = 0.003, n_samples: int = 4000,
                    iterations: int = 50, seed: int = 0) -> list[np.ndarray]:
    """The mesh's approximate half-turn self-symmetries S (4x4, bone frame): S(mesh) ≈ mesh.

    From the half turn about each principal axis through the centroid, a trimmed point-to-point ICP
    (Kabsch on the nearest 80 %) of the surface samples onto themselves, ``iterations`` times (on a
    ridge it keeps sliding by ~0.1-1 mm per iteration: no convergence test); a result is kept when
    the median distance of the moved samples to the surface is below ``max_residual`` (m). A crest is a ridge: turned end
    for end about its normal it nearly covers itself (the synthetic crest: 2.1 mm median; CT
    crest_right_03: 2.4 and 2.9 mm about two axes). Cached per mesh and arguments in the process
    (a tracker's initialisations, a benchmark's seeds): the result depends on nothing else.
    """
    vertices, faces = np.ascontiguousarray(vertices, float), np.ascontiguousarray(faces, np.int64)
    key = hashlib.sha1(vertices.tobytes() + faces.tobytes()
                       + repr((max_residual, n_samples, iterations, seed)).encode()).hexdigest()
    if key not in _SYMMETRY_CACHE:
        _SYMMETRY_CACHE[key] = _search_symmetries(vertices, faces, max_residual, n_samples, iterations, seed)
    return [S.copy() for S in _SYMMETRY_CACHE[key]]


def _search_symmetries(vertices, faces, max_residual, n_samples, iterations, seed) -> list[np.ndarray]:
    """:func:`mesh_symmetries` without the cache."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    pts, _ = trimesh.sample.sample_surface(mesh, n_samples, seed=seed)
    tree = cKDTree(pts)
    centre = pts.mean(axis=0)
    axes = np.linalg.eigh(np.cov((pts - centre).T))[1]
    found = []
    for k in range(3):
        R = quat.to_matrix(quat.exp_map(axes[:, k][None] * np.pi))[0]
        t = centre - R @ centre
        for _ in range(iterations):
            moved = pts @ R.T + t
            d, j = tree.query(moved)
            keep = d <= np.percentile(d, 80)
            dR, dt = kabsch(moved[keep], pts[j[keep]])
            R, t = dR @ R, dR @ t + dt
        if np.median(tree.query(pts @ R.T + t)[0]) < max_residual:
            found.append(se3.make_pose(R, t))
    return found


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R and translation t minimising |R a + t - b|² (Kabsch / Umeyama without scale)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca
