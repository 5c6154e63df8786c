"""Log-weights: log-sum-exp, normalisation, ESS, and NaN flags that never touch the caller's array."""
from __future__ import annotations

import numpy as np

from app.filter import weights as lw


def test_log_sum_exp_matches_the_direct_sum_and_survives_large_values():
    x = np.array([0.1, -2.0, 3.5])
    assert np.isclose(lw.log_sum_exp(x), np.log(np.exp(x).sum()))
    assert np.isclose(lw.log_sum_exp(x + 1e4), np.log(np.exp(x).sum()) + 1e4)
    assert np.isclose(lw.log_sum_exp(x - 1e4), np.log(np.exp(x).sum()) - 1e4)


def test_log_sum_exp_of_all_minus_inf_is_minus_inf():
    assert lw.log_sum_exp(np.full(3, -np.inf)) == -np.inf
    assert lw.log_sum_exp(np.array([-np.inf, 0.0])) == 0.0


def test_normalised_weights_sum_to_one(rng):
    x = rng.normal(0, 50, 100)
    assert np.isclose(np.exp(lw.normalise_log_weights(x)).sum(), 1.0)
    assert np.isclose(lw.normalised_weights(x).sum(), 1.0)


def test_ess_is_n_for_uniform_and_one_for_a_single_particle():
    assert np.isclose(lw.ess(np.zeros(50)), 50.0)
    assert np.isclose(lw.ess(np.full(50, -7.3)), 50.0)
    single = np.full(50, -np.inf)
    single[3] = 0.0
    assert np.isclose(lw.ess(single), 1.0)


def test_ess_equals_inverse_sum_of_squared_weights(rng):
    x = rng.normal(0, 2, 200)
    W = np.exp(x) / np.exp(x).sum()
    assert np.isclose(lw.ess(x), 1.0 / np.sum(W**2))


def test_nonfinite_mask_flags_nan_and_plus_inf_without_modifying_the_input():
    x = np.array([0.0, np.nan, -np.inf, np.inf, -3.0])
    before = x.copy()
    mask = lw.nonfinite_mask(x)
    np.testing.assert_array_equal(mask, [False, True, False, True, False])
    np.testing.assert_array_equal(x, before)  # NaN compares unequal, assert_array_equal handles it


def test_uniform_log_weights_are_normalised():
    assert np.isclose(lw.log_sum_exp(lw.uniform_log_weights(17)), 0.0)
