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


@pytest.mark.parametrize("n", [0, 1, 2, 200, 1000])
def test_the_shifts_quaternions_by_runs_equal_from_matrix_to_the_bit(rng, n):
    """particle_filter.from_matrix_runs (one eigh per run of equal rotations) gives quat.from_matrix's
    values, on resampled clouds (runs of copies, systematic resampling's order), clouds without copies,
    and rotations differing from their neighbour only in a zero's sign or one bit; and
    ParticleFilter.shift_to's cloud is the one computed with from_matrix over all particles."""
    from app.filter import resampling
    from app.filter.particle_filter import FilterConfig, ParticleFilter, from_matrix_runs

    for spread in (0.05, 1.5):
        p, q = random_particles(rng, n, spread)
        state = motion.ParticleState(p, np.zeros((n, 3)), q, np.zeros((n, 3)), rng.normal(0.0, 3.0, n))
        if n:
            state = state.take(resampling.systematic(state.lw, rng.random()))
        delta = se3.from_quat_trans(quat.exp_map(rng.normal(0, 0.1, 3)), rng.normal(0, 0.01, 3))
        R = (delta @ state.poses())[:, :3, :3]
        np.testing.assert_array_equal(from_matrix_runs(R), quat.from_matrix(R))
        np.testing.assert_array_equal(from_matrix_runs(R[::-1]), quat.from_matrix(R[::-1]))
        if n >= 2:
            twins = np.repeat(R[:1], n, axis=0)
            twins[1::3, 0, 1] = -twins[1::3, 0, 1] if twins[0, 0, 1] == 0 else np.nextafter(twins[1::3, 0, 1], 2.0)
            twins[2::5, 2, 2] = np.nextafter(twins[2::5, 2, 2], -2.0)
            np.testing.assert_array_equal(from_matrix_runs(twins), quat.from_matrix(twins))
            zeros = np.repeat(np.eye(3)[None], n, axis=0)
            zeros[::2, 0, 1] = -0.0                          # -0.0 == 0.0, but not the same bits
            np.testing.assert_array_equal(from_matrix_runs(zeros), quat.from_matrix(zeros))

        pf = ParticleFilter(FilterConfig(particles=max(n, 1)), model=None, rng=rng)
        if n:
            pf.state = state.copy()
            T_old = se3.from_quat_trans(quat.exp_map(rng.normal(0, 0.3, 3)), rng.normal(0, 0.1, 3))
            T_new = delta @ T_old
            pf.shift_to(T_new, T_old)
            poses = (T_new @ se3.inverse(T_old)) @ state.poses()
            np.testing.assert_array_equal(pf.state.q, quat.from_matrix(poses[:, :3, :3]))
            np.testing.assert_array_equal(pf.state.p, poses[:, :3, 3])
