"""The one-point initialiser's prior p(x): the pointed point on the mesh surface, with the measured
normal's prior (the formulas: :mod:`app.filter.smc_init`)."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from app.filter.smc_init.geometry import rotation_between, tangent_noise
from app.geometry import quaternion as quat


class SurfacePrior:
    """log p(x) = -d(x)² / (2 σ_t²) [- ∠(R n(s*), n_z)² / (2 σ_n²)] of the package docstring."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, point_base: np.ndarray, sigma_t: float,
                 n_samples: int, rng: np.random.Generator):
        import trimesh

        mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
        self.surface_bone, face_index = trimesh.sample.sample_surface(mesh, int(n_samples),
                                                                      seed=int(rng.integers(2**31)))
        self.normals_bone = np.asarray(mesh.face_normals)[face_index]
        self.tree = cKDTree(self.surface_bone)
        self.point_base = np.asarray(point_base, dtype=float).reshape(3)
        self.sigma_t = float(sigma_t)
        self.normal_base: np.ndarray | None = None
        self.sigma_n = 0.0

    def set_normal(self, normal_base: np.ndarray | None, sigma_n: float) -> None:
        """Turn on the normal prior with the measured unit normal (base frame), or off (None)."""
        self.normal_base = None if normal_base is None or sigma_n <= 0 else np.asarray(normal_base, float)
        self.sigma_n = float(sigma_n)

    def nearest(self, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """d(x): distance (m) of the pointed point, in each particle's bone frame, to the surface; and
        the index of the nearest surface sample s*(x)."""
        point_bone = quat.rotate(quat.conjugate(q), self.point_base[None] - p)
        return self.tree.query(point_bone)

    def log_density(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        d, idx = self.nearest(p, q)
        lp = -0.5 * (d / self.sigma_t) ** 2
        if self.normal_base is not None:
            n_base = quat.rotate(q, self.normals_bone[idx])
            angle = np.arccos(np.clip(n_base @ self.normal_base, -1.0, 1.0))
            lp = lp - 0.5 * (angle / self.sigma_n) ** 2
        return lp

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Draws from the prior (approximately: the nearest surface point is taken to be the drawn one)."""
        k = rng.integers(len(self.surface_bone), size=n)
        if self.normal_base is None:
            q = quat.random_uniform(rng, n)
        else:  # R n(s) = n_z up to N(0, σ_n), then a uniform twist about n_z
            align = quat.normalize(rotation_between(self.normals_bone[k], self.normal_base))
            twist = quat.exp_map(self.normal_base[None] * rng.uniform(-np.pi, np.pi, (n, 1)))
            tilt = quat.exp_map(tangent_noise(self.normal_base, self.sigma_n, n, rng))
            q = quat.normalize(quat.multiply(tilt, quat.multiply(twist, align)))
        p = self.point_base[None] - quat.rotate(q, self.surface_bone[k]) + rng.normal(0.0, self.sigma_t, (n, 3))
        return p, q
