"""Hand-eye solvers: AX = XB (eye-in-hand) and AX = ZB (robot-world), by name, via OpenCV.

Import as ``from calibration import solvers``.

Contract (every method)
-----------------------
``solve_hand_eye(T_base_flange, T_camera_board, method)`` takes N >= 3 captures, each the flange
pose in the robot base frame (from the joints and forward kinematics) and the board pose in the
camera optical frame (from PnP on the board's corners), and returns ``T_flange_camera``. For
captures i, j the board is fixed in the base, ``T_base_board = A_i X B_i``, with
``A_i = T_base_flange_i``, ``X = T_flange_camera``, ``B_i = T_camera_board_i``, so every pair gives

    A_ij X = X B_ij,   A_ij = A_j^-1 A_i,   B_ij = B_j B_i^-1                         (1)

This is ``cv2.calibrateHandEye(R_gripper2base, t_gripper2base, R_target2cam, t_target2cam)`` with
gripper = flange, target = board; it returns ``R_cam2gripper, t_cam2gripper = T_flange_camera``.

``solve_robot_world(T_base_flange, T_camera_board, method)`` solves the same captures as
``A'_i X' = Z' B'_i`` with ``A' = T_camera_board`` (OpenCV's world2cam, world = board),
``B' = T_flange_base`` (base2gripper), ``X' = T_board_base`` (base2world) and
``Z' = T_camera_flange`` (gripper2cam): ``cv2.calibrateRobotWorldHandEye``. It returns
``(T_flange_camera, T_base_board)``.

Methods (OpenCV's ``CALIB_HAND_EYE_*`` / ``CALIB_ROBOT_WORLD_HAND_EYE_*`` flags)
--------------------------------------------------------------------------------
What OpenCV implements for each name:

- ``tsai``: Tsai & Lenz 1989, rotation from modified Rodrigues vectors, then translation by
  least squares, (R_A - I) t_X = R_X t_B - t_A.
- ``park``: Park & Martin 1994, rotation from the Lie-algebra logs, R_X = (M^T M)^(-1/2) M^T with
  M = sum log(R_B) log(R_A)^T; translation as Tsai.
- ``horaud``: Horaud & Dornaika 1995, rotation as a unit quaternion (smallest eigenvector);
  translation as Tsai.
- ``andreff``: Andreff, Horaud & Espiau 1999, rotation and translation from one linear system
  (Kronecker products), rotation then orthonormalised.
- ``daniilidis``: Daniilidis 1999, dual quaternions, rotation and translation together (SVD).
- robot-world ``shah``: Shah 2013, Kronecker product and SVD; ``li``: Li, Wang & Wu 2010, one
  linear least-squares system in both rotations and translations.

On noise-free data every method recovers the true transforms to machine precision
(``tests/test_calibration_solvers.py``). The rotations must span at least two non-parallel axes;
``calibration.handeye.check_conditioning`` warns when they do not.
"""
from __future__ import annotations

import logging

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


def _split(T: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """OpenCV's input form: lists of (3, 3) rotations and (3, 1) translations."""
    return list(T[:, :3, :3]), list(T[:, :3, 3:4])


def solve_hand_eye(T_base_flange: np.ndarray, T_camera_board: np.ndarray, method: str = "park") -> np.ndarray:
    """Eye-in-hand calibration ``T_flange_camera`` from N captures (AX = XB, eq. 1).

    Parameters
    ----------
    T_base_flange : (N, 4, 4) float64, flange (tool0) poses in the robot base frame, metres.
    T_camera_board : (N, 4, 4) float64, board poses in the camera optical frame, metres.
    method : one of ``HAND_EYE_METHODS``.

    Returns
    -------
    (4, 4) float64 ``T_flange_camera``, the camera optical frame in the flange frame.

    Raises
    ------
    ValueError : unknown method, bad shapes, fewer than 3 captures, or OpenCV rejected the data.
    """
    import cv2

    key = _method_check(method, HAND_EYE_METHODS)
    A, B = _check_inputs(T_base_flange, T_camera_board)
    try:
        R, t = cv2.calibrateHandEye(*_split(A), *_split(B), method=getattr(cv2, _CV_HAND_EYE_FLAGS[key]))
    except cv2.error as exc:
        raise ValueError(f"OpenCV calibrateHandEye ({key}) failed: {exc}") from None
    return _pose(np.asarray(R), np.asarray(t))


def solve_robot_world(T_base_flange: np.ndarray, T_camera_board: np.ndarray,
                      method: str = "shah") -> tuple[np.ndarray, np.ndarray]:
    """Robot-world/hand-eye calibration: ``T_flange_camera`` and ``T_base_board`` together.

    Parameters
    ----------
    T_base_flange : (N, 4, 4) float64, flange poses in the robot base frame, metres.
    T_camera_board : (N, 4, 4) float64, board poses in the camera optical frame, metres.
    method : one of ``ROBOT_WORLD_METHODS``.

    Returns
    -------
    T_flange_camera : (4, 4) float64.
    T_base_board : (4, 4) float64, the board frame in the robot base frame.

    Raises
    ------
    ValueError : unknown method, bad shapes, fewer than 3 captures, or OpenCV rejected the data.
    """
    import cv2

    key = _method_check(method, ROBOT_WORLD_METHODS)
    Tbf, Tcb = _check_inputs(T_base_flange, T_camera_board)
    try:
        R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(
            *_split(Tcb), *_split(_inv(Tbf)), method=getattr(cv2, _CV_ROBOT_WORLD_FLAGS[key]))
    except cv2.error as exc:
        raise ValueError(f"OpenCV calibrateRobotWorldHandEye ({key}) failed: {exc}") from None
    T_board_base = _pose(np.asarray(R_bw), np.asarray(t_bw))
    T_camera_flange = _pose(np.asarray(R_gc), np.asarray(t_gc))
    return _inv(T_camera_flange), _inv(T_board_base)
