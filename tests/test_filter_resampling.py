"""Resampling: unbiased copies, systematic's low-variance promise, agreement with `particles`."""
from __future__ import annotations

import numpy as np
import pytest

from app.filter import resampling as rs


def random_log_weights(rng, n=40):
    x = rng.normal(0, 1.5, n)
    x[rng.random(n) < 0.2] = -np.inf  # some particles have zero weight
    x[0] = 0.0
    return x


@pytest.mark.parametrize("scheme", sorted(rs.SCHEMES))
def test_mean_copies_of_each_particle_equal_n_times_its_weight(scheme, rng):
    x = random_log_weights(rng)
    n = len(x)
    W = np.exp(x - np.logaddexp.reduce(x))
    draws = 4000
    counts = np.zeros(n)
    for _ in range(draws):
        A = rs.resample(scheme, x, rng)
        assert A.shape == (n,) and A.dtype == np.int64
        assert A.min() >= 0 and A.max() < n
        counts += np.bincount(A, minlength=n)
    mean = counts / draws
    # multinomial copies have variance N W (1 - W); the others less; 5 standard errors
    se = np.sqrt(n * W * (1 - W) / draws) + 1e-12
    assert np.all(np.abs(mean - n * W) <= 5 * se + 1e-9)
    assert np.all(counts[W == 0] == 0), "a zero-weight particle was copied"


def test_systematic_copies_are_floor_or_ceil_of_n_times_the_weight(rng):
    for _ in range(300):
        x = random_log_weights(rng, n=int(rng.integers(2, 60)))
        n = len(x)
        NW = n * np.exp(x - np.logaddexp.reduce(x))
        counts = np.bincount(rs.systematic(x, rng.random()), minlength=n)
        assert np.all(counts >= np.floor(NW - 1e-9)) and np.all(counts <= np.ceil(NW + 1e-9))


def test_systematic_matches_particles_library_given_the_same_uniform(rng):
    particles_rs = pytest.importorskip("particles.resampling")
    for _ in range(50):
        x = random_log_weights(rng, n=100)
        W = np.exp(x - np.logaddexp.reduce(x))
        u = rng.random()
        M = len(W)
        # particles.resampling.systematic(W, M) is inverse_cdf((rand(1) + arange(M)) / M, W):
        # feed its inner function the same uniform
        expected = particles_rs.inverse_cdf((np.array([u]) + np.arange(M)) / M, W)
        np.testing.assert_array_equal(rs.systematic(x, u), expected)


def test_systematic_is_invariant_to_the_normalisation_of_the_log_weights(rng):
    x = random_log_weights(rng)
    np.testing.assert_array_equal(rs.systematic(x, 0.37), rs.systematic(x + 1234.5, 0.37))
    np.testing.assert_array_equal(rs.systematic(x, 0.37), rs.systematic(x - 800.0, 0.37))


def test_uniform_weights_with_systematic_keep_every_particle_once():
    np.testing.assert_array_equal(rs.systematic(np.zeros(10), 0.5), np.arange(10))


def test_an_unknown_scheme_is_rejected_with_the_valid_names(rng):
    with pytest.raises(ValueError, match="multinomial, stratified, systematic"):
        rs.resample("sytematic", np.zeros(4), rng)
