"""app.geometry.se3: poses built from quaternions / rotation vectors against scipy, the closed-form
inverse, composition order (T_a_c = T_a_b @ T_b_c), distances and the rigidity check."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.geometry import quaternion as quat
from app.geometry import se3


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return se3.from_quat_trans(quat.random_uniform(rng, n), rng.uniform(-1, 1, (n, 3)))


def test_make_pose_places_rotation_and_translation():
    R = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix()
    T = se3.make_pose(R, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(T[:3, :3], R)
    np.testing.assert_array_equal(T[:3, 3], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    # broadcasting: one rotation, many translations
    assert se3.make_pose(R, np.zeros((5, 3))).shape == (5, 4, 4)


def test_quat_trans_round_trip_and_scipy_agreement(rng):
    q = quat.random_uniform(rng, 30)
    t = rng.uniform(-1, 1, (30, 3))
    T = se3.from_quat_trans(q, t)
    np.testing.assert_allclose(T[:, :3, :3], Rotation.from_quat(quat.to_xyzw(q)).as_matrix(), atol=1e-12)
    q_back, t_back = se3.to_quat_trans(T)
    np.testing.assert_allclose(q_back, q, atol=1e-12)   # both have w >= 0
    np.testing.assert_array_equal(t_back, t)


def test_from_rotvec_trans_matches_scipy(rng):
    v = rng.uniform(-2, 2, (10, 3))
    T = se3.from_rotvec_trans(v, np.zeros(3))
    np.testing.assert_allclose(T[:, :3, :3], Rotation.from_rotvec(v).as_matrix(), atol=1e-12)


def test_inverse_is_the_matrix_inverse_batched(rng):
    T = random_poses(rng, 20).reshape(4, 5, 4, 4)
    T_inv = se3.inverse(T)
    assert T_inv.shape == (4, 5, 4, 4)
    np.testing.assert_allclose(T_inv, np.linalg.inv(T), atol=1e-12)
    np.testing.assert_allclose(T @ T_inv, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


def test_compose_applies_right_to_left_to_points(rng):
    T_a_b, T_b_c = random_poses(rng, 2)
    p_c = rng.uniform(-1, 1, (7, 3))
    T_a_c = se3.compose(T_a_b, T_b_c)
    np.testing.assert_allclose(se3.transform_points(T_a_c, p_c),
                               se3.transform_points(T_a_b, se3.transform_points(T_b_c, p_c)), atol=1e-12)
    np.testing.assert_allclose(se3.compose(T_a_b, T_b_c, se3.inverse(T_b_c)), T_a_b, atol=1e-12)


def test_transform_points_matches_homogeneous_product(rng):
    T = random_poses(rng, 1)[0]
    p = rng.uniform(-1, 1, (9, 3))
    homogeneous = (T @ np.column_stack([p, np.ones(9)]).T).T
    np.testing.assert_allclose(se3.transform_points(T, p), homogeneous[:, :3], atol=1e-12)


def test_rotation_angle_and_translation_distance(rng):
    T_a = random_poses(rng, 1)[0]
    delta = se3.from_rotvec_trans(np.array([0.0, 0.3, 0.4]), np.array([0.0, 0.0, 0.0]))
    T_b = T_a @ delta
    T_b[:3, 3] = T_a[:3, 3] + [0.03, 0.04, 0.0]
    np.testing.assert_allclose(se3.rotation_angle(T_a, T_b), 0.5, atol=1e-12)
    np.testing.assert_allclose(se3.translation_distance(T_a, T_b), 0.05, atol=1e-15)
    # tiny angles stay accurate (no arccos of the trace)
    T_c = T_a @ se3.from_rotvec_trans(np.array([1e-9, 0.0, 0.0]), np.zeros(3))
    np.testing.assert_allclose(se3.rotation_angle(T_a, T_c), 1e-9, rtol=1e-5)
    # batched
    Ts = random_poses(rng, 6)
    expected = [quat.angle_between(*se3.to_quat_trans(np.stack([T_a, T]))[0]) for T in Ts]
    np.testing.assert_allclose(se3.rotation_angle(T_a, Ts), expected, atol=1e-12)


def test_is_rigid_accepts_poses_and_rejects_the_rest(rng):
    T = random_poses(rng, 3)
    assert se3.is_rigid(T[0]) and se3.is_rigid(T)
    scaled = T[0].copy()
    scaled[:3, :3] *= 1.01
    assert not se3.is_rigid(scaled)
    mirrored = T[0] @ np.diag([1.0, 1.0, -1.0, 1.0])
    assert not se3.is_rigid(mirrored)
    bad_row = T[0].copy()
    bad_row[3, 0] = 0.5
    assert not se3.is_rigid(bad_row)
    nan = T[0].copy()
    nan[0, 3] = np.nan
    assert not se3.is_rigid(nan)
    assert not se3.is_rigid(np.eye(3))


def test_compose_needs_at_least_one_pose():
    with pytest.raises(ValueError, match="at least one"):
        se3.compose()
