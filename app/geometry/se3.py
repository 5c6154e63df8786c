"""Rigid transforms SE(3) as 4x4 homogeneous matrices (row-major, translation in T[:3, 3]).

Import as ``from app.geometry import se3``. ``T_a_b`` is the pose of frame b in frame a: it maps
points from b to a, so ``T_a_c = T_a_b @ T_b_c`` (DESIGN.md, "Frames and conventions").
"""
from __future__ import annotations

import numpy as np

from app.geometry import quaternion as quat

RIGID_ATOL = 1e-6  # tolerance on R^T R = I and det R = 1 for poses read from files


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(..., 4, 4) pose from rotations (..., 3, 3) and translations (..., 3)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def from_quat_trans(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pose from unit quaternions (..., 4) (w, x, y, z) and translations (..., 3)."""
    return make_pose(quat.to_matrix(q), t)


def to_quat_trans(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(quaternions (..., 4) with w >= 0, translations (..., 3)) of poses (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    return quat.from_matrix(T[..., :3, :3]), T[..., :3, 3].copy()


def from_rotvec_trans(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pose from rotation vectors (axis * angle, rad) and translations."""
    return from_quat_trans(quat.exp_map(rotvec), t)


def inverse(T: np.ndarray) -> np.ndarray:
    """T^-1 = [R^T, -R^T t] in closed form, batched (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def compose(*Ts: np.ndarray) -> np.ndarray:
    """T_1 @ T_2 @ ... (left to right), e.g. ``compose(T_base_flange, T_flange_camera)``."""
    if not Ts:
        raise ValueError("compose needs at least one pose")
    out = np.asarray(Ts[0], dtype=float)
    for T in Ts[1:]:
        out = out @ T
    return out


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points (N, 3) mapped by one pose (4, 4): R p + t."""
    T = np.asarray(T, dtype=float)
    return np.asarray(p, dtype=float) @ T[:3, :3].T + T[:3, 3]


def rotation_angle(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """Angle (rad, [0, pi]) of the rotation between two poses' orientations, R_a^T R_b."""
    R = np.swapaxes(np.asarray(T_a)[..., :3, :3], -1, -2) @ np.asarray(T_b)[..., :3, :3]
    # arccos of the trace is ill-conditioned near 0: use the quaternion's angle (2 atan2(|xyz|, |w|))
    q = quat.from_matrix(R)
    return 2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0]))


def translation_distance(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """|t_a - t_b| (metres)."""
    return np.linalg.norm(np.asarray(T_a)[..., :3, 3] - np.asarray(T_b)[..., :3, 3], axis=-1)


def is_rigid(T: np.ndarray, atol: float = RIGID_ATOL) -> bool:
    """True for a finite 4x4 with orthonormal R, det R = +1 and last row (0, 0, 0, 1)."""
    T = np.asarray(T, dtype=float)
    if T.shape[-2:] != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[..., :3, :3]
    eye = np.broadcast_to(np.eye(3), R.shape)
    return bool(
        np.allclose(np.swapaxes(R, -1, -2) @ R, eye, atol=atol)
        and np.allclose(np.linalg.det(R), 1.0, atol=atol)
        and np.allclose(T[..., 3, :], [0.0, 0.0, 0.0, 1.0], atol=atol)
    )
