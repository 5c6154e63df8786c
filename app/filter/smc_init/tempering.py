"""Adaptive tempering and the Metropolis-Hastings moves of the one-point initialiser (steps 2 and
the level switch of :mod:`app.filter.smc_init`).

The targets are π_φ ∝ p(x) p_ℓ(z | x)^φ for the likelihood level ℓ in use (:mod:`.levels`). Each
step picks the next φ by the ESS rule (Jasra et al. 2011), resamples (systematic) and runs
``mh_moves`` MH sweeps, alternating an adaptive random-walk position move and an orientation move
about the pointed point; both are symmetric, so the acceptance is min(1, π_φ(x') / π_φ(x)).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from app.filter import resampling as rs
from app.filter import weights as lw_ops
from app.filter.smc_init.geometry import rotate_about
from app.filter.smc_init.levels import Budget, Level, evaluate, tempered
from app.filter.smc_init.prior import SurfacePrior
from app.geometry import quaternion as quat

log = logging.getLogger(__name__)


@dataclass
class Cloud:
    """N equally weighted poses (p (N, 3), q (N, 4)) with their log-likelihood ``ll`` at the current
    level and log-prior ``lp``."""

    p: np.ndarray
    q: np.ndarray
    ll: np.ndarray
    lp: np.ndarray

    def take(self, idx: np.ndarray) -> "Cloud":
        return Cloud(self.p[idx], self.q[idx], self.ll[idx], self.lp[idx])

    def where(self, accept: np.ndarray, other: "Cloud") -> "Cloud":
        """``other``'s poses where ``accept``, this cloud's elsewhere."""
        return Cloud(np.where(accept[:, None], other.p, self.p), np.where(accept[:, None], other.q, self.q),
                     np.where(accept, other.ll, self.ll), np.where(accept, other.lp, self.lp))


@dataclass
class StepScales:
    """MH step scales, each tuned towards ~30 % acceptance: ``position`` multiplies the cloud's
    position covariance step (2.38 / √3 rule), ``rotation`` multiplies σ_r (kept in [0.01, 1])."""

    position: float = 1.0
    rotation: float = 1.0


@dataclass
class Tempered:
    """A tempering's outcome: the cloud at φ = 1, the φ schedule from 0, the mean acceptance per step,
    and whether φ = 1 was reached by tempering (not by a budget's jump)."""

    cloud: Cloud
    phis: list[float] = field(default_factory=list)
    acceptance: list[float] = field(default_factory=list)
    reached: bool = True


def ess_fraction(log_w: np.ndarray) -> float:
    """ESS / N = (Σ w)² / (N Σ w²) of log-weights (w = exp(log_w - max), as :func:`app.filter.weights.ess`
    in fewer array passes: the ESS rule's bisection calls it ~40 times a step); 0 when every weight is zero."""
    m = np.max(log_w)
    if not np.isfinite(m):
        return 0.0
    w = np.exp(log_w - m)
    return float(np.sum(w) ** 2 / (len(w) * np.dot(w, w)))


def next_phi(phi: float, log_lik: np.ndarray, target_ess: float) -> float:
    """The largest φ' in (φ, 1] whose incremental weights (φ' - φ) log p(z | x) keep ESS >= target · N."""
    if ess_fraction(tempered(1.0 - phi, log_lik)) >= target_ess:
        return 1.0
    lo, hi = 0.0, 1.0 - phi
    for _ in range(40):                       # to 1e-12 of the step: far below what moves a weight
        mid = 0.5 * (lo + hi)
        if ess_fraction(tempered(mid, log_lik)) >= target_ess:
            lo = mid
        else:
            hi = mid
    return phi + max(lo, 1e-9)


class Tempering:
    """The moves and the tempering loop over a prior, with ``config`` an SMCInitConfig (mh_moves,
    target_ess, max_steps, sigma_r, p_global) and the shared evaluation ``budget``."""

    def __init__(self, prior: SurfacePrior, config, budget: Budget, rng: np.random.Generator):
        self.prior, self.config, self.budget, self.rng = prior, config, budget, rng

    def score(self, level: Level, p: np.ndarray, q: np.ndarray) -> Cloud:
        return Cloud(p, q, evaluate(level, p, q, self.budget), self.prior.log_density(p, q))

    def temper(self, cloud: Cloud, phi: float, level: Level, local: bool = False, budgeted: bool = True) -> Tempered:
        """MH sweeps at φ, then the next φ, resampling, sweeps, until φ = 1; past ``max_steps``, the
        budget's evaluation limit (when ``budgeted``) or its deadline (the safety net), φ jumps to 1.
        ``local``: no global orientation jumps."""
        c, scales = self.config, StepScales()
        out = Tempered(cloud, [0.0, phi] if phi > 0 else [0.0])
        while True:
            out.cloud, accepted = self.sweeps(out.cloud, phi, level, scales, local)
            out.acceptance.append(accepted)
            if phi >= 1.0:
                return out
            if self.budget.late():
                log.warning("one-point initialisation: the %.0f s safety net was reached (init.budget_s): "
                            "stopping", c.budget_s)
            jump = len(out.phis) > c.max_steps or self.budget.late() or (budgeted and self.budget.spent())
            new_phi = 1.0 if jump else next_phi(phi, out.cloud.ll, c.target_ess)
            out.reached &= not jump
            out.cloud = self._resample(out.cloud, tempered(new_phi - phi, out.cloud.ll))
            phi = new_phi
            out.phis.append(phi)

    def switch(self, cloud: Cloud, phi: float, level_from: Level, level_to: Level) -> tuple[Cloud, float]:
        """Move the cloud from π ∝ p p_from^φ to π' ∝ p p_to^φ' with φ' = min(1, φ s_from / s_to) (the
        levels' scales): rescore it at ``level_to``, weight by π'/π, resample. Returns (cloud, φ')."""
        phi_to = min(1.0, phi * level_from.scale / level_to.scale)
        moved = self.score(level_to, cloud.p, cloud.q)
        log_w = tempered(phi_to, moved.ll) - tempered(phi, cloud.ll)
        log.debug("level %s -> %s at φ %.3g -> %.3g: ESS %.0f %%", level_from.name, level_to.name, phi, phi_to,
                  100 * ess_fraction(log_w))
        return self._resample(moved, log_w), phi_to

    def _resample(self, cloud: Cloud, log_w: np.ndarray) -> Cloud:
        """Systematic resampling by log-weights; uniform when every weight is zero."""
        if not np.any(np.isfinite(log_w)):
            return cloud
        return cloud.take(rs.resample("systematic", lw_ops.normalise_log_weights(log_w), self.rng))

    def sweeps(self, cloud: Cloud, phi: float, level: Level, scales: StepScales, local: bool) -> tuple[Cloud, float]:
        """``mh_moves`` MH sweeps at φ, alternating position and orientation moves; tunes ``scales``
        in place. Returns the cloud and the mean acceptance."""
        n_sweeps, rng, accepted = self.config.mh_moves, self.rng, 0.0
        for sweep in range(n_sweeps):
            if sweep % 2 == 0:
                p_new, q_new = self._position_move(cloud.p, cloud.q, scales.position)
            else:
                p_new, q_new = self._orientation_move(cloud.p, cloud.q, scales.rotation,
                                                      0.0 if local else self.config.p_global)
            proposal = self.score(level, p_new, q_new)
            log_ratio = (proposal.lp + tempered(phi, proposal.ll)) - (cloud.lp + tempered(phi, cloud.ll))
            accept = np.log(rng.uniform(size=len(cloud.p))) < np.nan_to_num(log_ratio, nan=-np.inf)
            cloud = cloud.where(accept, proposal)
            rate = float(accept.mean())
            accepted += rate / n_sweeps
            if sweep % 2 == 0:
                scales.position *= np.exp(rate - 0.3)
            else:
                scales.rotation = float(np.clip(scales.rotation * np.exp(rate - 0.3), 0.01, 1.0))
        return cloud, accepted

    def _position_move(self, p: np.ndarray, q: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        cov = np.cov(p.T) + np.eye(3) * 1e-8
        step = self.rng.multivariate_normal(np.zeros(3), (scale * 2.38 / np.sqrt(3)) ** 2 * cov, size=len(p))
        return p + step, q

    def _orientation_move(self, p: np.ndarray, q: np.ndarray, scale_r: float,
                          p_global: float) -> tuple[np.ndarray, np.ndarray]:
        """A rotation δ about the pointed point: local N(0, (scale_r σ_r)²); with probability
        ``p_global`` a uniform one (with the normal prior: a uniform twist about the measured normal,
        which keeps the prior's normal term). Both are symmetric (δ and δ⁻¹ equally likely)."""
        n, c, rng, prior = len(p), self.config, self.rng, self.prior
        dq = quat.exp_map(rng.normal(0.0, scale_r * c.sigma_r, (n, 3)))
        jump = rng.uniform(size=n) < p_global
        if prior.normal_base is None:
            dq[jump] = quat.random_uniform(rng, int(jump.sum()))
        else:
            dq[jump] = quat.exp_map(prior.normal_base[None] * rng.uniform(-np.pi, np.pi, (int(jump.sum()), 1)))
        return rotate_about(prior.point_base, p, q, dq)
