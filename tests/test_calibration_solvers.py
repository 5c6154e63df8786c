"""Hand-eye solvers (calibration.solvers, OpenCV): known simulated transforms recovered by every method."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration import solvers

EXACT_RAD = 1e-6
EXACT_M = 1e-6


def _random_pose(rng, rot_scale, trans_scale):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * rot_scale).as_matrix()
    T[:3, 3] = rng.normal(size=3) * trans_scale
    return T


def _captures(rng, n=10, rot_noise_rad=0.0, trans_noise_m=0.0):
    """Synthetic AX = XB data: true T_flange_camera, T_base_board, flange and board poses.

    Noise (per axis, Gaussian) perturbs each board pose in the camera, as PnP errors would.
    """
    X = _random_pose(rng, 1.0, 0.1)
    T_base_board = _random_pose(rng, 1.0, 0.5)
    Tbf = np.stack([_random_pose(rng, 0.6, 0.3) for _ in range(n)])
    Tcb = np.stack([np.linalg.inv(Tbf[i] @ X) @ T_base_board for i in range(n)])
    if rot_noise_rad or trans_noise_m:
        Tcb = np.stack([T @ _random_pose(rng, rot_noise_rad, trans_noise_m) for T in Tcb])
    return X, T_base_board, Tbf, Tcb


def _errors(T, T_true):
    """(rotation error rad, translation error m)."""
    dR = T[:3, :3].T @ T_true[:3, :3]
    return np.linalg.norm(Rotation.from_matrix(dR).as_rotvec()), np.linalg.norm(T[:3, 3] - T_true[:3, 3])


@pytest.mark.parametrize("seed", [1, 7])
@pytest.mark.parametrize("method", solvers.HAND_EYE_METHODS)
def test_hand_eye_recovers_exact_transform(method, seed):
    X, _, Tbf, Tcb = _captures(np.random.default_rng(seed))
    rad, m = _errors(solvers.solve_hand_eye(Tbf, Tcb, method), X)
    assert rad < EXACT_RAD and m < EXACT_M


@pytest.mark.parametrize("seed", [2, 8])
@pytest.mark.parametrize("method", solvers.ROBOT_WORLD_METHODS)
def test_robot_world_recovers_exact_hand_eye_and_board(method, seed):
    X, T_base_board, Tbf, Tcb = _captures(np.random.default_rng(seed))
    X_est, B_est = solvers.solve_robot_world(Tbf, Tcb, method)
    for est, true in ((X_est, X), (B_est, T_base_board)):
        rad, m = _errors(est, true)
        assert rad < EXACT_RAD and m < EXACT_M


def test_hand_eye_exact_with_minimal_three_captures():
    X, _, Tbf, Tcb = _captures(np.random.default_rng(9), n=3)
    for method in solvers.HAND_EYE_METHODS:
        rad, m = _errors(solvers.solve_hand_eye(Tbf, Tcb, method), X)
        assert rad < EXACT_RAD and m < EXACT_M, method


@pytest.mark.parametrize("method", solvers.HAND_EYE_METHODS + solvers.ROBOT_WORLD_METHODS)
def test_noisy_board_poses_give_small_errors(method):
    # 0.05 deg and 0.5 mm per axis on every board pose, 12 captures: every method stays within
    # 0.1 deg and 2 mm of the truth (observed: <= 0.05 deg, <= 1 mm)
    X, T_base_board, Tbf, Tcb = _captures(np.random.default_rng(3), n=12,
                                          rot_noise_rad=np.radians(0.05), trans_noise_m=5e-4)
    if method in solvers.HAND_EYE_METHODS:
        pairs = [(solvers.solve_hand_eye(Tbf, Tcb, method), X)]
    else:
        X_est, B_est = solvers.solve_robot_world(Tbf, Tcb, method)
        pairs = [(X_est, X), (B_est, T_base_board)]
    for est, true in pairs:
        rad, m = _errors(est, true)
        assert np.degrees(rad) < 0.1 and m < 2e-3


def test_method_names_are_case_insensitive():
    X, _, Tbf, Tcb = _captures(np.random.default_rng(10))
    np.testing.assert_allclose(solvers.solve_hand_eye(Tbf, Tcb, "PARK"), solvers.solve_hand_eye(Tbf, Tcb, "park"))


def test_unknown_method_lists_valid_names():
    _, _, Tbf, Tcb = _captures(np.random.default_rng(5), n=4)
    with pytest.raises(ValueError, match="valid: tsai, park"):
        solvers.solve_hand_eye(Tbf, Tcb, "magic")
    with pytest.raises(ValueError, match="valid: shah, li"):
        solvers.solve_robot_world(Tbf, Tcb, "tsai")


def test_too_few_captures_rejected():
    _, _, Tbf, Tcb = _captures(np.random.default_rng(6), n=2)
    with pytest.raises(ValueError, match="at least 3 captures"):
        solvers.solve_hand_eye(Tbf, Tcb, "park")


def test_mismatched_or_non_finite_inputs_rejected():
    _, _, Tbf, Tcb = _captures(np.random.default_rng(11), n=5)
    with pytest.raises(ValueError, match="equal N"):
        solvers.solve_hand_eye(Tbf, Tcb[:4], "park")
    bad = Tcb.copy()
    bad[2, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        solvers.solve_robot_world(Tbf, bad, "shah")
