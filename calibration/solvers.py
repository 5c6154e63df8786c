"""Hand-eye solvers: AX = XB (eye-in-hand) and AX = ZB (robot-world), by name.

Import as ``from calibration import solvers``.

Contract (every method)
-----------------------
``solve_hand_eye(T_base_flange, T_camera_board, method)`` takes N >= 3 captures, each the flange
pose in the robot base frame (from the joints and forward kinematics) and the board pose in the
camera optical frame (from PnP on the board's corners), and returns ``T_flange_camera``. For
captures i, j the board is fixed in the base, ``T_base_board = A_i X B_i``, with
``A_i = T_base_flange_i``, ``X = T_flange_camera``, ``B_i = T_camera_board_i``, so every pair gives

    A_ij X = X B_ij,   A_ij = A_j^-1 A_i,   B_ij = B_j B_i^-1                         (1)

(all pairs i < j are used). ``solve_robot_world(T_base_flange, T_camera_board, method)`` solves
the same captures as ``A'_i X' = Z' B'_i`` (OpenCV's form) with ``A' = T_camera_board``,
``X' = T_board_base``, ``Z' = T_camera_flange``, ``B' = T_flange_base`` and returns
``(T_flange_camera, T_base_board)``.

Methods (names as in OpenCV's ``CALIB_HAND_EYE_*`` / ``CALIB_ROBOT_WORLD_HAND_EYE_*``)
---------------------------------------------------------------------------------------
- ``tsai``: Tsai & Lenz 1989, modified Rodrigues vectors P = 2 sin(theta/2) n;
  skew(P_A + P_B) P' = P_B - P_A, then P_X = 2 P' / sqrt(1 + |P'|^2).
- ``park``: Park & Martin 1994, alpha = log R_A, beta = log R_B, M = sum beta alpha^T,
  R_X = (M^T M)^(-1/2) M^T.
- ``horaud``: Horaud & Dornaika 1995, unit quaternions: (L(q_A) - R(q_B)) q_X = 0, q_X the
  eigenvector of the smallest eigenvalue of sum (L - R)^T (L - R).
- ``andreff``: Andreff, Horaud & Espiau 1999, one linear system in vec(R_X) (row-major) and t_X:
  [I9 - R_A (x) R_B, 0; I3 (x) t_B^T, I3 - R_A] [vec R_X; t_X] = [0; t_A], R_X then
  orthonormalised.
- ``daniilidis``: Daniilidis 1999, dual quaternions, rotation and translation together from the
  two smallest right singular vectors of the stacked 6x8 matrices.
- Tsai, Park and Horaud then solve the translation by least squares:
  (R_A - I) t_X = R_X t_B - t_A.
- Robot-world ``shah`` (Shah 2013, Kronecker product and SVD) and ``li`` (Li, Wang & Wu 2010,
  one linear least-squares system in vec(R_X), vec(R_Z), t_X, t_Z; rotations orthonormalised).

Backends: OpenCV's ``cv2.calibrateHandEye`` / ``cv2.calibrateRobotWorldHandEye`` are used when
the installed OpenCV exposes them to Python. OpenCV 5.0.0's Python package does not (upstream
opencv/opencv issue 29565, fixed by PR 29584 after that release); then the numpy implementations
here, written from the papers above, are used. ``backend()`` says which one runs, and
``backend_name="numpy"`` forces the numpy path. Cross-checked against OpenCV 4.14's
``calibrateHandEye``: Park, Horaud, Daniilidis, Andreff, Shah and Li agree to 1e-12 on noisy data;
Tsai differs (up to ~0.1 deg with 0.5 deg of rotation noise, equally accurate) because OpenCV's minimal quaternions do not fix
the sign of the scalar part, while here every rotation's quaternion has w >= 0.
"""
from __future__ import annotations

import logging
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

HAND_EYE_METHODS = ("tsai", "park", "horaud", "andreff", "daniilidis")
ROBOT_WORLD_METHODS = ("shah", "li")

_CV_HAND_EYE_FLAGS = {
    "tsai": "CALIB_HAND_EYE_TSAI",
    "park": "CALIB_HAND_EYE_PARK",
    "horaud": "CALIB_HAND_EYE_HORAUD",
    "andreff": "CALIB_HAND_EYE_ANDREFF",
    "daniilidis": "CALIB_HAND_EYE_DANIILIDIS",
}
_CV_ROBOT_WORLD_FLAGS = {"shah": "CALIB_ROBOT_WORLD_HAND_EYE_SHAH", "li": "CALIB_ROBOT_WORLD_HAND_EYE_LI"}


def _cv2():
    try:
        import cv2
    except ImportError:  # pragma: no cover - cv2 is a dependency
        return None
    return cv2


def backend() -> str:
    """``"opencv"`` when the installed cv2 exposes ``calibrateHandEye``, else ``"numpy"``."""
    cv2 = _cv2()
    if cv2 is not None and hasattr(cv2, "calibrateHandEye") and hasattr(cv2, "calibrateRobotWorldHandEye"):
        return "opencv"
    return "numpy"


# --------------------------------------------------------------------------------------------
# small rotation helpers (private: app.geometry owns the public SE(3) API)

def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _orthonormalise(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (Frobenius) to a 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of a 3x3 rotation; robust near 0 and pi."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def _rotation_from_quat(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    w, x, y, z = q / np.linalg.norm(q)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product, (w, x, y, z)."""
    w1, v1 = a[0], a[1:]
    w2, v2 = b[0], b[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def _qleft(q: np.ndarray) -> np.ndarray:
    """L(q) with q p = L(q) p."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def _qright(q: np.ndarray) -> np.ndarray:
    """R(q) with p q = R(q) p."""
    w, x, y, z = q
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of one or many rigid transforms, (..., 4, 4)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


# --------------------------------------------------------------------------------------------
# AX = XB

def relative_motions(T_base_flange: np.ndarray, T_camera_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All pairwise motions of eq. (1).

    Parameters
    ----------
    T_base_flange : (N, 4, 4) float64, flange poses in the base frame.
    T_camera_board : (N, 4, 4) float64, board poses in the camera optical frame.

    Returns
    -------
    A, B : (N(N-1)/2, 4, 4) float64, ``A_ij = A_j^-1 A_i`` (flange motion) and
        ``B_ij = B_j B_i^-1`` (camera motion), pairs i < j in lexicographic order.
    """
    n = len(T_base_flange)
    i, j = np.triu_indices(n, k=1)
    A = _inv(T_base_flange[j]) @ T_base_flange[i]
    B = T_camera_board[j] @ _inv(T_camera_board[i])
    return A, B


def _translation_lstsq(A: np.ndarray, B: np.ndarray, R_X: np.ndarray) -> np.ndarray:
    """Solve (R_A - I) t_X = R_X t_B - t_A over all pairs, least squares."""
    M = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (np.einsum("ij,nj->ni", R_X, B[:, :3, 3]) - A[:, :3, 3]).reshape(-1)
    t, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return t


def _rot_tsai(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    rows, rhs = [], []
    for a, b in zip(A, B):
        ra, rb = _log_rotation(a[:3, :3]), _log_rotation(b[:3, :3])
        Pa = 2.0 * np.sin(np.linalg.norm(ra) / 2.0) * _unit(ra)
        Pb = 2.0 * np.sin(np.linalg.norm(rb) / 2.0) * _unit(rb)
        rows.append(_skew(Pa + Pb))
        rhs.append(Pb - Pa)
    Pp, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
    P = 2.0 * Pp / np.sqrt(1.0 + Pp @ Pp)
    n2 = P @ P
    R = (1.0 - n2 / 2.0) * np.eye(3) + 0.5 * (np.outer(P, P) + np.sqrt(4.0 - n2) * _skew(P))
    return _orthonormalise(R)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else np.zeros(3)


def _rot_park(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    M = np.zeros((3, 3))
    for a, b in zip(A, B):
        M += np.outer(_log_rotation(b[:3, :3]), _log_rotation(a[:3, :3]))
    w, V = np.linalg.eigh(M.T @ M)
    inv_sqrt = V @ np.diag(1.0 / np.sqrt(np.maximum(w, 1e-300))) @ V.T
    return _orthonormalise(inv_sqrt @ M.T)


def _rot_horaud(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    S = np.zeros((4, 4))
    for a, b in zip(A, B):
        C = _qleft(_quat_wxyz(a[:3, :3])) - _qright(_quat_wxyz(b[:3, :3]))
        S += C.T @ C
    _, V = np.linalg.eigh(S)
    return _rotation_from_quat(V[:, 0])


def _solve_andreff(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    # row-major vec: vec(R_A X R_B^T) = (R_A (x) R_B) vec(X). Rotation and translation in one
    # linear least-squares system (Andreff eq. 10):
    #   [I9 - R_A (x) R_B, 0; I3 (x) t_B^T, I3 - R_A] [vec(R_X); t_X] = [0; t_A]
    n = len(A)
    M = np.zeros((12 * n, 12))
    rhs = np.zeros(12 * n)
    for k, (a, b) in enumerate(zip(A, B)):
        r = 12 * k
        M[r:r + 9, :9] = np.eye(9) - np.kron(a[:3, :3], b[:3, :3])
        M[r + 9:r + 12, :9] = np.kron(np.eye(3), b[:3, 3][None, :])
        M[r + 9:r + 12, 9:] = np.eye(3) - a[:3, :3]
        rhs[r + 9:r + 12] = a[:3, 3]
    x, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    R = x[:9].reshape(3, 3)
    det = np.linalg.det(R)
    if abs(det) < 1e-12:
        raise ValueError("Andreff: the linear solution is degenerate (captures too similar)")
    R = R * np.cbrt(np.sign(det) / abs(det))
    return _pose(_orthonormalise(R), x[9:])


def _solve_daniilidis(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    rows = []
    for a, b in zip(A, B):
        qa, qb = _quat_wxyz(a[:3, :3]), _quat_wxyz(b[:3, :3])
        da = 0.5 * _qmul(np.concatenate([[0.0], a[:3, 3]]), qa)
        db = 0.5 * _qmul(np.concatenate([[0.0], b[:3, 3]]), qb)
        S = np.zeros((6, 8))
        S[:3, 0] = qa[1:] - qb[1:]
        S[:3, 1:4] = _skew(qa[1:] + qb[1:])
        S[3:, 0] = da[1:] - db[1:]
        S[3:, 1:4] = _skew(da[1:] + db[1:])
        S[3:, 4] = qa[1:] - qb[1:]
        S[3:, 5:8] = _skew(qa[1:] + qb[1:])
        rows.append(S)
    _, _, Vt = np.linalg.svd(np.concatenate(rows))
    v1, v2 = Vt[-2], Vt[-1]
    u1, w1, u2, w2 = v1[:4], v1[4:], v2[:4], v2[4:]
    # lambda1 v1 + lambda2 v2 with |q| = 1 and q . q' = 0; s = lambda1 / lambda2
    a_, b_, c_ = u1 @ w1, u1 @ w2 + u2 @ w1, u2 @ w2
    if abs(a_) < 1e-15:
        roots = [-c_ / b_]
    else:
        disc = max(b_ * b_ - 4.0 * a_ * c_, 0.0)
        roots = [(-b_ + np.sqrt(disc)) / (2.0 * a_), (-b_ - np.sqrt(disc)) / (2.0 * a_)]
    vals = [s * s * (u1 @ u1) + 2.0 * s * (u1 @ u2) + u2 @ u2 for s in roots]
    k = int(np.argmax(vals))
    l2 = 1.0 / np.sqrt(vals[k])
    l1 = roots[k] * l2
    q = l1 * u1 + l2 * u2
    dq = l1 * w1 + l2 * w2
    q_conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    t = 2.0 * _qmul(dq, q_conj)[1:]
    return _pose(_rotation_from_quat(q), t)


_ROTATION_SOLVERS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "tsai": _rot_tsai,
    "park": _rot_park,
    "horaud": _rot_horaud,
}


def _check_inputs(T_base_flange: np.ndarray, T_camera_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    A = np.asarray(T_base_flange, dtype=np.float64)
    B = np.asarray(T_camera_board, dtype=np.float64)
    if A.ndim != 3 or A.shape[1:] != (4, 4) or B.shape != A.shape:
        raise ValueError(
            f"expected two (N, 4, 4) pose stacks of equal N, got {A.shape} and {B.shape}")
    if len(A) < 3:
        raise ValueError(f"hand-eye calibration needs at least 3 captures, got {len(A)}")
    if not (np.isfinite(A).all() and np.isfinite(B).all()):
        raise ValueError("hand-eye inputs contain NaN or inf")
    return A, B


def _method_check(method: str, names: tuple[str, ...]) -> str:
    key = method.lower()
    if key not in names:
        raise ValueError(f"unknown method {method!r}; valid: {', '.join(names)}")
    return key


def solve_hand_eye(T_base_flange: np.ndarray, T_camera_board: np.ndarray, method: str = "park",
                   backend_name: str | None = None) -> np.ndarray:
    """Eye-in-hand calibration ``T_flange_camera`` from N captures (AX = XB, eq. 1).

    Parameters
    ----------
    T_base_flange : (N, 4, 4) float64, flange (tool0) poses in the robot base frame, metres.
    T_camera_board : (N, 4, 4) float64, board poses in the camera optical frame, metres.
    method : one of ``HAND_EYE_METHODS``.
    backend_name : ``"opencv"``, ``"numpy"`` or None (OpenCV when available, see ``backend()``).

    Returns
    -------
    (4, 4) float64 ``T_flange_camera``, the camera optical frame in the flange frame.
    """
    key = _method_check(method, HAND_EYE_METHODS)
    A, B = _check_inputs(T_base_flange, T_camera_board)
    use = backend_name or backend()
    if use == "opencv":
        cv2 = _cv2()
        R, t = cv2.calibrateHandEye(
            list(A[:, :3, :3]), list(A[:, :3, 3:4]), list(B[:, :3, :3]), list(B[:, :3, 3:4]),
            method=getattr(cv2, _CV_HAND_EYE_FLAGS[key]))
        return _pose(np.asarray(R), np.asarray(t))
    if use != "numpy":
        raise ValueError(f"unknown backend {use!r}; valid: opencv, numpy")
    Aij, Bij = relative_motions(A, B)
    if key == "daniilidis":
        return _solve_daniilidis(Aij, Bij)
    if key == "andreff":
        return _solve_andreff(Aij, Bij)
    R_X = _ROTATION_SOLVERS[key](Aij, Bij)
    return _pose(R_X, _translation_lstsq(Aij, Bij, R_X))


# --------------------------------------------------------------------------------------------
# AX = ZB

def _rw_shah(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # column-major vec: R_Z = R_A R_X R_B^T  ->  vec(R_Z) = (R_B (x) R_A) vec(R_X)
    K = sum(np.kron(b[:3, :3], a[:3, :3]) for a, b in zip(A, B))
    U, _, Vt = np.linalg.svd(K)
    RX = Vt[0].reshape(3, 3, order="F")
    RZ = U[:, 0].reshape(3, 3, order="F")
    RX = _orthonormalise(RX * np.sign(np.linalg.det(RX)))
    RZ = _orthonormalise(RZ * np.sign(np.linalg.det(RZ)))
    return RX, RZ


def _rw_li(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T_X, T_Z) from one linear system; rotations orthonormalised, translations kept."""
    n = len(A)
    M = np.zeros((12 * n, 24))
    rhs = np.zeros(12 * n)
    I3 = np.eye(3)
    for k, (a, b) in enumerate(zip(A, B)):
        Ra, ta, Rb, tb = a[:3, :3], a[:3, 3], b[:3, :3], b[:3, 3]
        r = 12 * k
        # R_A R_X - R_Z R_B = 0 (column-major vec)
        M[r:r + 9, 0:9] = np.kron(I3, Ra)
        M[r:r + 9, 9:18] = -np.kron(Rb.T, I3)
        # R_A t_X - t_Z - R_Z t_B = -t_A
        M[r + 9:r + 12, 9:18] = -np.kron(tb[None, :], I3)
        M[r + 9:r + 12, 18:21] = Ra
        M[r + 9:r + 12, 21:24] = -I3
        rhs[r + 9:r + 12] = -ta
    x, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    RX = _orthonormalise(x[0:9].reshape(3, 3, order="F"))
    RZ = _orthonormalise(x[9:18].reshape(3, 3, order="F"))
    return _pose(RX, x[18:21]), _pose(RZ, x[21:24])


def _rw_translations(A: np.ndarray, B: np.ndarray, RX: np.ndarray, RZ: np.ndarray):
    """Solve R_A t_X - t_Z = R_Z t_B - t_A, least squares over all captures."""
    M = np.concatenate([np.hstack([a[:3, :3], -np.eye(3)]) for a in A])
    rhs = np.concatenate([RZ @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    x, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    return x[:3], x[3:]


def solve_robot_world(T_base_flange: np.ndarray, T_camera_board: np.ndarray, method: str = "shah",
                      backend_name: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Robot-world/hand-eye calibration: ``T_flange_camera`` and ``T_base_board`` together.

    Parameters
    ----------
    T_base_flange : (N, 4, 4) float64, flange poses in the robot base frame, metres.
    T_camera_board : (N, 4, 4) float64, board poses in the camera optical frame, metres.
    method : one of ``ROBOT_WORLD_METHODS``.
    backend_name : ``"opencv"``, ``"numpy"`` or None (OpenCV when available).

    Returns
    -------
    T_flange_camera : (4, 4) float64.
    T_base_board : (4, 4) float64, the board frame in the robot base frame.
    """
    key = _method_check(method, ROBOT_WORLD_METHODS)
    Tbf, Tcb = _check_inputs(T_base_flange, T_camera_board)
    A = Tcb                  # T_camera_board   (OpenCV: world2cam)
    B = _inv(Tbf)            # T_flange_base    (OpenCV: base2gripper)
    use = backend_name or backend()
    if use == "opencv":
        cv2 = _cv2()
        R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(
            list(A[:, :3, :3]), list(A[:, :3, 3:4]), list(B[:, :3, :3]), list(B[:, :3, 3:4]),
            method=getattr(cv2, _CV_ROBOT_WORLD_FLAGS[key]))
        T_board_base = _pose(np.asarray(R_bw), np.asarray(t_bw))
        T_camera_flange = _pose(np.asarray(R_gc), np.asarray(t_gc))
    elif use == "numpy":
        if key == "shah":
            RX, RZ = _rw_shah(A, B)
            tX, tZ = _rw_translations(A, B, RX, RZ)
            T_board_base, T_camera_flange = _pose(RX, tX), _pose(RZ, tZ)
        else:
            T_board_base, T_camera_flange = _rw_li(A, B)
    else:
        raise ValueError(f"unknown backend {use!r}; valid: opencv, numpy")
    return _inv(T_camera_flange), _inv(T_board_base)
