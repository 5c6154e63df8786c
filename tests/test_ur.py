"""app.geometry.ur: UR's published DH tables, forward kinematics at hand-derived configurations and
against an independent product of elementary transforms, the robot config block, and joint
interpolation at and between samples and outside their span."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.geometry import se3
from app.geometry.ur import (UR_MODELS, DHParameters, camera_pose, dh_from_config, forward_kinematics,
                             interpolate_joints)

UR5E = UR_MODELS["ur5e"]


def test_published_ur5e_table():
    np.testing.assert_array_equal(UR5E.d, [0.1625, 0, 0, 0.1333, 0.0997, 0.0996])
    np.testing.assert_array_equal(UR5E.a, [0, -0.425, -0.3922, 0, 0, 0])
    np.testing.assert_array_equal(UR5E.alpha, [np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0])
    assert set(UR_MODELS) == {"ur3e", "ur5e", "ur10e", "ur16e"}


def test_ur5e_flange_at_zero_configuration():
    # all joints at 0: the arm lies along -x; the wrist offsets d4, d6 point along -y and d5 down
    T = forward_kinematics(UR5E, np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [-0.425 - 0.3922, -(0.1333 + 0.0996), 0.1625 - 0.0997], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [-0.8172, -0.2329, 0.0628], atol=1e-12)
    # axes: alpha1 = pi/2 gives z1 = -y0, y1 = z0; alpha4 = pi/2 then z4 = -z0 (d5 points down);
    # alpha5 = -pi/2 then y5 = z0, z5 = -y0. Flange: x = x0, y = z0, z = -y0 (the tool points along -y)
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


@pytest.mark.parametrize("model", sorted(UR_MODELS))
def test_upright_configuration_by_hand(model):
    # q = (0, -pi/2, 0, -pi/2, 0, 0), derived link by link:
    # frame 1 at z = d1 with x1 = x0, z1 = -y0; shoulder -pi/2 about -y0 turns x2 to -z0, so
    # a2 < 0 and a3 < 0 lift the elbow and wrist 1 to z = d1 - a2 - a3; wrist 1 (-pi/2) turns x4 to
    # -x0 and z4 to +z0, d4 moves along z3 = -y0; d5 moves up along z4; wrist 2's alpha5 = -pi/2
    # turns z5 to -y0, so d6 moves along -y. Flange: (0, -(d4 + d6), d1 - a2 - a3 + d5),
    # axes x6 = -x0, y6 = -z0, z6 = -y0.
    dh = UR_MODELS[model]
    d1, d4, d5, d6 = dh.d[0], dh.d[3], dh.d[4], dh.d[5]
    a2, a3 = dh.a[1], dh.a[2]
    T = forward_kinematics(dh, np.array([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0]))
    np.testing.assert_allclose(T[:3, 3], [0.0, -(d4 + d6), d1 - a2 - a3 + d5], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], [[-1, 0, 0], [0, 0, -1], [0, -1, 0]], atol=1e-12)
    if model == "ur5e":
        np.testing.assert_allclose(T[:3, 3], [0.0, -0.2329, 1.0794], atol=1e-12)


def _elementary_product(dh: DHParameters, q: np.ndarray) -> np.ndarray:
    """T = prod_i Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i), each factor built separately with scipy."""
    T = np.eye(4)
    for i in range(6):
        Rz = se3.make_pose(Rotation.from_euler("z", q[i]).as_matrix(), np.zeros(3))
        Tz = se3.make_pose(np.eye(3), [0.0, 0.0, dh.d[i]])
        Tx = se3.make_pose(np.eye(3), [dh.a[i], 0.0, 0.0])
        Rx = se3.make_pose(Rotation.from_euler("x", dh.alpha[i]).as_matrix(), np.zeros(3))
        T = T @ Rz @ Tz @ Tx @ Rx
    return T


@pytest.mark.parametrize("model", sorted(UR_MODELS))
def test_forward_kinematics_matches_an_elementary_product_batched(model, rng):
    dh = UR_MODELS[model]
    q = rng.uniform(-np.pi, np.pi, (4, 3, 6))
    T = forward_kinematics(dh, q)
    assert T.shape == (4, 3, 4, 4)
    expected = np.stack([_elementary_product(dh, qi) for qi in q.reshape(-1, 6)]).reshape(T.shape)
    np.testing.assert_allclose(T, expected, atol=1e-12)
    assert se3.is_rigid(T, atol=1e-12)


def test_first_joint_rotates_the_flange_about_base_z(rng):
    q = rng.uniform(-np.pi, np.pi, 6)
    q_turned = q.copy()
    q_turned[0] += 0.7
    Rz = se3.make_pose(Rotation.from_euler("z", 0.7).as_matrix(), np.zeros(3))
    np.testing.assert_allclose(forward_kinematics(UR5E, q_turned), Rz @ forward_kinematics(UR5E, q), atol=1e-12)


def test_camera_pose_is_flange_pose_times_hand_eye(rng):
    q = rng.uniform(-np.pi, np.pi, (5, 6))
    T_flange_camera = se3.from_rotvec_trans(rng.normal(size=3), [0.03, -0.05, 0.08])
    np.testing.assert_allclose(camera_pose(UR5E, q, T_flange_camera),
                               forward_kinematics(UR5E, q) @ T_flange_camera, atol=1e-15)


# --- configuration ----------------------------------------------------------------------------

def test_dh_from_config_by_model_and_by_table():
    assert dh_from_config({"model": "ur5e"}) is UR5E
    assert dh_from_config({"model": "UR10e"}) is UR_MODELS["ur10e"]
    dh = dh_from_config({"dh": UR5E.to_dict()})
    assert dh == UR5E and hash(dh) == hash(UR5E)
    assert dh != UR_MODELS["ur3e"]


@pytest.mark.parametrize("robot, match", [
    ({}, r"robot\.model.*robot\.dh"),
    ({"model": "ur5e", "dh": UR5E.to_dict()}, "exactly one"),
    ({"model": "ur7"}, r"robot\.model.*ur3e, ur5e, ur10e, ur16e"),
    ({"dh": {"a": [0] * 6, "d": [0] * 6}}, r"robot\.dh.*alpha"),
    ({"dh": {"a": [0] * 5, "d": [0] * 6, "alpha": [0] * 6}}, r"robot\.dh.*'a'"),
    ({"dh": {"a": [0] * 6, "d": [0, 0, 0, 0, 0, np.nan], "alpha": [0] * 6}}, r"'d'.*finite"),
    ("ur5e", "mapping"),
])
def test_dh_from_config_errors_name_the_key(robot, match):
    with pytest.raises(ValueError, match=match):
        dh_from_config(robot)


def test_dh_parameters_validate_each_field():
    with pytest.raises(ValueError, match="'alpha'"):
        DHParameters(a=np.zeros(6), d=np.zeros(6), alpha=np.zeros(7))
    with pytest.raises(ValueError, match="'a'"):
        DHParameters(a=np.full(6, np.inf), d=np.zeros(6), alpha=np.zeros(6))


# --- joint interpolation ----------------------------------------------------------------------

STAMPS = np.array([0.0, 0.1, 0.2, 0.4])
Q = np.outer([0.0, 1.0, 2.0, 6.0], np.arange(1.0, 7.0))  # joint j = (j + 1) * 10 * t


def test_interpolation_at_samples_and_between():
    q, valid = interpolate_joints(STAMPS, Q, np.array([0.0, 0.05, 0.1, 0.3, 0.4]))
    assert valid.all()
    np.testing.assert_allclose(q, np.outer([0.0, 0.5, 1.0, 4.0, 6.0], np.arange(1.0, 7.0)), atol=1e-12)


def test_interpolation_outside_the_span_is_invalid_nan():
    q, valid = interpolate_joints(STAMPS, Q, np.array([-0.001, 0.2, 0.40001]))
    np.testing.assert_array_equal(valid, [False, True, False])
    assert np.isnan(q[[0, 2]]).all() and np.isfinite(q[1]).all()


def test_interpolation_next_to_a_nan_sample():
    Q_nan = Q.copy()
    Q_nan[2, 3] = np.nan
    q, valid = interpolate_joints(STAMPS, Q_nan, np.array([0.05, 0.1, 0.15, 0.2, 0.3, 0.4]))
    # 0.15 and 0.3 are bracketed by the NaN sample, 0.2 is it; 0.1 hits its neighbour exactly
    np.testing.assert_array_equal(valid, [True, True, False, False, False, True])
    assert np.isnan(q[~valid]).all()
    np.testing.assert_allclose(q[1], Q[1])


def test_interpolation_edge_cases():
    q, valid = interpolate_joints(np.array([1.0]), Q[:1] + 3.0, np.array([1.0, 1.5]))
    np.testing.assert_array_equal(valid, [True, False])
    np.testing.assert_array_equal(q[0], Q[0] + 3.0)
    q, valid = interpolate_joints(np.zeros(0), np.zeros((0, 6)), np.array([0.0]))
    assert not valid.any() and q.shape == (1, 6)
    q, valid = interpolate_joints(STAMPS, Q, np.zeros(0))
    assert q.shape == (0, 6) and valid.shape == (0,)
    with pytest.raises(ValueError, match="non-decreasing"):
        interpolate_joints(STAMPS[::-1], Q, np.array([0.1]))
    with pytest.raises(ValueError, match=r"\(3, 6\)"):
        interpolate_joints(STAMPS, Q[:3], np.array([0.1]))
