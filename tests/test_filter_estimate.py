"""Weighted mean pose and spreads."""
from __future__ import annotations

import numpy as np

from app.filter import estimate as est
from app.geometry import quaternion as quat
from app.geometry import se3


def test_weighted_mean_ignores_quaternion_signs(rng):
    q0 = quat.exp_map(np.array([0.3, -0.2, 1.0]))
    q = quat.multiply(quat.exp_map(rng.normal(0, 0.05, (500, 3))), q0)
    p = rng.normal(0, 0.002, (500, 3)) + [0.1, 0.2, 0.3]
    lw = rng.normal(0, 1, 500)
    flipped = q * np.where(rng.random(500) < 0.5, -1.0, 1.0)[:, None]
    a = est.estimate(p, q, lw)
    b = est.estimate(p, flipped, lw)
    np.testing.assert_allclose(a.T_base_bone, b.T_base_bone, atol=1e-12)
    assert np.isclose(a.rotation_spread, b.rotation_spread)
    assert quat.angle_between(se3.to_quat_trans(a.T_base_bone)[0], q0) < 0.01


def test_weighted_mean_position_and_spread_match_the_weighted_moments(rng):
    p = rng.normal(0, 0.003, (1000, 3))
    q = np.tile([1.0, 0, 0, 0], (1000, 1))
    lw = rng.normal(0, 0.5, 1000)
    W = np.exp(lw) / np.exp(lw).sum()
    e = est.estimate(p, q, lw)
    mean = W @ p
    np.testing.assert_allclose(e.T_base_bone[:3, 3], mean)
    np.testing.assert_allclose(e.position_std, np.sqrt(W @ (p - mean) ** 2))
    assert np.isclose(e.position_spread, np.sqrt(np.sum(W @ (p - mean) ** 2)))
    assert e.rotation_spread < 1e-7


def test_rotation_spread_is_the_rms_angle_to_the_mean():
    q0 = np.array([1.0, 0, 0, 0])
    angles = np.array([0.02, -0.02, 0.0, 0.0])
    q = quat.multiply(quat.exp_map(np.stack([angles, 0 * angles, 0 * angles], 1)), q0)
    e = est.estimate(np.zeros((4, 3)), q, np.zeros(4))
    assert np.isclose(e.rotation_spread, np.sqrt(np.mean(angles**2)))


def test_a_single_dominant_particle_gives_its_pose(rng):
    q = quat.random_uniform(rng, 10)
    p = rng.normal(0, 1, (10, 3))
    lw = np.full(10, -np.inf)
    lw[7] = 0.0
    e = est.estimate(p, q, lw)
    np.testing.assert_allclose(e.T_base_bone, se3.from_quat_trans(q[7], p[7]), atol=1e-12)
    assert e.position_spread == 0.0 and e.rotation_spread < 1e-7
    np.testing.assert_allclose(est.weighted_mean_pose(p, q, lw), e.T_base_bone, atol=1e-12)
