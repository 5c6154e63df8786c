"""Batched Hamilton quaternions, scalar first ``(w, x, y, z)``, float64.

Import as ``from app.geometry import quaternion as quat``. Conventions (STYLE.md §4): Hamilton
product (i j = k, i j k = -1); unit quaternions represent rotations, q and -q the same one;
rotation vectors are axis * angle (radians). ``to_xyzw`` / ``from_xyzw`` are the only conversions
to the scalar-last order of TUM files, rerun and scipy.
"""
from __future__ import annotations

import numpy as np

_SMALL = 1e-8  # below this angle (rad) exp/log use their Taylor series


def multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product q1 ⊗ q2, (..., 4)."""
    w1, x1, y1, z1 = np.moveaxis(np.asarray(q1, dtype=float), -1, 0)
    w2, x2, y2, z2 = np.moveaxis(np.asarray(q2, dtype=float), -1, 0)
    return np.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], axis=-1)


def conjugate(q: np.ndarray) -> np.ndarray:
    """(w, -x, -y, -z): the inverse of a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def normalize(q: np.ndarray) -> np.ndarray:
    """q / |q|; raises ValueError for a zero (or non-finite) quaternion instead of repairing it."""
    q = np.asarray(q, dtype=float)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError("cannot normalise a zero or non-finite quaternion")
    return q / norm


def exp_map(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion of a rotation vector v: (cos(|v|/2), v/|v| sin(|v|/2)), (..., 3) -> (..., 4)."""
    v = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    small = angle < _SMALL
    safe = np.where(small, 1.0, angle)
    # sin(|v|/2)/|v| -> 1/2 - |v|^2/48 near zero
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([np.cos(half), k * v], axis=-1)


def log_map(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of a unit quaternion, (..., 4) -> (..., 3)."""
    q = np.asarray(q, dtype=float)
    q = np.where(q[..., :1] < 0, -q, q)
    w = np.clip(q[..., :1], -1.0, 1.0)
    xyz = q[..., 1:]
    s = np.linalg.norm(xyz, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, w)
    small = s < _SMALL
    k = np.where(small, 2.0 / np.where(w == 0, 1.0, w), angle / np.where(small, 1.0, s))
    return k * xyz


def to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), w >= 0, of rotation matrices (..., 3, 3).

    Takes the eigenvector of Bar-Itzhack's symmetric 4x4 matrix (robust for every rotation and
    tolerant of slightly non-orthogonal input).
    """
    R = np.asarray(R, dtype=float)
    m = R
    K = np.empty(R.shape[:-2] + (4, 4))
    K[..., 0, 0] = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    K[..., 0, 1] = K[..., 1, 0] = m[..., 2, 1] - m[..., 1, 2]
    K[..., 0, 2] = K[..., 2, 0] = m[..., 0, 2] - m[..., 2, 0]
    K[..., 0, 3] = K[..., 3, 0] = m[..., 1, 0] - m[..., 0, 1]
    K[..., 1, 1] = m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2]
    K[..., 1, 2] = K[..., 2, 1] = m[..., 0, 1] + m[..., 1, 0]
    K[..., 1, 3] = K[..., 3, 1] = m[..., 0, 2] + m[..., 2, 0]
    K[..., 2, 2] = m[..., 1, 1] - m[..., 0, 0] - m[..., 2, 2]
    K[..., 2, 3] = K[..., 3, 2] = m[..., 1, 2] + m[..., 2, 1]
    K[..., 3, 3] = m[..., 2, 2] - m[..., 0, 0] - m[..., 1, 1]
    _, vectors = np.linalg.eigh(K / 3.0)
    q = vectors[..., :, -1]
    return np.where(q[..., :1] < 0, -q, q)


def rotate(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points (..., 3) rotated by unit quaternions (..., 4): q ⊗ (0, p) ⊗ q*."""
    q = np.asarray(q, dtype=float)
    p = np.asarray(p, dtype=float)
    u = q[..., 1:]
    w = q[..., :1]
    t = 2.0 * np.cross(u, p)
    return p + w * t + np.cross(u, t)


def weighted_mean(q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted mean rotation: the principal eigenvector of M = sum_j w_j q_j q_j^T (Markley et al. 2007).

    It maximises sum_j w_j (q . q_j)^2, i.e. minimises the weighted chordal (Frobenius) distance
    of the rotation matrices; q_j q_j^T is the same for q_j and -q_j, so the signs of the inputs
    do not matter.

    Parameters
    ----------
    q : (N, 4) float64
        Unit quaternions (w, x, y, z); the sign of each is irrelevant.
    w : (N,) float64
        Non-negative weights with a positive sum (need not be normalised).

    Returns
    -------
    (4,) float64 unit quaternion with w >= 0.

    Raises
    ------
    ValueError
        For shapes other than (N, 4) and (N,), negative or non-finite weights, or a zero sum.
    """
    q = np.asarray(q, dtype=float)
    w = np.asarray(w, dtype=float)
    if q.ndim != 2 or q.shape[1] != 4 or w.shape != (q.shape[0],):
        raise ValueError(f"weighted_mean expects q (N, 4) and w (N,), got q {q.shape} and w {w.shape}; "
                         f"w must have shape ({q.shape[0] if q.ndim == 2 else 'N'},)")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weighted_mean needs finite non-negative weights")
    total = w.sum()
    if not total > 0:
        raise ValueError("weighted_mean needs weights with a positive sum, got all zero")
    M = np.einsum("n,ni,nj->ij", w / total, q, q)
    _, vectors = np.linalg.eigh(M)
    mean = vectors[:, -1]
    return -mean if mean[0] < 0 else mean


def angle_between(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle (radians, [0, pi]) of q1^-1 ⊗ q2, independent of the signs of q1 and q2.

    Computed as 2 atan2(|vec(q1* ⊗ q2)|, |scal(q1* ⊗ q2)|), accurate for tiny angles too (the
    arccos of the dot product loses half the digits there). Shapes broadcast: (..., 4) -> (...).
    """
    d = multiply(conjugate(q1), q2)
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def to_xyzw(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) -> (x, y, z, w), for TUM files, rerun and scipy."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def from_xyzw(q: np.ndarray) -> np.ndarray:
    """(x, y, z, w) -> (w, x, y, z)."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def random_uniform(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4) unit quaternions uniform on SO(3) (normalised 4D Gaussians), w >= 0."""
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)


def allclose_up_to_sign(q1: np.ndarray, q2: np.ndarray, atol: float = 1e-8) -> bool:
    """True when q1 == q2 or q1 == -q2 elementwise within ``atol`` (per quaternion)."""
    q1 = np.asarray(q1, dtype=float)
    q2 = np.asarray(q2, dtype=float)
    same = np.all(np.abs(q1 - q2) <= atol, axis=-1)
    flipped = np.all(np.abs(q1 + q2) <= atol, axis=-1)
    return bool(np.all(same | flipped))
