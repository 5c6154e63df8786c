"""One level for every statistical test of the status and the lifecycle (issue 32, DESIGN.md "The status
as a test"): ``status.alpha``, the probability that a right pose fails one test by chance on one frame.

Import as ``from app.tracking import levels``. Each test turns the one level into its critical value:

- the consistency test (``behind``; app/tracking/fit_test.py, app/filter/refine.py): the count of
  measurements behind the model against its Poisson-binomial mean plus z standard deviations, one-sided,
  z = -Φ⁻¹(α) (:func:`normal_level`; α = Φ(-3) = 0.135 % gives the 3 sd it had as ``refine.behind_z``);
- the held pose's test (``held``; app/filter/static_prior.py): Δχ² = δᵀ (H / inflation) δ is χ²₆ / inflation
  under the image's uninflated noise, so the bound is χ²₆(1 - α) / ``status.covariance_inflation``
  (:func:`held_level`; it was ``status.max_held_chi2`` = 4, P ~ 5e-4);
- the wide search's bar on a found fit's share within 1 σ (:func:`sharp_bar`): ``status.min_fitness``'s share
  within 3 σ carried to 1 σ for Gaussian residuals (0.411; it was ``recovery.search_min_sharp`` = 0.5);
- the start's prior (the ``outside_start`` trigger; app/filter/recovery.py): a never-ok track farther from
  its start pose than k of the start's sigmas, k² = χ²₃(1 - α) (:func:`chi_level`; it was
  ``recovery.start_sigmas`` = 4.03, α 0.1 %).

The χ² survival functions for an integer number of degrees of freedom k are closed forms (Abramowitz &
Stegun 26.4.4-26.4.5): for even k, Q(x; k) = e^{-x/2} Σ_{i<k/2} (x/2)^i / i!; for odd k,
Q(x; k) = 2 Φ(-√x) + 2 φ(√x) Σ_{i=1}^{(k-1)/2} x^{i-1/2} / (1·3·…·(2i-1)). The quantile is found by
bisection (Q falls monotonically in x).
"""
from __future__ import annotations

import functools
import math
from statistics import NormalDist

ALPHA = NormalDist().cdf(-3.0)       # status.alpha's default: one-sided 3 sd, 0.135 %
_STANDARD = NormalDist()


def normal_level(alpha: float) -> float:
    """z with P(Z > z) = alpha, Z standard normal (one-sided)."""
    return -_STANDARD.inv_cdf(alpha)


def sharp_bar(min_fitness: float, sharp_sigmas: float = 1.0, confirm_sigmas: float = 3.0) -> float:
    """The share within ``sharp_sigmas`` σ that goes with a fitness of ``min_fitness`` within ``confirm_sigmas`` σ
    for Gaussian residuals: min_fitness (2Φ(s) − 1) / (2Φ(c) − 1) (0.6 -> 0.411 at 1 and 3 σ). The wide search's
    bar on a found fit's consistent sharp share (issue 32, merge 12: it was ``recovery.search_min_sharp``, 0.5;
    one fit-quality share, ``status.min_fitness``, asked of the fit at both widths)."""
    return float(min_fitness) * _within(sharp_sigmas) / _within(confirm_sigmas)


def _within(k: float) -> float:
    """P(|Z| < k) for a standard normal Z: 2Φ(k) − 1."""
    return 2.0 * _STANDARD.cdf(k) - 1.0


def chi2_sf(x: float, dof: int) -> float:
    """P(χ²_dof > x) for an integer dof >= 1 (module docstring: A&S 26.4.4-26.4.5)."""
    if x <= 0.0:
        return 1.0
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= (x / 2.0) / i
            total += term
        return math.exp(-x / 2.0) * total
    root = math.sqrt(x)
    term, total = root, 0.0
    for i in range(1, (dof - 1) // 2 + 1):
        if i > 1:
            term *= x / (2 * i - 1)
        total += term
    return 2.0 * _STANDARD.cdf(-root) + 2.0 * _STANDARD.pdf(root) * total


@functools.lru_cache(maxsize=64)
def chi2_level(alpha: float, dof: int) -> float:
    """x with P(χ²_dof > x) = alpha (bisection to 1e-10 relative)."""
    lo, hi = 0.0, 1.0
    while chi2_sf(hi, dof) > alpha:
        hi *= 2.0
    while hi - lo > 1e-10 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2_sf(mid, dof) > alpha else (lo, mid)
    return 0.5 * (lo + hi)


def chi_level(alpha: float, dof: int) -> float:
    """sqrt of :func:`chi2_level`: a radius in standard deviations (the start's prior, dof 3)."""
    return math.sqrt(chi2_level(alpha, dof))


def held_level(alpha: float, covariance_inflation: float) -> float:
    """The held pose's bound on Δχ² = δᵀ (H / inflation) δ: χ²₆(1 - alpha) / inflation."""
    return chi2_level(alpha, 6) / covariance_inflation
