"""Log-weights: normalisation with log-sum-exp and the effective sample size.

Import as ``from app.filter import weights as lw``. Conventions (DESIGN.md, "Weights and
resampling"; STYLE.md §6): the filter stores un-normalised log-weights ``lw`` (N,) float64;
``w̄_j += log p(z | x_j)`` each weighing; normalised weights are ``W = exp(lw - LSE(lw))``.

- ``log_sum_exp(lw)  = m + log Σ_j exp(lw_j - m)``, with m = max(lw) (stable; -inf when every
  entry is -inf);
- ``normalise_log_weights(lw) = lw - LSE(lw)``, so that Σ exp(.) = 1;
- ``ess(lw) = exp(2 LSE(lw) - LSE(2 lw)) = (Σ W_j)² / Σ W_j²``, in [1, N].

NaN handling: nothing here writes into the caller's array. ``nonfinite_mask`` flags the NaN / +inf
entries of a log-likelihood vector; the stepper (:mod:`app.filter.particle_filter`) sets them to
-inf in its own copy and counts them. When every log-weight is -inf, ``log_sum_exp`` is -inf and
``normalise_log_weights`` returns NaN: the caller decides (the stepper resets to uniform weights
and reports it).
"""
from __future__ import annotations

import numpy as np


def log_sum_exp(lw: np.ndarray) -> float:
    """log Σ_j exp(lw_j), computed stably.

    Parameters
    ----------
    lw : (N,) float64 log-weights; -inf entries allowed, NaN not (propagates)

    Returns
    -------
    float: -inf when every entry is -inf (or N = 0)
    """
    lw = np.asarray(lw, dtype=float)
    if lw.size == 0:
        return -np.inf
    m = np.max(lw)
    if not np.isfinite(m):
        return float(m)  # all -inf -> -inf; +inf / NaN propagate
    return float(m + np.log(np.sum(np.exp(lw - m))))


def normalise_log_weights(lw: np.ndarray) -> np.ndarray:
    """lw - LSE(lw): log-weights whose exponentials sum to one; a new (N,) array."""
    lw = np.asarray(lw, dtype=float)
    return lw - log_sum_exp(lw)


def normalised_weights(lw: np.ndarray) -> np.ndarray:
    """W = exp(lw - LSE(lw)), (N,) float64, summing to one."""
    return np.exp(normalise_log_weights(lw))


def ess(lw: np.ndarray) -> float:
    """Effective sample size exp(2 LSE(lw) - LSE(2 lw)) = 1 / Σ W_j², in [1, N] (NaN if all -inf)."""
    lw = np.asarray(lw, dtype=float)
    return float(np.exp(2.0 * log_sum_exp(lw) - log_sum_exp(2.0 * lw)))


def uniform_log_weights(n: int) -> np.ndarray:
    """(n,) normalised uniform log-weights, -log n each."""
    return np.full(n, -np.log(n))


def nonfinite_mask(log_lik: np.ndarray) -> np.ndarray:
    """(N,) bool: True where a log-likelihood is NaN or +inf (a backend failure, never a value).

    -inf is a legitimate value (zero likelihood) and is not flagged.
    """
    log_lik = np.asarray(log_lik, dtype=float)
    return np.isnan(log_lik) | (log_lik == np.inf)
