"""The static samplers of app/bench/samplers.py (issue 33, item 4) on a target whose mode is known:
MH and multiple-try Metropolis climb to it within their evaluation budget, count their evaluations,
and say from which evaluation their best pose has been a success."""
from __future__ import annotations

import numpy as np
import pytest

from app.bench.samplers import CHAINS, TRIES, run_mh, run_mtm
from app.geometry import quaternion as quat


class _Prior:
    """Poses 6 mm / 6 deg around the mode; no measured normal (uniform twists)."""

    normal_base = None

    def __init__(self, p0, q0):
        self.p0, self.q0, self.point_base = p0, q0, p0.copy()

    def sample(self, n, rng):
        q = quat.multiply(quat.exp_map(rng.normal(0.0, 0.1, (n, 3))), np.repeat(self.q0[None], n, axis=0))
        return self.p0 + rng.normal(0.0, 0.006, (n, 3)), quat.normalize(q)


class _Target:
    """log π: a Gaussian of 1 mm and 2 deg about (p0, q0); counts evaluations."""

    def __init__(self):
        self.p0, self.q0 = np.array([0.1, 0.2, 0.3]), quat.normalize(np.array([1.0, 0.2, 0.0, 0.1]))
        self.prior = _Prior(self.p0, self.q0)
        self.evaluations = 0

    def log_pi(self, p, q):
        self.evaluations += len(p)
        angle = quat.angle_between(q, np.broadcast_to(self.q0, q.shape))
        return -0.5 * np.sum((p - self.p0) ** 2, axis=1) / 0.001 ** 2 - 0.5 * (angle / np.radians(2.0)) ** 2

    def success(self, p, q):
        return np.linalg.norm(p - self.p0) < 0.002 and float(quat.angle_between(q, self.q0)) < np.radians(3.0)


@pytest.mark.parametrize("run", [run_mh, run_mtm])
def test_a_sampler_reaches_a_known_mode_within_its_budget_and_counts_its_work(run):
    target = _Target()
    budget = 20_000
    best = run(target, budget, np.random.default_rng(0), target.success)
    assert target.evaluations <= budget
    assert best.since is not None and CHAINS <= best.since <= target.evaluations
    assert target.success(*best.pose)


def test_multiple_try_metropolis_spends_2k_minus_1_evaluations_per_chain_and_step():
    target = _Target()
    run_mtm(target, CHAINS + 3 * (2 * TRIES - 1) * CHAINS, np.random.default_rng(1), target.success)
    assert target.evaluations == CHAINS + 3 * (2 * TRIES - 1) * CHAINS
