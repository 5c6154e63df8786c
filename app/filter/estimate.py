"""The filter's output: weighted mean pose and the particle spread.

Import as ``from app.filter import estimate``. DESIGN.md "Output": the position is the weighted
mean Σ W_j p_j; the orientation is the weighted quaternion mean, the principal eigenvector of
Σ W_j q_j q_jᵀ (Markley et al. 2007), insensitive to the sign of each q_j; (B) found this less
jittery than the maximum-likelihood particle. W = exp(lw - LSE(lw)).

Spread, the tracker's own uncertainty (used by :mod:`app.filter.status`):
- position: sqrt(trace(Σ_j W_j (p_j - p̄)(p_j - p̄)ᵀ)), metres (the RMS distance to the mean);
  per-axis standard deviations too;
- orientation: sqrt(Σ_j W_j θ_j²), radians, θ_j the angle between q_j and the mean (RMS angle).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.filter.weights import normalised_weights
from app.geometry import quaternion as quat
from app.geometry import se3


@dataclass
class PoseEstimate:
    """T_base_bone (4, 4); position_spread (m); position_std (3,) m per base axis; rotation_spread (rad)."""

    T_base_bone: np.ndarray
    position_spread: float
    position_std: np.ndarray
    rotation_spread: float


def weighted_mean_pose(p: np.ndarray, q: np.ndarray, lw: np.ndarray) -> np.ndarray:
    """(4, 4) pose from the weighted mean position (N, 3) and quaternion mean (N, 4) under lw (N,)."""
    W = normalised_weights(lw)
    return se3.from_quat_trans(quat.weighted_mean(q, W), W @ p)


def estimate(p: np.ndarray, q: np.ndarray, lw: np.ndarray) -> PoseEstimate:
    """Weighted mean pose and spreads (module docstring) of particles (p, q) under log-weights lw.

    Parameters
    ----------
    p : (N, 3) m, positions in the base frame
    q : (N, 4) unit quaternions (w, x, y, z), any signs
    lw : (N,) log-weights, not all -inf
    """
    W = normalised_weights(lw)
    p_mean = W @ p
    d = p - p_mean
    cov = np.einsum("n,ni,nj->ij", W, d, d)
    q_mean = quat.weighted_mean(q, W)
    theta = quat.angle_between(q, q_mean[None])
    return PoseEstimate(
        T_base_bone=se3.from_quat_trans(q_mean, p_mean),
        position_spread=float(np.sqrt(max(np.trace(cov), 0.0))),
        position_std=np.sqrt(np.maximum(np.diag(cov), 0.0)),
        rotation_spread=float(np.sqrt(W @ theta**2)),
    )
