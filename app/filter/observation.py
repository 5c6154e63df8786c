"""The likelihood backend contract: what the particle filter needs from an observation model.

Import as ``from app.filter.observation import LikelihoodBackend``. DESIGN.md "Observation": a
backend renders N pose hypotheses of the tracking mesh at the filter's resolution and scores each
against one measured depth image with the model of :mod:`app.filter.likelihood_ref` (the
specification). Implementations: :class:`app.render.likelihood.GLLikelihoodBackend` (batched GL
rendering + compute shader; fast on a GPU) and :class:`app.render.cpu_likelihood.CPULikelihoodBackend`
(exact numba z-buffer fused with the pixel term; fast without one). ``tests/test_backend_conformance.py``
holds the tests every backend must pass against the numpy reference; a new backend is added by
passing them and listing it in :data:`BACKENDS`.

The choice is the tracker config's ``render.backend``: 'gl', 'cpu', or 'auto' (cpu when the GL
context is a software renderer such as Mesa's llvmpipe, gl on a GPU; :mod:`app.render.backends`).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

BACKENDS = ("auto", "gl", "cpu")  # values of render.backend


class LikelihoodBackend(Protocol):
    """Scores N pose hypotheses against one measured depth image (filter resolution h x w).

    ``name`` : 'gl' | 'cpu'; ``timings`` : seconds per backend stage of the last
    ``log_likelihood`` call (stage names are the backend's own, e.g. render / likelihood /
    readback for gl).
    """

    name: str
    timings: dict[str, float]

    def log_likelihood(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray) -> np.ndarray:
        """(N, 4, 4) float64 poses, (h, w) float32 metres (0 / non-finite invalid) -> (N,) float64
        log p(z | x_j) of :func:`app.filter.likelihood_ref.log_likelihood`."""
        ...

    def render_depth(self, T_camera_bone: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses -> (N, h, w) float32 linear depth in metres, image row order, 0 = not covered."""
        ...

    def describe(self) -> str:
        """One line naming the backend and where it runs (summaries, logs, benchmarks)."""
        ...

    def sync(self) -> None:
        """Wait until the work issued so far is done (benchmarks time whole frames with it)."""
        ...

    def release(self) -> None:
        """Free the backend's resources (GL objects); the backend is unusable afterwards."""
        ...
