"""app.geometry.quaternion: the Hamilton convention pinned, every operation checked against scipy's
Rotation (scalar last: converted with the module's own boundary functions), the weighted mean
against closed forms."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from app.geometry import quaternion as quat

_finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
_raw4 = arrays(np.float64, (4,), elements=_finite).filter(lambda v: np.linalg.norm(v) > 1e-3)
unit_quats = _raw4.map(lambda v: v / np.linalg.norm(v))
points = arrays(np.float64, (3,), elements=st.floats(-10.0, 10.0, allow_nan=False))
# rotation vectors with angle up to just below pi (log's canonical range), plus tiny ones
rotvecs = st.one_of(
    arrays(np.float64, (3,), elements=st.floats(-1.8, 1.8, allow_nan=False)).filter(
        lambda v: np.linalg.norm(v) < np.pi - 1e-6),
    arrays(np.float64, (3,), elements=st.floats(-1e-9, 1e-9, allow_nan=False)),
)


def scipy_rot(q: np.ndarray) -> Rotation:
    return Rotation.from_quat(quat.to_xyzw(q))


# --- the convention itself ---------------------------------------------------------------------

ONE, I, J, K = np.eye(4)


def test_hamilton_i_times_j_is_k():
    np.testing.assert_array_equal(quat.multiply(I, J), K)
    np.testing.assert_array_equal(quat.multiply(J, I), -K)


def test_hamilton_ijk_is_minus_one():
    np.testing.assert_array_equal(quat.multiply(quat.multiply(I, J), K), -ONE)
    for e in (I, J, K):
        np.testing.assert_array_equal(quat.multiply(e, e), -ONE)


def test_rotation_about_z_by_90_degrees_maps_x_to_y():
    q = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(quat.rotate(q, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(quat.to_matrix(q) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)


def test_xyzw_round_trip_in_tum_order():
    q_wxyz = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_array_equal(quat.to_xyzw(q_wxyz), [0.2, 0.3, 0.4, 0.1])   # TUM: qx qy qz qw
    np.testing.assert_array_equal(quat.from_xyzw([0.2, 0.3, 0.4, 0.1]), q_wxyz)
    batch = np.random.default_rng(0).standard_normal((5, 7, 4))
    np.testing.assert_array_equal(quat.from_xyzw(quat.to_xyzw(batch)), batch)


# --- against scipy -----------------------------------------------------------------------------

@given(unit_quats, unit_quats)
def test_multiply_matches_scipy_composition(q1, q2):
    expected = (scipy_rot(q1) * scipy_rot(q2)).as_quat()
    assert quat.allclose_up_to_sign(quat.multiply(q1, q2), quat.from_xyzw(expected), atol=1e-12)


@given(unit_quats)
def test_to_matrix_matches_scipy(q):
    np.testing.assert_allclose(quat.to_matrix(q), scipy_rot(q).as_matrix(), atol=1e-12)


@given(unit_quats)
def test_from_matrix_recovers_the_quaternion_with_w_nonnegative(q):
    R = scipy_rot(q).as_matrix()
    q_back = quat.from_matrix(R)
    assert q_back[0] >= 0.0
    assert quat.allclose_up_to_sign(q_back, q, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q_back), 1.0, atol=1e-14)


def test_from_matrix_at_the_hard_cases_angle_pi_and_identity():
    for axis in np.eye(3):
        R = Rotation.from_rotvec(np.pi * axis).as_matrix()
        q = quat.from_matrix(R)
        assert quat.allclose_up_to_sign(q, np.concatenate([[0.0], axis]), atol=1e-12)
    np.testing.assert_allclose(quat.from_matrix(np.eye(3)), [1.0, 0.0, 0.0, 0.0], atol=1e-15)


def test_from_matrix_is_batched():
    q = quat.random_uniform(np.random.default_rng(1), 12).reshape(3, 4, 4)
    q_back = quat.from_matrix(quat.to_matrix(q))
    assert q_back.shape == (3, 4, 4)
    np.testing.assert_allclose(q_back, q, atol=1e-12)   # random_uniform already has w >= 0


@given(rotvecs)
def test_exp_map_matches_scipy(v):
    q = quat.exp_map(v)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-14)
    assert quat.allclose_up_to_sign(q, quat.from_xyzw(Rotation.from_rotvec(v).as_quat()), atol=1e-12)


@given(rotvecs)
def test_log_map_inverts_exp_map(v):
    np.testing.assert_allclose(quat.log_map(quat.exp_map(v)), v, atol=1e-12, rtol=1e-10)


@given(unit_quats)
def test_log_map_matches_scipy_and_ignores_the_sign(q):
    expected = Rotation.from_quat(quat.to_xyzw(q)).as_rotvec()
    angle = np.linalg.norm(expected)
    if np.pi - angle < 1e-6:
        return  # at pi, v and -v are the same rotation: compared by the pi test below
    np.testing.assert_allclose(quat.log_map(q), expected, atol=1e-10)
    np.testing.assert_allclose(quat.log_map(-q), expected, atol=1e-10)


def test_log_map_angle_is_at_most_pi():
    q = np.array([-1e-3, 1.0, 0.0, 0.0])
    q /= np.linalg.norm(q)
    v = quat.log_map(q)
    assert np.linalg.norm(v) <= np.pi
    np.testing.assert_allclose(Rotation.from_rotvec(v).as_matrix(), quat.to_matrix(q), atol=1e-12)


def test_exp_and_log_are_accurate_near_identity():
    v = np.array([3e-12, -1e-12, 2e-12])
    q = quat.exp_map(v)
    np.testing.assert_allclose(q[1:], v / 2, rtol=1e-12)
    np.testing.assert_allclose(quat.log_map(q), v, rtol=1e-12)
    np.testing.assert_array_equal(quat.exp_map(np.zeros(3)), [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(quat.log_map(np.array([1.0, 0.0, 0.0, 0.0])), np.zeros(3))


def test_exp_and_log_are_batched():
    v = np.random.default_rng(2).uniform(-1, 1, (2, 5, 3))
    q = quat.exp_map(v)
    assert q.shape == (2, 5, 4)
    np.testing.assert_allclose(quat.log_map(q), v, atol=1e-12)


@given(unit_quats, points)
def test_rotate_matches_scipy_and_the_matrix(q, p):
    expected = scipy_rot(q).apply(p)
    np.testing.assert_allclose(quat.rotate(q, p), expected, atol=1e-11)
    np.testing.assert_allclose(quat.to_matrix(q) @ p, expected, atol=1e-11)


@given(unit_quats)
def test_conjugate_is_the_inverse(q):
    np.testing.assert_allclose(quat.multiply(q, quat.conjugate(q)), [1.0, 0.0, 0.0, 0.0], atol=1e-14)


# --- normalise, angles, helpers ------------------------------------------------------------------

def test_normalize_scales_to_unit_norm_and_refuses_zero():
    np.testing.assert_allclose(quat.normalize([2.0, 0.0, 0.0, 0.0]), [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.linalg.norm(quat.normalize(np.ones((3, 4))), axis=-1), 1.0)
    with pytest.raises(ValueError, match="zero"):
        quat.normalize(np.zeros(4))
    with pytest.raises(ValueError, match="zero"):
        quat.normalize(np.array([[1.0, 0, 0, 0], [0, 0, 0, 0]]))
    with pytest.raises(ValueError, match="non-finite"):
        quat.normalize(np.array([np.nan, 0, 0, 1.0]))


@given(unit_quats, unit_quats)
def test_angle_between_matches_scipy_and_is_sign_invariant(q1, q2):
    expected = (scipy_rot(q1).inv() * scipy_rot(q2)).magnitude()
    assert abs(quat.angle_between(q1, q2) - expected) < 1e-9
    assert abs(quat.angle_between(-q1, q2) - expected) < 1e-9
    assert abs(quat.angle_between(q1, -q2) - expected) < 1e-9


def test_angle_between_resolves_tiny_angles():
    q = quat.random_uniform(np.random.default_rng(3), 1)[0]
    dq = quat.exp_map(np.array([1e-9, 0.0, 0.0]))
    np.testing.assert_allclose(quat.angle_between(q, quat.multiply(q, dq)), 1e-9, rtol=1e-6)
    assert quat.angle_between(q, q) == 0.0


def test_random_uniform_is_unit_and_uniform():
    q = quat.random_uniform(np.random.default_rng(4), 20000)
    assert q.shape == (20000, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)
    # uniform on SO(3): E[q q^T] over the double cover is I/4, and the angle has density (1 - cos)/pi
    np.testing.assert_allclose(q.T @ q / len(q), np.eye(4) / 4, atol=0.01)
    angles = 2 * np.arccos(np.clip(np.abs(q[:, 0]), 0, 1))
    np.testing.assert_allclose(np.mean(angles), np.pi / 2 + 2 / np.pi, atol=0.02)


def test_allclose_up_to_sign():
    q = np.array([0.5, 0.5, 0.5, 0.5])
    assert quat.allclose_up_to_sign(q, -q)
    assert quat.allclose_up_to_sign(np.stack([q, -q]), np.stack([-q, q]))
    assert not quat.allclose_up_to_sign(q, q * [1, -1, 1, 1])


# --- weighted mean (Markley et al. 2007) ----------------------------------------------------------

def test_weighted_mean_of_identical_quaternions_is_that_quaternion():
    q = quat.random_uniform(np.random.default_rng(5), 1)[0]
    mean = quat.weighted_mean(np.tile(q, (7, 1)), np.arange(1.0, 8.0))
    np.testing.assert_allclose(mean, q, atol=1e-12)


def test_weighted_mean_ignores_sign_flips_and_weight_scale():
    rng = np.random.default_rng(6)
    centre = quat.random_uniform(rng, 1)[0]
    q = quat.multiply(centre, quat.exp_map(rng.normal(0, 0.2, (50, 3))))
    w = rng.uniform(0, 1, 50)
    mean = quat.weighted_mean(q, w)
    flips = np.where(rng.uniform(size=(50, 1)) < 0.5, -1.0, 1.0)
    np.testing.assert_allclose(quat.weighted_mean(q * flips, w), mean, atol=1e-12)
    np.testing.assert_allclose(quat.weighted_mean(q, 1e3 * w), mean, atol=1e-12)
    assert mean[0] >= 0
    assert quat.angle_between(mean, centre) < 0.1


def test_weighted_mean_of_two_matches_the_chordal_closed_form():
    # M = w1 q1 q1^T + w2 q2 q2^T has its top eigenvector in span(q1, q2); with d = q1.q2 and
    # r = sqrt((w1 - w2)^2 + 4 w1 w2 d^2) its eigenvalue is (w1 + w2 + r) / 2 and the vector is
    # proportional to (w1 - w2 + r) q1 + 2 w2 d q2 (Markley et al. 2007 give the same two-vector case)
    rng = np.random.default_rng(7)
    for _ in range(20):
        q1, q2 = quat.random_uniform(rng, 2)
        w1, w2 = rng.uniform(0.1, 1.0, 2)
        d = q1 @ q2
        r = np.sqrt((w1 - w2) ** 2 + 4 * w1 * w2 * d**2)
        expected = (w1 - w2 + r) * q1 + 2 * w2 * d * q2
        expected /= np.linalg.norm(expected)
        assert quat.allclose_up_to_sign(quat.weighted_mean(np.stack([q1, q2]), np.array([w1, w2])),
                                        expected, atol=1e-10)


def test_weighted_mean_with_equal_weights_lies_halfway():
    q1 = quat.exp_map(np.array([0.0, 0.0, 0.4]))
    q2 = quat.exp_map(np.array([0.0, 0.0, -0.2]))
    mean = quat.weighted_mean(np.stack([q1, -q2]), np.array([2.0, 2.0]))
    np.testing.assert_allclose(mean, quat.exp_map(np.array([0.0, 0.0, 0.1])), atol=1e-12)


def test_weighted_mean_rejects_bad_weights():
    q = quat.random_uniform(np.random.default_rng(8), 3)
    with pytest.raises(ValueError, match="non-negative"):
        quat.weighted_mean(q, np.array([1.0, -0.5, 1.0]))
    with pytest.raises(ValueError, match="positive sum"):
        quat.weighted_mean(q, np.zeros(3))
    with pytest.raises(ValueError, match=r"\(3,\)"):
        quat.weighted_mean(q, np.ones(4))
