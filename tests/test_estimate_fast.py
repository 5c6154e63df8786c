"""The filter's per-frame arithmetic written for speed gives the values of the general functions it
replaces, to the bit, on random inputs: the estimate (quat.weighted_mean, quat.angle_between,
se3.from_quat_trans) and the particles' poses and prediction (app/filter/motion.py)."""
from __future__ import annotations

import numpy as np
import pytest

from app.filter import motion
from app.filter.estimate import PoseEstimate, estimate
from app.filter.weights import normalised_weights
from app.geometry import quaternion as quat
from app.geometry import se3


def reference_estimate(p, q, lw) -> PoseEstimate:
    """The estimate as written before (general functions)."""
    W = normalised_weights(lw)
    p_mean = W @ p
    d = p - p_mean
    cov = np.einsum("n,ni,nj->ij", W, d, d)
    q_mean = quat.weighted_mean(q, W)
    theta = quat.angle_between(q, q_mean[None])
    return PoseEstimate(se3.from_quat_trans(q_mean, p_mean), float(np.sqrt(max(np.trace(cov), 0.0))),
                        np.sqrt(np.maximum(np.diag(cov), 0.0)), float(np.sqrt(W @ theta**2)))


def random_particles(rng, n, spread):
    q = quat.multiply(quat.exp_map(rng.normal(0, spread, (n, 3))), quat.exp_map(rng.normal(0, 2.0, 3))[None])
    q[rng.random(n) < 0.5] *= -1.0                  # any signs
    return rng.normal(0.0, 0.01, (n, 3)) + rng.normal(0, 0.3, 3), q


@pytest.mark.parametrize("n, spread", [(1, 0.1), (7, 1e-9), (200, 0.05), (1000, 1.5)])
def test_the_estimate_equals_the_general_functions_to_the_bit(rng, n, spread):
    for _ in range(5):
        p, q = random_particles(rng, n, spread)
        lw = rng.normal(0.0, 5.0, n)
        lw[rng.random(n) < 0.2] = -np.inf
        lw[0] = 0.0
        got, want = estimate(p, q, lw), reference_estimate(p, q, lw)
        np.testing.assert_array_equal(got.T_base_bone, want.T_base_bone)
        np.testing.assert_array_equal(got.position_std, want.position_std)
        assert got.position_spread == want.position_spread and got.rotation_spread == want.rotation_spread


def test_invalid_weights_still_raise_the_clear_error():
    p, q = np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1))
    for lw in (np.full(3, np.nan), np.full(3, -np.inf)):
        with pytest.raises(ValueError, match="weighted_mean needs"):
            estimate(p, q, lw)


@pytest.mark.parametrize("n", [1, 200, 1000])
def test_the_particles_poses_and_rotation_step_equal_the_general_functions_to_the_bit(rng, n):
    p, q = random_particles(rng, n, 0.3)
    state = motion.ParticleState(p, np.zeros((n, 3)), q, np.zeros((n, 3)), np.zeros(n))
    np.testing.assert_array_equal(state.poses(), se3.from_quat_trans(q, p))
    rotvec = rng.normal(0, 0.05, (n, 3))
    rotvec[0] = 0.0                                  # the small-angle branch
    rotvec[-1] = 1e-9
    np.testing.assert_array_equal(motion._rotate_left(rotvec, q), quat.multiply(quat.exp_map(rotvec), q))
