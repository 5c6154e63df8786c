"""Hand-eye solvers (calibration.solvers): known transforms recovered, numpy ports match OpenCV."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration import solvers


def _random_pose(rng, rot_scale, trans_scale):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * rot_scale).as_matrix()
    T[:3, 3] = rng.normal(size=3) * trans_scale
    return T


def _captures(rng, n=10, noise=0.0):
    """Synthetic AX = XB data: true T_flange_camera, T_base_board, flange and board poses."""
    X = _random_pose(rng, 1.0, 0.1)
    T_base_board = _random_pose(rng, 1.0, 0.5)
    Tbf = np.stack([_random_pose(rng, 0.6, 0.3) for _ in range(n)])
    Tcb = np.stack([np.linalg.inv(Tbf[i] @ X) @ T_base_board for i in range(n)])
    if noise:
        Tcb = np.stack([T @ _random_pose(rng, noise * 0.01, noise * 0.001) for T in Tcb])
    return X, T_base_board, Tbf, Tcb


def _errors(T, T_true):
    dR = T[:3, :3].T @ T_true[:3, :3]
    return (np.degrees(np.linalg.norm(Rotation.from_matrix(dR).as_rotvec())),
            np.linalg.norm(T[:3, 3] - T_true[:3, 3]))


@pytest.mark.parametrize("method", solvers.HAND_EYE_METHODS)
def test_numpy_hand_eye_recovers_exact_transform(method):
    X, _, Tbf, Tcb = _captures(np.random.default_rng(1))
    deg, m = _errors(solvers.solve_hand_eye(Tbf, Tcb, method, backend_name="numpy"), X)
    assert deg < 1e-8 and m < 1e-9


@pytest.mark.parametrize("method", solvers.ROBOT_WORLD_METHODS)
def test_numpy_robot_world_recovers_hand_eye_and_board(method):
    X, T_base_board, Tbf, Tcb = _captures(np.random.default_rng(2))
    X_est, B_est = solvers.solve_robot_world(Tbf, Tcb, method, backend_name="numpy")
    for est, true in ((X_est, X), (B_est, T_base_board)):
        deg, m = _errors(est, true)
        assert deg < 1e-8 and m < 1e-9


needs_cv = pytest.mark.skipif(solvers.backend() != "opencv",
                              reason="installed OpenCV does not expose calibrateHandEye to Python")


@needs_cv
@pytest.mark.parametrize("method", ["park", "horaud", "andreff", "daniilidis"])
def test_numpy_hand_eye_matches_opencv_on_noisy_data(method):
    _, _, Tbf, Tcb = _captures(np.random.default_rng(3), n=12, noise=1.0)
    a = solvers.solve_hand_eye(Tbf, Tcb, method, backend_name="numpy")
    b = solvers.solve_hand_eye(Tbf, Tcb, method, backend_name="opencv")
    np.testing.assert_allclose(a, b, atol=1e-9)


@needs_cv
def test_numpy_tsai_as_accurate_as_opencv_on_noisy_data():
    # OpenCV's minimal quaternions do not fix the scalar's sign, so the two Tsai results differ
    # on noisy data; both must be about as far from the truth
    for seed in range(3, 8):
        X, _, Tbf, Tcb = _captures(np.random.default_rng(seed), n=12, noise=1.0)
        deg_np, m_np = _errors(solvers.solve_hand_eye(Tbf, Tcb, "tsai", backend_name="numpy"), X)
        deg_cv, m_cv = _errors(solvers.solve_hand_eye(Tbf, Tcb, "tsai", backend_name="opencv"), X)
        assert deg_np < 1.5 * deg_cv + 0.05
        assert m_np < 1.5 * m_cv + 5e-4


@needs_cv
@pytest.mark.parametrize("method", solvers.ROBOT_WORLD_METHODS)
def test_numpy_robot_world_matches_opencv_on_noisy_data(method):
    _, _, Tbf, Tcb = _captures(np.random.default_rng(4), n=12, noise=1.0)
    for a, b in zip(solvers.solve_robot_world(Tbf, Tcb, method, backend_name="numpy"),
                    solvers.solve_robot_world(Tbf, Tcb, method, backend_name="opencv")):
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_unknown_method_lists_valid_names():
    _, _, Tbf, Tcb = _captures(np.random.default_rng(5), n=4)
    with pytest.raises(ValueError, match="valid: tsai, park"):
        solvers.solve_hand_eye(Tbf, Tcb, "magic")


def test_too_few_captures_rejected():
    _, _, Tbf, Tcb = _captures(np.random.default_rng(6), n=2)
    with pytest.raises(ValueError, match="at least 3 captures"):
        solvers.solve_hand_eye(Tbf, Tcb, "park")
