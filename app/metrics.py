"""Pose error metrics ((B) section 6.1; BOP's pose_error.py for the definitions).

All poses are 4x4 ``T_base_bone`` (the bone in the robot base frame); model points are in the bone
frame, metres. Results are in metres and radians; callers convert for display.

- ADD (Hinterstoisser et al. 2012): mean distance between model points under the two poses.
- ADD-S: mean distance from each point under the estimate to the closest point under the truth
  (symmetric objects).
- translation error: |t_est - t_gt|; rotation error: angle of R_est^T R_gt.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from app.geometry import se3


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (M, 3) mapped by T (4, 4)."""
    return points @ T[:3, :3].T + T[:3, 3]


def add(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD: mean_i |T_est p_i - T_gt p_i| (metres)."""
    return float(np.linalg.norm(transform(T_est, points) - transform(T_gt, points), axis=1).mean())


def add_s(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD-S: mean_i min_j |T_est p_i - T_gt p_j| (metres)."""
    distances, _ = cKDTree(transform(T_gt, points)).query(transform(T_est, points), k=1)
    return float(distances.mean())


def translation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """|t_est - t_gt| (metres)."""
    return float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


def rotation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Angle of R_est^T R_gt (radians, in [0, pi])."""
    return float(se3.rotation_angle(T_est, T_gt))


def summarise(values) -> dict[str, float]:
    """median, p95, max (and mean) of a sequence, ignoring NaN; NaN when empty."""
    arr = np.asarray(values, dtype=float)
    arr = arr[np.isfinite(arr)]
    if arr.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "max": float("nan"), "mean": float("nan")}
    return {"median": float(np.median(arr)), "p95": float(np.percentile(arr, 95)),
            "max": float(arr.max()), "mean": float(arr.mean())}
