"""IMU-to-marker rotation, AX = XB closed form (app.marker.handeye_rotation)."""
import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.marker import handeye_rotation as handeye


def _angle_deg(R1, R2):
    return np.rad2deg(np.linalg.norm(Rotation.from_matrix(R1.T @ R2).as_rotvec()))


def _sequence(rng, n=40, noise_deg=0.0):
    X = Rotation.random(random_state=rng.integers(2**31)).as_matrix()          # R_S_M
    R_C_W = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
    R_W_S = Rotation.from_rotvec(rng.normal(0, 0.6, (n, 3))).as_matrix()
    R_C_M = R_C_W @ R_W_S @ X
    if noise_deg:
        def noisy(R):
            return R @ Rotation.from_rotvec(rng.normal(0, np.deg2rad(noise_deg), (n, 3))).as_matrix()
        R_W_S, R_C_M = noisy(R_W_S), noisy(R_C_M)
    return X, R_W_S, R_C_M


def test_recovers_known_rotation_exactly_without_noise():
    rng = np.random.default_rng(1)
    X, R_W_S, R_C_M = _sequence(rng)
    X_est, report = handeye.calibrate_imu_to_marker(R_W_S, R_C_M)
    assert _angle_deg(X, X_est) < 1e-8
    assert report["residual_deg_max"] < 1e-8


def test_noise_error_within_documented_bound():
    sigma = 0.5
    rng = np.random.default_rng(2)
    for _ in range(5):
        X, R_W_S, R_C_M = _sequence(rng, n=40, noise_deg=sigma)
        A, B = handeye.motion_pairs(R_W_S, R_C_M, max_lag=1)
        X_est = handeye.solve_rotation_axxb(A, B)
        theta = np.mean(np.linalg.norm(Rotation.from_matrix(A).as_rotvec(), axis=1))
        bound = 2 * np.deg2rad(sigma) / (theta * np.sqrt(len(A) / 3))          # module docstring
        assert np.deg2rad(_angle_deg(X, X_est)) < 3 * bound


@pytest.mark.parametrize("noise_deg, agree_deg", [(0.0, 1e-6), (0.3, 0.5)])
def test_matches_opencv_park_rotation(noise_deg, agree_deg):
    # OpenCV's Park & Martin forms its relative motions from the same consecutive pairs; with noise
    # the two weight them differently, so they agree exactly only without noise
    rng = np.random.default_rng(3)
    X, R_W_S, R_C_M = _sequence(rng, n=12, noise_deg=noise_deg)
    A, B = handeye.motion_pairs(R_W_S, R_C_M, min_angle=0.0, max_lag=1)
    X_est = handeye.solve_rotation_axxb(A, B)
    # eye-in-hand analogy: gripper = IMU sensor S (pose R_W_S), camera = marker M, target = the camera C
    t0 = [np.zeros(3)] * len(R_W_S)
    R_cv, _ = cv2.calibrateHandEye(list(R_W_S), t0, list(np.swapaxes(R_C_M, 1, 2)), t0,
                                   method=cv2.CALIB_HAND_EYE_PARK)
    assert _angle_deg(R_cv, X_est) < agree_deg
    assert _angle_deg(X, X_est) < (1.0 if noise_deg else 1e-6)


def test_outlier_pair_is_dropped():
    rng = np.random.default_rng(4)
    X, R_W_S, R_C_M = _sequence(rng, n=40, noise_deg=0.2)
    R_C_M[17] = R_C_M[17] @ Rotation.from_rotvec([0.0, np.deg2rad(40), 0.0]).as_matrix()   # a flipped pose
    X_est, report = handeye.calibrate_imu_to_marker(R_W_S, R_C_M)
    assert report["pairs_used"] < report["pairs"]
    assert _angle_deg(X, X_est) < 0.5


def test_parallel_axes_are_degenerate():
    angles = np.linspace(0.3, 1.5, 5)
    A = Rotation.from_rotvec(np.outer(angles, [0, 0, 1.0])).as_matrix()
    with pytest.raises(ValueError, match="parallel"):
        handeye.solve_rotation_axxb(A, A)
