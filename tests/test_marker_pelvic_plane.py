"""Anterior pelvic plane and radiographic angles (app.marker.pelvic_plane) against hand-computed cases."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.marker import pelvic_plane as app_plane

D = np.deg2rad


@pytest.mark.parametrize("axis, inc, ant", [
    ([-np.sin(D(45)), -np.cos(D(45)), 0.0], 45.0, 0.0),      # right hip, 45° down-lateral, no anteversion
    ([np.sin(D(45)), -np.cos(D(45)), 0.0], 45.0, 0.0),       # the same for a left hip
    ([-1.0, 0.0, 0.0], 90.0, 0.0),                           # straight lateral
    ([0.0, -1.0, 0.0], 0.0, 0.0),                            # straight down
    ([0.0, 0.0, 1.0], 0.0, 90.0),                            # straight anterior (atan2(0, -0) = 0)
    ([-np.cos(D(20)) * np.sin(D(40)), -np.cos(D(20)) * np.cos(D(40)), np.sin(D(20))], 40.0, 20.0),
    ([-3.0, -3.0, np.sqrt(18.0)], 45.0, 45.0),               # not normalised: |a| = 6
])
def test_radiographic_angles_hand_cases(axis, inc, ant):
    i, a = app_plane.radiographic_angles(np.array(axis))
    assert np.rad2deg(i) == pytest.approx(inc, abs=1e-9)
    assert np.rad2deg(a) == pytest.approx(ant, abs=1e-9)


def test_axis_from_angles_inverts_radiographic_angles():
    rng = np.random.default_rng(0)
    for side in ("left", "right"):
        inc, ant = rng.uniform(0.1, 1.4, 20), rng.uniform(-0.5, 0.8, 20)
        axes = np.array([app_plane.axis_from_angles(i, a, side) for i, a in zip(inc, ant)])
        i2, a2 = app_plane.radiographic_angles(axes)
        np.testing.assert_allclose(i2, inc, atol=1e-12)
        np.testing.assert_allclose(a2, ant, atol=1e-12)


def test_frame_from_landmarks_canonical_and_rotated():
    left, right, pubic = np.array([0.12, 0, 0]), np.array([-0.12, 0, 0]), np.array([0.0, -0.09, 0])
    np.testing.assert_allclose(app_plane.frame_from_landmarks(left, right, pubic), np.eye(3), atol=1e-12)
    R = Rotation.from_rotvec([0.3, -0.7, 1.1]).as_matrix()
    t = np.array([0.1, 0.2, 0.5])
    R_ref_P = app_plane.frame_from_landmarks(R @ left + t, R @ right + t, R @ pubic + t)
    np.testing.assert_allclose(R_ref_P, R, atol=1e-12)
    # pubic tubercles 0.03 posterior (z -0.03) of the ASIS line, 0.09 caudal: the plane tilts about x
    tilted = app_plane.frame_from_landmarks(left, right, np.array([0.0, -0.09, -0.03]))
    np.testing.assert_allclose(tilted[:, 2], [0, -np.sin(np.arctan2(0.03, 0.09)), np.cos(np.arctan2(0.03, 0.09))],
                               atol=1e-12)


def test_collinear_landmarks_raise():
    with pytest.raises(ValueError, match="collinear"):
        app_plane.frame_from_landmarks([0.1, 0, 0], [-0.1, 0, 0], [0.0, 0, 0])


def test_fragment_angles_follow_a_rotation_about_the_app_normal():
    # a fragment turned 10° about the APP's anterior axis z: a straight-down axis tilts 10° laterally
    R_C_P = Rotation.from_rotvec([0.2, 0.4, -0.3]).as_matrix()
    R_C_M0 = Rotation.from_rotvec([1.0, 0.1, 0.5]).as_matrix()
    axis_M = app_plane.axis_in_marker(R_C_P, R_C_M0, D(0.0), D(0.0))
    turn = R_C_P @ Rotation.from_rotvec([0, 0, D(-10.0)]).as_matrix() @ R_C_P.T    # in C, about z_P
    inc, ant = app_plane.fragment_angles(R_C_P, turn @ R_C_M0, axis_M)
    assert np.rad2deg(inc) == pytest.approx(10.0, abs=1e-9)
    assert np.rad2deg(ant) == pytest.approx(0.0, abs=1e-9)


def test_registration_averages_device_orientations():
    rng = np.random.default_rng(5)
    R_true = Rotation.from_rotvec([0.4, -0.2, 0.9]).as_matrix()
    noisy = R_true @ Rotation.from_rotvec(rng.normal(0, D(0.5), (200, 3))).as_matrix()
    R_M_P = Rotation.from_rotvec([0, 0, 0.3]).as_matrix()
    R_ref_P = app_plane.register_pelvic_plane(noisy, R_M_P)
    err = np.rad2deg(np.linalg.norm(Rotation.from_matrix((R_true @ R_M_P).T @ R_ref_P).as_rotvec()))
    assert err < 0.2
