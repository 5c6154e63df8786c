"""The likelihoods the one-point initialiser tempers through: the filter's, and cheaper ones at a
lower resolution, counted against one evaluation budget.

A sequence of SMC targets need not share one likelihood (Del Moral, Doucet & Jasra 2006): the
sampler draws and tempers at a coarse resolution first and moves to the filter's resolution at the
end (:meth:`app.filter.smc_init.tempering.Tempering.switch`). Between two levels the
log-likelihood scales by about the ratio of their pixel counts (a sum of per-pixel terms over the
same scene: ``Level.scale`` is the pixel count, or 1 with the pixel-count regularisation, which
divides the sum by the covered pixel count), so π ∝ p(x) p_a(z | x)^φ ≈ p(x) p_b(z | x)^(φ s_a / s_b).

Non-finite policy (the particle filter's, :mod:`app.filter.particle_filter`): a NaN or +inf
log-likelihood is a backend failure, scored as -inf (zero likelihood) and counted in
``Budget.nonfinite``; -inf is a legitimate value.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from app.depth_image import downsample_nearest
from app.filter import weights as lw_ops
from app.geometry import se3

log = logging.getLogger(__name__)

MIN_LEVEL_SIZE = (16, 12)   # px: coarser levels are not made (too few pixels to tell poses apart)


@dataclass
class Budget:
    """The initialisation's work: poses scored at every level (``evaluations``, the budget's unit),
    non-finite log-likelihoods met, the current run's evaluation ``limit`` and the wall-time safety
    net ``deadline`` (perf_counter s)."""

    evaluations: int = 0
    nonfinite: int = 0
    limit: int | None = None
    deadline: float | None = None

    def spent(self) -> bool:
        return self.limit is not None and self.evaluations >= self.limit

    def late(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline


@dataclass
class Level:
    """One likelihood: ``score(p, q)`` -> (N,) log p(z | x) of poses (base frame), ``name`` (e.g. '80x60')
    and ``scale``, what its log-likelihood scales with (see the module docstring)."""

    name: str
    score: Callable[[np.ndarray, np.ndarray], np.ndarray]
    scale: float = 1.0


def evaluate(level: Level, p: np.ndarray, q: np.ndarray, budget: Budget) -> np.ndarray:
    """(N,) log-likelihoods of ``level`` at poses (p, q), counted in ``budget``; NaN / +inf -> -inf, counted."""
    ll = np.asarray(level.score(p, q), dtype=float)
    budget.evaluations += len(p)
    bad = lw_ops.nonfinite_mask(ll)
    if bad.any():
        budget.nonfinite += int(bad.sum())
        log.warning("one-point initialisation: %d of %d log-likelihoods at %s are NaN or +inf: scored as -inf",
                    int(bad.sum()), len(ll), level.name)
        ll = np.where(bad, -np.inf, ll)
    return ll


def tempered(phi: float, ll: np.ndarray) -> np.ndarray:
    """φ log p(z | x) with a zero likelihood kept at -inf at every φ (0 · -inf would be NaN)."""
    return np.where(ll == -np.inf, -np.inf, phi * np.where(ll == -np.inf, 0.0, ll))


def backend_level(backend, camera, depth: np.ndarray, T_camera_base: np.ndarray, params=None) -> Level:
    """The level of a likelihood backend on ``depth`` (its resolution). The CPU backend scores any
    number of poses in one call (one parallel launch); others get ``capacity`` poses per call."""
    batch = None if getattr(backend, "name", "") == "cpu" else getattr(backend, "capacity", None)

    def score(p, q):
        T = T_camera_base @ se3.from_quat_trans(q, p)
        step = batch or max(len(T), 1)
        parts = [np.asarray(backend.log_likelihood(T[i:i + step], depth), float) for i in range(0, len(T), step)]
        return np.concatenate(parts) if parts else np.zeros(0)

    params = params if params is not None else getattr(backend, "params", None)
    per_pixel = params is not None and getattr(params, "pixel_count_reg", 0.0) > 0.0
    return Level(f"{camera.width}x{camera.height}", score, 1.0 if per_pixel else float(camera.width * camera.height))


def make_levels(backend, camera, depth: np.ndarray, T_base_camera: np.ndarray,
                coarse: tuple[tuple[int, int], ...]) -> list[Level]:
    """The likelihood levels, coarse to fine, ending with the filter's (``backend`` on ``depth``).

    ``coarse``: (divisor of the filter's resolution, triangle budget) per coarser level, e.g.
    ((4, 250), (2, 500)): 40x30 with the mesh decimated to 250 triangles and 80x60 with 500 below
    160x120 (the cost per pose is mostly per triangle: BENCHMARKS.md §5). They need a backend that
    can be rebuilt at another camera and mesh (``backend.resized``, the CPU backend); with any other
    backend only the filter's level is used, and a level under :data:`MIN_LEVEL_SIZE` or of the same
    size as another is skipped.
    """
    T_camera_base = se3.inverse(np.asarray(T_base_camera, float))
    full = backend_level(backend, camera, depth, T_camera_base)
    if not hasattr(backend, "resized"):
        return [full]
    levels, sizes = [], {(camera.width, camera.height)}
    for d, triangles in sorted(((int(d), int(t)) for d, t in coarse if int(d) > 1), reverse=True):
        w, h = camera.width // d, camera.height // d
        if w < MIN_LEVEL_SIZE[0] or h < MIN_LEVEL_SIZE[1] or (w, h) in sizes:
            continue
        sizes.add((w, h))
        small = camera.resized(w, h)
        levels.append(backend_level(_coarse_backend(backend, small, triangles), small, downsample_nearest(depth, w, h),
                                    T_camera_base))
    return levels + [full]


def _coarse_backend(backend, camera, triangles: int):
    """``backend`` at ``camera`` with its mesh decimated to ``triangles`` (culling kept only if the
    decimated mesh is still wound outwards)."""
    import trimesh

    from app.mesh import decimate, outward_wound

    if triangles >= len(backend.faces):
        return backend.resized(camera)
    mesh = decimate(trimesh.Trimesh(backend.vertices, backend.faces, process=False), triangles)
    cull = bool(backend.cull and outward_wound(mesh))
    return backend.resized(camera, np.asarray(mesh.vertices), np.asarray(mesh.faces), cull_back_faces=cull)
