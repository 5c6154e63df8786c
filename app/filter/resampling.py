"""Resampling in the log domain: ancestor indices from log-weights.

Import as ``from app.filter import resampling as rs``. Contract of every scheme (as in
nchopin/particles' ``resampling.py``): log-weights ``lw`` (N,) (any normalisation; -inf allowed,
not all -inf) in, ancestor indices ``A`` (N,) int64 in [0, N) out; particle i is copied as many
times as i appears in A. Every stochastic scheme takes ``rng: np.random.Generator``.

Schemes, registered by name in ``SCHEMES`` (``resample(scheme, lw, rng)`` raises ValueError
listing the valid names):

- ``systematic`` (default; (A) Alg. 1 / (B) Alg. 1): one uniform u ~ U[0, 1), the N points
  s_n = (u + n) / N, n = 0..N-1; A_n is the first j whose cumulative weight C_j = Σ_{i<=j} W_i
  satisfies C_j >= s_n. Computed in the log domain: log C_j = logaddexp.accumulate(lw - LSE(lw))
  compared with log s_n. Low variance: the number of copies of particle i is floor(N W_i) or
  ceil(N W_i).
- ``stratified``: s_n = (u_n + n) / N with N independent uniforms.
- ``multinomial``: N sorted independent uniforms (not recommended: the noisiest).

With the same uniform draw, ``systematic`` returns the same ancestors as
``particles.resampling.systematic`` (its ``inverse_cdf`` picks the first j with C_j >= s_n too).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from app.filter.weights import normalise_log_weights

DEFAULT_SCHEME = "systematic"


def _inverse_cdf_log(log_s: np.ndarray, lw: np.ndarray) -> np.ndarray:
    """First j with log C_j >= log s_n for sorted points s_n (log domain inverse CDF)."""
    log_c = np.logaddexp.accumulate(normalise_log_weights(lw))
    # rounding can leave log C_{N-1} slightly below 0 = log 1: clip to the last particle
    return np.minimum(np.searchsorted(log_c, log_s, side="left"), len(lw) - 1).astype(np.int64)


def _log_points(s: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(s)


def systematic(lw: np.ndarray, u: float, n: int | None = None) -> np.ndarray:
    """Systematic resampling with the given uniform draw u in [0, 1) ((A) Alg. 1).

    Parameters
    ----------
    lw : (N,) log-weights, not all -inf
    u : the single uniform variate
    n : number of draws (default N; another count selects n of N, e.g. the one-point
        initialiser keeping its particles out of a wider first draw)

    Returns
    -------
    (n,) int64 ancestor indices, non-decreasing
    """
    n = len(lw) if n is None else int(n)
    return _inverse_cdf_log(_log_points((u + np.arange(n)) / n), lw)


def systematic_rng(lw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling drawing its uniform from ``rng``."""
    return systematic(lw, rng.random())


def stratified(lw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Stratified resampling: one uniform per stratum [n/N, (n+1)/N)."""
    n = len(lw)
    return _inverse_cdf_log(_log_points((rng.random(n) + np.arange(n)) / n), lw)


def multinomial(lw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Multinomial resampling: N independent draws from W (sorted uniforms, inverse CDF)."""
    n = len(lw)
    return _inverse_cdf_log(_log_points(np.sort(rng.random(n))), lw)


SCHEMES: dict[str, Callable[[np.ndarray, np.random.Generator], np.ndarray]] = {
    "systematic": systematic_rng,
    "stratified": stratified,
    "multinomial": multinomial,
}


def check_scheme(scheme: str) -> None:
    """Raise ValueError naming the valid schemes when ``scheme`` is not one of them."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown resampling scheme {scheme!r}; valid: {', '.join(sorted(SCHEMES))}")


def resample(scheme: str, lw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Ancestor indices (N,) int64 drawn with the named scheme (see the module docstring)."""
    check_scheme(scheme)
    return SCHEMES[scheme](np.asarray(lw, dtype=float), rng)
