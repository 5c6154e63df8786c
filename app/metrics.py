"""Pose error metrics ((B) section 6.1; the BOP toolkit's ``pose_error.py`` for the definitions).

All poses are 4x4 ``T_base_bone`` (the bone in the robot base frame; any common frame works) and
model points ``p_i`` (M, 3) are in the bone frame, metres. Results are in metres and radians
(VSD: a unitless fraction); callers convert for display.

Point-distance errors, with ``x_i = T_est p_i`` and ``y_i = T_gt p_i``:

- ADD (Hinterstoisser et al. 2012):  ``mean_i |x_i - y_i|``
- ADD-S (symmetric objects):        ``mean_i min_j |x_i - y_j|``
- MDD (maximum distance deviation):  ``max_i |x_i - y_i|``
- MDD-S (its symmetric variant):     ``max_i min_j |x_i - y_j|`` -- the largest distance from the
  estimated surface to the true one, BOP's MSSD without an explicit symmetry list; an upper bound
  on how far any projected template point can sit off the bone's surface.
- translation error ``|t_est - t_gt|``; rotation error: the angle of ``R_est^T R_gt`` in [0, pi].

Visible surface discrepancy (Hodan et al. 2016; BOP 2019 variant), from the model's depth
rendered at the estimate (``D_est``) and at the truth (``D_gt``) and the measured depth ``D``
(0 = no measurement), all converted to distances along the pixel rays when ``K`` is given:

- visibility of the truth: ``V_gt = D_gt > 0  and  (D_gt - D <= delta  or  D == 0)``
- of the estimate: ``V_est = (D_est > 0 and (D_est - D <= delta or D == 0))  or  (V_gt and D_est > 0)``
- ``e_VSD = (sum_{V_gt & V_est} [|D_est - D_gt| >= tau] + |V_gt xor V_est|) / |V_gt | V_est|``
  (1 when the union is empty). ``tau`` = 20 mm as in (B), ``delta`` = 15 mm as in BOP; a pose is
  correct when ``e_VSD < 0.3``; the recall is the fraction of correct poses.

``summarise`` gives median / p95 / max / mean of per-frame values; ``recall`` the fraction of
values below a threshold.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from app.geometry import se3

VSD_TAU = 0.020        # m, misalignment tolerance of VSD ((B) 6.1)
VSD_DELTA = 0.015      # m, visibility tolerance (BOP)
VSD_THRESHOLD = 0.3    # e_VSD below this: the pose counts as correct ((B) 6.1)
LOST_ADD_MM = 10.0     # a frame whose ADD exceeds this is lost (issue 3's definition), whatever its status
DANGEROUS_ADD_MM = 5.0  # status ok while ADD exceeds this: the confident wrong pose, which must never happen
STATUS_CODE = {"ok": 0, "uncertain": 1, "lost": 2}   # a status as a number (rerun scalars; ranking: worse is higher)


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (M, 3) mapped by T (4, 4)."""
    return points @ T[:3, :3].T + T[:3, 3]


def _pointwise(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(transform(T_est, points) - transform(T_gt, points), axis=1)


def _closest(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray, tree: cKDTree | None = None) -> np.ndarray:
    tree = tree if tree is not None else cKDTree(transform(T_gt, points))
    distances, _ = tree.query(transform(T_est, points), k=1)
    return distances


def add(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD: mean_i |T_est p_i - T_gt p_i| (metres)."""
    return float(_pointwise(T_est, T_gt, points).mean())


def add_s(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD-S: mean_i min_j |T_est p_i - T_gt p_j| (metres)."""
    return float(_closest(T_est, T_gt, points).mean())


def mdd(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """MDD: max_i |T_est p_i - T_gt p_i| (metres)."""
    return float(_pointwise(T_est, T_gt, points).max())


def mdd_s(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """MDD-S: max_i min_j |T_est p_i - T_gt p_j| (metres), the symmetric maximum distance."""
    return float(_closest(T_est, T_gt, points).max())


def symmetric_errors(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ADD-S and MDD-S of a sequence of poses (N, 4, 4) each, one KD-tree per frame (metres, (N,))."""
    T_est = np.asarray(T_est, dtype=float).reshape(-1, 4, 4)
    T_gt = np.asarray(T_gt, dtype=float).reshape(-1, 4, 4)
    # distances are invariant under a common rigid motion: express the estimate in the truth's bone
    # frame, so one KD-tree of the model points serves every frame
    tree = cKDTree(points)
    mean, maximum = np.empty(len(T_est)), np.empty(len(T_est))
    for k, (Te, Tg) in enumerate(zip(T_est, T_gt)):
        d, _ = tree.query(transform(se3.inverse(Tg) @ Te, points), k=1)
        mean[k], maximum[k] = d.mean(), d.max()
    return mean, maximum


def translation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """|t_est - t_gt| (metres)."""
    return float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


def rotation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Angle of R_est^T R_gt (radians, in [0, pi])."""
    return float(se3.rotation_angle(T_est, T_gt))


def depth_to_distance(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Distance along each pixel's ray (H, W) from a z-depth image (H, W), K (3, 3); 0 stays 0."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    scale = np.sqrt(((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
    return np.where(np.isfinite(depth) & (depth > 0), depth * scale, 0.0)


def vsd(depth_est: np.ndarray, depth_gt: np.ndarray, depth_measured: np.ndarray, K: np.ndarray | None = None,
        tau: float = VSD_TAU, delta: float = VSD_DELTA) -> float:
    """Visible surface discrepancy (module docstring), a fraction in [0, 1].

    Parameters
    ----------
    depth_est, depth_gt : (H, W) the model's depth rendered at the estimated / true pose, metres, 0 = not covered
    depth_measured : (H, W) the measured depth, metres, 0 or non-finite = no measurement
    K : (3, 3) intrinsics; given, depths become distances along the rays (BOP); None compares z
    tau : m, misalignment tolerance (step cost); delta : m, visibility tolerance
    """
    d_est, d_gt, d_meas = (np.where(np.isfinite(d) & (d > 0), np.asarray(d, dtype=float), 0.0)
                           for d in (depth_est, depth_gt, depth_measured))
    if not (d_est.shape == d_gt.shape == d_meas.shape):
        raise ValueError(f"depth images differ in shape: {d_est.shape}, {d_gt.shape}, {d_meas.shape}")
    if K is not None:
        d_est, d_gt, d_meas = (depth_to_distance(d, K) for d in (d_est, d_gt, d_meas))
    no_meas = d_meas == 0
    visible_gt = (d_gt > 0) & ((d_gt - d_meas <= delta) | no_meas)
    visible_est = ((d_est > 0) & ((d_est - d_meas <= delta) | no_meas)) | (visible_gt & (d_est > 0))
    union = visible_gt | visible_est
    n_union = int(union.sum())
    if n_union == 0:
        return 1.0
    inter = visible_gt & visible_est
    misaligned = int((np.abs(d_est[inter] - d_gt[inter]) >= tau).sum())
    return float((misaligned + n_union - int(inter.sum())) / n_union)


def recall(values, threshold: float) -> float:
    """Fraction of values strictly below ``threshold`` (NaN counts as a failure); NaN when empty."""
    arr = np.asarray(values, dtype=float).ravel()
    if arr.size == 0:
        return float("nan")
    return float(np.mean(np.nan_to_num(arr, nan=np.inf) < threshold))


def vsd_recall(values, threshold: float = VSD_THRESHOLD) -> float:
    """Fraction of frames whose e_VSD is below ``threshold`` (0.3, (B) 6.1)."""
    return recall(values, threshold)


def summarise(values) -> dict[str, float]:
    """median, p95, max (and mean) of a sequence, ignoring NaN; NaN when empty."""
    arr = np.asarray(values, dtype=float)
    arr = arr[np.isfinite(arr)]
    if arr.size == 0:
        return {"median": float("nan"), "p95": float("nan"), "max": float("nan"), "mean": float("nan")}
    return {"median": float(np.median(arr)), "p95": float(np.percentile(arr, 95)),
            "max": float(arr.max()), "mean": float(arr.mean())}
