"""Observation models: what the particle filter needs from the evidence of one frame.

Import as ``from app.filter.observation import ObservationModel, Evidence, CompositeObservation``.
An observation model (DESIGN.md "Observation"; the "modality" of Stoiber's M3T) scores N pose
hypotheses against one frame and reports its own evidence for the tracking status: how many of an
estimate's pixels it measured, what share of them the estimate explains, whether occluders hide the
bone. The filter (:mod:`app.filter.particle_filter`) knows only this Protocol.

Implementations:

- the depth likelihood backends (:class:`LikelihoodBackend`, which also render depth): the GL one,
  :class:`app.render.likelihood.GLLikelihoodBackend` (batched GL rendering + compute shader; fast on a
  GPU), and the CPU one, :class:`app.render.cpu_likelihood.CPULikelihoodBackend` (exact numba z-buffer
  fused with the pixel term; fast without one). Both score with the model of
  :mod:`app.filter.likelihood_ref` (the specification) and report :func:`depth_evidence`;
- :class:`CompositeObservation`, the sum of several models (M3T's "link"):
  log p(z_1, ..., z_K | x) = Σ_k log p(z_k | x) for conditionally independent evidence.

``tests/test_backend_conformance.py`` holds the tests every model must pass against the numpy
reference; a new backend is added by passing them and listing it in :data:`BACKENDS`. The choice is
the tracker config's ``render.backend``: 'gl', 'cpu', or 'auto' (cpu when the GL context is a
software renderer such as Mesa's llvmpipe, gl on a GPU; :mod:`app.render.backends`).

**Non-finite policy** (one for the whole application): a NaN or +inf log-likelihood is a model's
failure, never a value; :func:`finite_log_likelihood` turns it into -inf (zero likelihood) and
counts it. -inf itself is a legitimate value.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence, runtime_checkable

import numpy as np

from app.filter import likelihood_ref
from app.filter.likelihood_ref import LikelihoodParams
from app.filter.weights import nonfinite_mask

log = logging.getLogger(__name__)

BACKENDS = ("auto", "gl", "cpu")  # values of render.backend


@dataclass(frozen=True)
class Evidence:
    """A model's evidence about one pose estimate in one frame (for the status rules).

    covered_pixels : measured pixels the pose covers that no occluder hides (app/filter/status.py)
    inliers : of those, the pixels the pose explains (within the model's noise)
    bone_hidden : occluders hide the bone: fewer than the filter's ``min_covered_pixels`` are left
    """

    covered_pixels: int
    inliers: int
    bone_hidden: bool

    @property
    def inlier_fraction(self) -> float:
        """inliers / covered_pixels (NaN when nothing is covered)."""
        return self.inliers / self.covered_pixels if self.covered_pixels else float("nan")


@runtime_checkable
class ObservationModel(Protocol):
    """Scores N pose hypotheses against one frame and reports its own evidence.

    ``name`` : short name ('gl', 'cpu', 'gl+colour'); ``timings`` : seconds per stage of the last
    ``log_likelihood`` call (stage names are the model's own).
    """

    name: str
    timings: dict[str, float]

    def log_likelihood(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray) -> np.ndarray:
        """(N, 4, 4) float64 poses, (h, w) float32 metres (0 / non-finite invalid) -> (N,) float64
        log p(z | x_j) (for the depth backends: :func:`app.filter.likelihood_ref.log_likelihood`)."""
        ...

    def has_measurement(self, depth_meas: np.ndarray) -> bool:
        """Whether the frame holds anything this model can weigh (a valid pixel)."""
        ...

    def evidence(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray, min_covered_pixels: int) -> Evidence:
        """The :class:`Evidence` of one pose (4, 4) in this frame; hidden below ``min_covered_pixels``."""
        ...

    def describe(self) -> str:
        """One line naming the model and where it runs (summaries, logs, benchmarks)."""
        ...

    def release(self) -> None:
        """Free the model's resources (GL objects); the model is unusable afterwards."""
        ...


@runtime_checkable
class LikelihoodBackend(ObservationModel, Protocol):
    """A depth observation model that renders the hypotheses (GL or CPU) at the filter resolution."""

    def render_depth(self, T_camera_bone: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses -> (N, h, w) float32 linear depth in metres, image row order, 0 = not covered."""
        ...

    def sync(self) -> None:
        """Wait until the work issued so far is done (benchmarks time whole frames with it)."""
        ...


def finite_log_likelihood(log_lik: np.ndarray) -> tuple[np.ndarray, int]:
    """The non-finite policy: (a float64 copy with NaN / +inf set to -inf, how many were set).

    The caller reports the count (the filter's ``n_nan``); a warning is logged when it is not 0.
    """
    log_lik = np.array(log_lik, dtype=float)
    bad = nonfinite_mask(log_lik)
    n_bad = int(bad.sum())
    if n_bad:
        log.warning("%d of %d log-likelihoods are NaN or +inf: weighted as -inf", n_bad, len(log_lik))
        log_lik[bad] = -np.inf
    return log_lik, n_bad


def has_valid_depth(depth_meas: np.ndarray | None, params: LikelihoodParams) -> bool:
    """Whether any pixel is a valid measurement (finite, 0 < z <= z_max)."""
    return depth_meas is not None and bool(np.any(likelihood_ref.valid_measurement(depth_meas, params)))


def depth_evidence(render_depth: Callable[[np.ndarray], np.ndarray], T_camera_bone: np.ndarray,
                   depth_meas: np.ndarray, params: LikelihoodParams, min_covered_pixels: int) -> Evidence:
    """The depth models' evidence: render the pose once, count its valid covered pixels that no
    occluder hides and the inliers among them (|z - z*| < 3 σ(z*), :func:`likelihood_ref.inlier_mask`).

    A pixel measured more than ``params.occluder_margin`` in front of the rendered depth sees an
    occluder (a hand over the bone) and is left out of both counts (app/filter/status.py).
    """
    rendered = render_depth(np.asarray(T_camera_bone, dtype=float)[None])[0]
    valid = likelihood_ref.valid_measurement(depth_meas, params) & (rendered > 0)
    with np.errstate(invalid="ignore"):
        occluded = valid & (depth_meas < rendered - params.occluder_margin)
    considered = valid & ~occluded
    covered = int(considered.sum())
    inliers = int((likelihood_ref.inlier_mask(depth_meas, rendered, params) & considered).sum()) if covered else 0
    return Evidence(covered, inliers, covered < min_covered_pixels)


class CompositeObservation:
    """The sum of several observation models: log p(z | x) = Σ_k log p_k(z | x) (module docstring).

    Evidence combines as counts: covered pixels and inliers add up (the inlier fraction is the
    pooled share); the bone is hidden only when every model finds it hidden. Every model sees the
    same frame (each takes what it needs from it); one model alone scores exactly as itself.
    """

    def __init__(self, models: Sequence[ObservationModel]):
        if not models:
            raise ValueError("CompositeObservation needs at least one observation model")
        self.models = list(models)
        self.name = "+".join(m.name for m in self.models)
        self.timings: dict[str, float] = {}

    def log_likelihood(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray) -> np.ndarray:
        total = np.zeros(len(T_camera_bone), dtype=float)
        self.timings = {}
        for model in self.models:
            total = total + np.asarray(model.log_likelihood(T_camera_bone, depth_meas), dtype=float)
            self.timings.update({f"{model.name}_{k}": v for k, v in model.timings.items()})
        return total

    def has_measurement(self, depth_meas: np.ndarray) -> bool:
        return any(m.has_measurement(depth_meas) for m in self.models)

    def evidence(self, T_camera_bone: np.ndarray, depth_meas: np.ndarray, min_covered_pixels: int) -> Evidence:
        parts = [m.evidence(T_camera_bone, depth_meas, min_covered_pixels) for m in self.models]
        return Evidence(sum(e.covered_pixels for e in parts), sum(e.inliers for e in parts),
                        all(e.bone_hidden for e in parts))

    def describe(self) -> str:
        return " + ".join(m.describe() for m in self.models)

    def release(self) -> None:
        for model in self.models:
            model.release()
