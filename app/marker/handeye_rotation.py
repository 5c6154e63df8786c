"""IMU-to-marker rotation: AX = XB on rotations, closed form (Park & Martin 1994; publication C eq. 7-15).

Import as ``from app.marker import handeye_rotation as handeye``.

Both sensors sit in one box: the marker frame M and the IMU's sensor frame S differ by a fixed
rotation X = R_S_M. For two instants i, j with simultaneous marker orientations R_C_M (camera) and
IMU orientations R_W_S (the IMU's world), the relative motions

    A = R_W_S(i)^T R_W_S(j)      (the box's motion seen by the IMU, in S)
    B = R_C_M(i)^T R_C_M(j)      (the same motion seen by the camera, in M)

satisfy A X = X B. With α = log A and β = log B (rotation vectors), α = X β; Park & Martin's
least-squares solution is

    M = Σ_j β_j α_j^T,     X = (M^T M)^{-1/2} M^T,

computed here as the orthogonal polar factor of M^T by an SVD (with the determinant forced to +1,
which only matters for degenerate inputs). It needs at least two motions about non-parallel axes.

The frames in which A and B are expressed (W, C) cancel, so the IMU's yaw drift only enters through
the drift during each pair's interval: pairs are taken close in time (:func:`motion_pairs`).

Noise: with orientation noise σ (rad, per axis) on each sample and K pairs of rotation angle θ about
well-spread axes, the error of X is about 2σ / (θ √(K/3)) (each α, β carries ≈ √2 σ per axis; the fit
averages K pairs over 3 axes). Tests check this bound with a factor of safety.

OpenCV's ``calibrateHandEye(..., method=CALIB_HAND_EYE_PARK)`` solves the full AX = XB with
translations; the IMU gives none, so this rotation-only form is used, and the tests compare it with
OpenCV's rotation on the same data.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def solve_rotation_axxb(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with A_j X = X B_j in the least-squares sense (Park & Martin).

    A, B : (K, 3, 3) relative rotations (A in the frame of X's rows, B in X's columns).
    Returns X : (3, 3).
    """
    A = np.asarray(A, float)
    B = np.asarray(B, float)
    if A.shape != B.shape or A.ndim != 3 or A.shape[1:] != (3, 3) or len(A) < 2:
        raise ValueError(f"need A and B of equal shape (K>=2, 3, 3), got {A.shape} and {B.shape}")
    alpha = Rotation.from_matrix(A).as_rotvec()
    beta = Rotation.from_matrix(B).as_rotvec()
    M = beta.T @ alpha                      # Σ β_j α_j^T
    U, s, Vt = np.linalg.svd(M.T)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise ValueError("degenerate motions: the rotation axes are (nearly) parallel; rotate the box about "
                         "at least two different axes")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt                       # (M^T M)^{-1/2} M^T


def motion_pairs(R_W_S: np.ndarray, R_C_M: np.ndarray, min_angle: float = np.deg2rad(10.0),
                 max_lag: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Relative motions (A, B) from simultaneous orientation samples.

    R_W_S, R_C_M : (N, 3, 3) IMU and marker orientations at the same instants.
    Pairs (i, j) with 0 < j - i <= max_lag whose IMU rotation exceeds ``min_angle`` (rad).
    """
    R_W_S = np.asarray(R_W_S, float)
    R_C_M = np.asarray(R_C_M, float)
    A, B = [], []
    for lag in range(1, max_lag + 1):
        a = np.einsum("nji,njk->nik", R_W_S[:-lag], R_W_S[lag:])
        b = np.einsum("nji,njk->nik", R_C_M[:-lag], R_C_M[lag:])
        keep = np.linalg.norm(Rotation.from_matrix(a).as_rotvec(), axis=1) >= min_angle
        A.append(a[keep])
        B.append(b[keep])
    return np.concatenate(A), np.concatenate(B)


def residuals(A: np.ndarray, B: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Angles (K,) in radians of A_j X (X B_j)^T: how far each pair is from A X = X B."""
    return np.linalg.norm(Rotation.from_matrix(A @ X @ np.swapaxes(X @ B, 1, 2)).as_rotvec(), axis=1)


def calibrate_imu_to_marker(R_W_S: np.ndarray, R_C_M: np.ndarray, min_angle: float = np.deg2rad(10.0),
                            max_lag: int = 10, outlier_factor: float | None = 3.0) -> tuple[np.ndarray, dict]:
    """X = R_S_M from simultaneous IMU and marker orientations; also residuals.

    With ``outlier_factor``, pairs whose residual exceeds that many times the median residual (a
    marker pose flipped by the planar ambiguity, a wrong detection) are dropped once and X is solved
    again. Returns X (3, 3) and ``{'pairs', 'pairs_used', 'residual_deg_mean', 'residual_deg_max'}``
    over the pairs used.
    """
    A, B = motion_pairs(R_W_S, R_C_M, min_angle, max_lag)
    if len(A) < 2:
        raise ValueError(f"only {len(A)} motion pairs above {np.rad2deg(min_angle):.1f} deg: move the box more")
    X = solve_rotation_axxb(A, B)
    res = residuals(A, B, X)
    used = np.ones(len(A), bool)
    if outlier_factor is not None:
        used = res <= outlier_factor * max(np.median(res), 1e-9)
        if 2 <= used.sum() < len(A):
            X = solve_rotation_axxb(A[used], B[used])
            res = residuals(A[used], B[used], X)
    res = np.rad2deg(res)
    return X, {"pairs": int(len(A)), "pairs_used": int(used.sum()), "residual_deg_mean": float(res.mean()),
               "residual_deg_max": float(res.max())}
