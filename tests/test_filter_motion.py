"""Motion model: one-step statistics against the closed form, dropped frames, initialisers."""
from __future__ import annotations

import numpy as np
import pytest

from app.filter import motion
from app.geometry import quaternion as quat
from app.geometry import se3

N = 200_000


def state_at(n, p0, v0, q0=(1.0, 0, 0, 0), omega0=(0, 0, 0)):
    return motion.ParticleState(
        p=np.tile(np.asarray(p0, float), (n, 1)), v=np.tile(np.asarray(v0, float), (n, 1)),
        q=np.tile(np.asarray(q0, float), (n, 1)), omega=np.tile(np.asarray(omega0, float), (n, 1)),
        lw=np.zeros(n))


def position_moments(dt, params, rng, v0=(0.1, -0.2, 0.05)):
    s = motion.predict_position(state_at(N, (0.3, 0.0, 0.5), v0), dt, params, rng)
    return s, np.cov(np.hstack([s.p[:, :1], s.v[:, :1]]).T)


@pytest.mark.parametrize("dt", [1 / 90, 1 / 30])
def test_position_step_matches_the_closed_form(dt, rng):
    params = motion.MotionParams(sigma_a=5.0, lambda_v=0.9)
    s, cov = position_moments(dt, params, rng)
    sa2 = params.sigma_a**2
    np.testing.assert_allclose(s.p.mean(0), np.array([0.3, 0.0, 0.5]) + dt * np.array([0.1, -0.2, 0.05]),
                               atol=5 * np.sqrt(dt**4 / 4 * sa2 / N))
    np.testing.assert_allclose(s.v.mean(0), 0.9 * np.array([0.1, -0.2, 0.05]), atol=5 * np.sqrt(dt**2 * sa2 / N))
    expected = np.array([[dt**4 / 4 * sa2, dt**3 / 2 * sa2], [dt**3 / 2 * sa2, dt**2 * sa2]])
    np.testing.assert_allclose(cov, expected, rtol=0.02)


def test_a_dropped_frame_scales_the_variance_as_the_closed_form(rng):
    params = motion.MotionParams()
    _, cov1 = position_moments(1 / 90, params, rng)
    _, cov2 = position_moments(2 / 90, params, rng)
    np.testing.assert_allclose(cov2 / cov1, [[16, 8], [8, 4]], rtol=0.03)


def test_orientation_increment_has_the_model_mean_and_covariance(rng):
    params = motion.MotionParams(sigma_alpha=50.0, lambda_v=0.9)
    dt = 1 / 30
    q0 = quat.exp_map(np.array([0.4, -1.0, 2.0]))
    omega0 = np.array([0.5, -1.0, 0.3])
    s = motion.predict_orientation(state_at(N, (0, 0, 0), (0, 0, 0), q0, omega0), dt, params, rng)
    # base-frame rate: the increment is q_t ⊗ q_{t-1}^-1 (left), its rotation vector is dt ω_t
    inc = quat.log_map(quat.multiply(s.q, quat.conjugate(q0)))
    np.testing.assert_allclose(inc, dt * s.omega, atol=1e-9)
    sd = dt**2 * params.sigma_alpha
    np.testing.assert_allclose(inc.mean(0), dt * 0.9 * omega0, atol=5 * sd / np.sqrt(N))
    np.testing.assert_allclose(np.cov(inc.T), sd**2 * np.eye(3), atol=0.02 * sd**2)
    np.testing.assert_allclose(np.linalg.norm(s.q, axis=1), 1.0, atol=1e-12)


def test_constant_rate_without_noise_rotates_about_a_base_axis(rng):
    params = motion.MotionParams(sigma_alpha=0.0, lambda_v=1.0, sigma_a=0.0)
    q0 = quat.exp_map(np.array([0.0, 1.0, 0.0]))
    s = state_at(1, (0.1, 0.2, 0.3), (0.01, 0, 0), q0, (0.0, 0.0, np.pi))
    for _ in range(10):
        s = motion.predict(s, 0.05, params, rng)
    # half a turn about the base z axis, applied on the left
    expected = quat.multiply(quat.exp_map(np.array([0.0, 0.0, np.pi / 2])), q0)
    assert quat.allclose_up_to_sign(s.q[0], expected, atol=1e-9)
    np.testing.assert_allclose(s.p[0], [0.1 + 0.005, 0.2, 0.3])


def test_initialise_spreads_particles_around_the_pose(rng):
    T = se3.from_quat_trans(quat.exp_map(np.array([0.2, 0.3, -0.1])), np.array([0.1, 0.0, 0.4]))
    s = motion.initialise(T, 20_000, sigma_p=0.01, sigma_r=0.05, rng=rng)
    assert s.n == 20_000 and np.allclose(np.exp(s.lw).sum(), 1.0)
    np.testing.assert_allclose(s.p.mean(0), T[:3, 3], atol=5e-4)
    np.testing.assert_allclose(s.p.std(0), 0.01, rtol=0.03)
    q0, _ = se3.to_quat_trans(T)
    r = quat.log_map(quat.multiply(s.q, quat.conjugate(q0)))
    np.testing.assert_allclose(r.std(0), 0.05, rtol=0.03)
    assert np.all(s.v == 0) and np.all(s.omega == 0)


def test_initialise_from_point_puts_the_bone_point_on_the_prior(rng):
    q = quat.random_uniform(rng, 5000)
    point_bone = np.array([0.02, -0.01, 0.005])
    s = motion.initialise_from_point(np.array([0.1, 0.2, 0.3]), q, 5000, sigma_p=0.005, rng=rng,
                                     point_bone=point_bone)
    x = s.p + quat.rotate(s.q, np.tile(point_bone, (5000, 1)))
    np.testing.assert_allclose(x.mean(0), [0.1, 0.2, 0.3], atol=5e-4)
    np.testing.assert_allclose(x.std(0), 0.005, rtol=0.05)
    np.testing.assert_array_equal(s.q, q)


def test_take_copies_ancestors_and_resets_weights():
    s = state_at(4, (0, 0, 0), (0, 0, 0))
    s.p[:, 0] = np.arange(4)
    s.lw = np.array([0.0, -1.0, -2.0, -3.0])
    t = s.take(np.array([0, 0, 1, 3]))
    np.testing.assert_array_equal(t.p[:, 0], [0, 0, 1, 3])
    np.testing.assert_allclose(t.lw, -np.log(4))
    np.testing.assert_array_equal(s.p[:, 0], np.arange(4))  # the source state is unchanged
