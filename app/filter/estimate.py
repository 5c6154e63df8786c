"""The filter's output: weighted mean pose and the particle spread.

Import as ``from app.filter import estimate``. DESIGN.md "Output": the position is the weighted
mean Σ W_j p_j; the orientation is the weighted quaternion mean, the principal eigenvector of
Σ W_j q_j q_jᵀ (Markley et al. 2007), insensitive to the sign of each q_j; (B) found this less
jittery than the maximum-likelihood particle. W = exp(lw - LSE(lw)).

Spread, the tracker's own uncertainty (used by :mod:`app.filter.status`):
- position: sqrt(trace(Σ_j W_j (p_j - p̄)(p_j - p̄)ᵀ)), metres (the RMS distance to the mean);
  per-axis standard deviations too;
- orientation: sqrt(Σ_j W_j θ_j²), radians, θ_j the angle between q_j and the mean (RMS angle);
- the template's points (issue 32, the status's one lost spread): for a point x (bone frame) the RMS
  distance of its particles' images R_j x + p_j to their weighted mean, the largest over the points
  (:func:`template_spread`). Its bound, by Minkowski's inequality on
  R_j x + p_j - (R̄ x + p̄) = (p_j - p̄) + (R_j R̄ᵀ - I) R̄ x with |(R_j R̄ᵀ - I) y| <= θ_j |y|:
  spread(x) <= position spread + rotation spread |x| (the RMS about the points' own mean is at most
  the RMS about any fixed point).
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

    Per frame, so written for speed: the quaternion mean, the angles and the pose are those of
    quat.weighted_mean, quat.angle_between and se3.from_quat_trans with the same arithmetic (the
    same values to the bit, tests/test_estimate_fast.py), without their validation and broadcasting.
    """
    W = normalised_weights(lw)
    p_mean = W @ p
    d = p - p_mean
    cov = np.einsum("n,ni,nj->ij", W, d, d)
    q_mean = _weighted_mean_quaternion(q, W)
    theta = _angles_to(q, q_mean)
    return PoseEstimate(
        T_base_bone=_pose(q_mean, p_mean),
        position_spread=float(np.sqrt(max(np.trace(cov), 0.0))),
        position_std=np.sqrt(np.maximum(np.diag(cov), 0.0)),
        rotation_spread=float(np.sqrt(W @ theta**2)),
    )


def template_spread(p: np.ndarray, q: np.ndarray, lw: np.ndarray, points_bone: np.ndarray,
                    pose: PoseEstimate, limit: float, reach: float | None = None) -> float:
    """m, the template's points' spread over the particles (module docstring): the largest over the points
    of sqrt(Σ_j W_j |R_j x + p_j - Σ_k W_k (R_k x + p_k)|²). Computed only where it could exceed ``limit``:
    when the bound position_spread + rotation_spread max|x| is within ``limit`` the bound is returned
    (a frame at rest costs nothing; the status compares it with ``limit`` only). ``reach``: max|x| (m) when
    the caller keeps it (the filter's :attr:`app.filter.motion_gate.MotionGate.reach`), else computed here.

    Exact over every point, in closed form: with R̄ = Σ W_j R_j, p̄ = Σ W_j p_j, ΔR_j = R_j - R̄ and
    Δp_j = p_j - p̄, the variance at x is xᵀ A x + 2 bᵀ x + c with A = Σ W_j ΔR_jᵀ ΔR_j, b = Σ W_j ΔR_jᵀ Δp_j
    and c = Σ W_j |Δp_j|² (3x3 sums over the particles once, then 3x3 per point; it was a subsample of 64
    of the points before 2026-11-28, which could miss the largest)."""
    points_bone = np.asarray(points_bone, float).reshape(-1, 3)
    if reach is None:
        reach = float(np.max(np.linalg.norm(points_bone, axis=1)))
    bound = pose.position_spread + pose.rotation_spread * reach
    if bound <= limit or not np.isfinite(bound):
        return float(bound)
    W = normalised_weights(lw)
    R = quat.to_matrix(q)                                                    # (N, 3, 3)
    dR = R - np.einsum("n,nij->ij", W, R)[None]
    dp = p - (W @ p)[None]
    A = np.einsum("n,nki,nkj->ij", W, dR, dR)
    b = np.einsum("n,nki,nk->i", W, dR, dp)
    c = float(W @ np.einsum("ni,ni->n", dp, dp))
    var = np.einsum("mi,ij,mj->m", points_bone, A, points_bone) + 2.0 * points_bone @ b + c
    return float(np.sqrt(max(float(np.max(var)), 0.0)))


def _weighted_mean_quaternion(q: np.ndarray, W: np.ndarray) -> np.ndarray:
    """quat.weighted_mean(q, W) for finite non-negative W with a positive sum (Markley et al. 2007)."""
    if not np.all(np.isfinite(W)) or not W.sum() > 0:
        return quat.weighted_mean(q, W)          # raises its clear error
    M = np.einsum("n,ni,nj->ij", W / W.sum(), q, q)
    mean = np.linalg.eigh(M)[1][:, -1]
    return -mean if mean[0] < 0 else mean


def _angles_to(q: np.ndarray, q_mean: np.ndarray) -> np.ndarray:
    """(N,) quat.angle_between(q, q_mean[None]): 2 atan2(|vec(d)|, |scal(d)|), d = q_j* ⊗ q_mean."""
    c = q * np.array([1.0, -1.0, -1.0, -1.0])
    w1, x1, y1, z1 = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
    w2, x2, y2, z2 = (float(x) for x in q_mean)
    vec = np.empty((len(q), 3))
    vec[:, 0] = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    vec[:, 1] = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    vec[:, 2] = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    scal = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    return 2.0 * np.arctan2(np.linalg.norm(vec, axis=-1), np.abs(scal))


def _pose(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """se3.from_quat_trans of one quaternion (4,) and translation (3,)."""
    w, x, y, z = (float(v) for v in q)
    T = np.zeros((4, 4))
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = t
    T[3, 3] = 1.0
    return T
