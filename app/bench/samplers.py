"""The thesis's static samplers on one frame from one point, side by side with the detector (issue 33, item 4).

Import as ``from app.bench.samplers import compare``. Publication (B) chapters 5-6 compare static
samplers for a pose from one depth image; here on the CT crests, on the same starts as
app/bench/start.py (the frame a point-only trial starts on, its point 2-5 mm off the crest):

- the target π(x) ∝ p(x) p(z | x): the one-point prior (app/filter/smc_init/prior.py, the pointed
  point on the surface up to ``init.point_sigma``, the measured normal's prior) and the likelihood at
  the filter's resolution (the backend the filter and the wide search score with);
- **MH**: ``CHAINS`` random-walk Metropolis-Hastings chains from prior draws, each step a position
  move N(0, POSITION_STEP_M² I) or an orientation move about the pointed point (N(0, ROTATION_STEP_RAD²),
  or with probability P_GLOBAL a uniform twist about the measured normal: the SMC's moves at a fixed
  scale), accepted with min(1, π(x') / π(x));
- **MTM**: multiple-try Metropolis (Liu, Liang and Wong, JASA 2000) with ``TRIES`` tries per step and
  the same symmetric moves: one of the tries chosen in proportion to π, accepted with
  Σ π(tries) / Σ π(references), ``TRIES`` - 1 references drawn from the chosen try plus the
  current state (2 ``TRIES`` - 1 evaluations per step);
- **SMC**: the product's one-point SMC (app/filter/smc_init/) with the same evaluation budget (one run,
  a third of it on prior draws, as the recovery's; its symmetry check is not budgeted, so it spends
  more than the budget); **smc_verified**: the same, its pose then verified by the refinement as a
  wide-search candidate (app/tracking/detector.py's SMCDetector: a pose the refinement does not
  confirm is no detection);
- **detector**: the wide search around the point, verified by the refinement (app/tracking/detector.py).

Each sampler's estimate is its best pose so far by π (MH, MTM: the maximum a posteriori among the
poses it scored) or its weighted mean (SMC); success is the estimate within ``SUCCESS_MM`` (ADD) and
``SUCCESS_DEG`` of the truth; evaluations to success: the likelihood evaluations spent when the
estimate first succeeded (MH, MTM: and stayed so, a best-so-far only improves by π, not by error:
the first evaluation count from which it is within the tolerance to the end), the whole run's for
the SMC and the detector, which give one answer at the end. The detector also spends refinements
(at the sensor's resolution), counted apart.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from app import metrics
from app.filter.smc_init.geometry import measured_normal, rotate_about
from app.filter.smc_init.levels import backend_level
from app.filter.smc_init.prior import SurfacePrior
from app.geometry import quaternion as quat
from app.geometry import se3

SUCCESS_MM, SUCCESS_DEG = 2.0, 2.0
CHAINS = 50
TRIES = 5
POSITION_STEP_M = 0.002
ROTATION_STEP_RAD = 0.05
P_GLOBAL = 0.1
SAMPLERS = ("mh", "mtm", "smc", "smc_verified", "detector")


@dataclass
class SamplerRun:
    """One sampler on one start: success, evaluations to success (None: not reached), evaluations
    spent, refinements (the detector's), the estimate's ADD (mm) and rotation error (deg), CPU s."""

    sampler: str
    success: bool
    evaluations_to_success: int | None
    evaluations: int
    refinements: int
    add_mm: float
    rotation_deg: float
    cpu_s: float
    log_pi_gap: float = float("nan")   # log π(estimate) - log π(truth) (MH, MTM): > 0, the target prefers a wrong pose


class Target:
    """log π(x) = log p(x) + log p(z | x) on one frame (module docstring), counting evaluations."""

    def __init__(self, tracker, depth_small, T_base_camera, point, rng):
        c = tracker.config
        self.prior = SurfacePrior(tracker.mesh_vertices, tracker.mesh_faces, point, c.init_point_sigma, 4000, rng)
        normal = measured_normal(depth_small, tracker.camera, T_base_camera, self.prior.point_base, 0.01)
        self.prior.set_normal(normal, 0.35)
        self.level = backend_level(tracker.backend, tracker.camera, depth_small, se3.inverse(T_base_camera))
        self.evaluations = 0

    def log_pi(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        ll = np.asarray(self.level.score(p, q), float)
        self.evaluations += len(p)
        ll = np.where(np.isfinite(ll), ll, -np.inf)
        return self.prior.log_density(p, q) + ll


class _Best:
    """The best pose so far by π and the evaluation count from which it has been a success."""

    def __init__(self, success):
        self.success, self.log_pi, self.pose, self.since = success, -np.inf, None, None

    def offer(self, p, q, log_pi, evaluations: int) -> None:
        k = int(np.argmax(log_pi))
        if log_pi[k] > self.log_pi:
            self.log_pi, self.pose = float(log_pi[k]), (p[k].copy(), q[k].copy())
            ok = self.success(*self.pose)
            self.since = (self.since if self.since is not None else evaluations) if ok else None


def _move(target: Target, p, q, rng):
    """One symmetric move per pose: half position steps, half orientation steps about the point."""
    n = len(p)
    position = rng.uniform(size=n) < 0.5
    p_new = np.where(position[:, None], p + rng.normal(0.0, POSITION_STEP_M, (n, 3)), p)
    dq = quat.exp_map(rng.normal(0.0, ROTATION_STEP_RAD, (n, 3)))
    jump = rng.uniform(size=n) < P_GLOBAL
    axis = target.prior.normal_base
    if jump.any():
        dq[jump] = quat.exp_map(axis[None] * rng.uniform(-np.pi, np.pi, (int(jump.sum()), 1))) if axis is not None \
            else quat.random_uniform(rng, int(jump.sum()))
    p_rot, q_rot = rotate_about(target.prior.point_base, p, q, dq)
    return np.where(position[:, None], p_new, p_rot), np.where(position[:, None], q, q_rot)


def run_mh(target: Target, budget: int, rng, success) -> _Best:
    best = _Best(success)
    p, q = target.prior.sample(CHAINS, rng)
    lp = target.log_pi(p, q)
    best.offer(p, q, lp, target.evaluations)
    while target.evaluations + CHAINS <= budget:
        p2, q2 = _move(target, p, q, rng)
        lp2 = target.log_pi(p2, q2)
        accept = np.log(rng.uniform(size=CHAINS)) < (lp2 - lp)
        p, q, lp = np.where(accept[:, None], p2, p), np.where(accept[:, None], q2, q), np.where(accept, lp2, lp)
        best.offer(p2, q2, lp2, target.evaluations)
    return best


def run_mtm(target: Target, budget: int, rng, success) -> _Best:
    best = _Best(success)
    p, q = target.prior.sample(CHAINS, rng)
    lp = target.log_pi(p, q)
    best.offer(p, q, lp, target.evaluations)
    k, n = TRIES, CHAINS
    while target.evaluations + (2 * k - 1) * n <= budget:
        pt, qt = _move(target, np.repeat(p, k, axis=0), np.repeat(q, k, axis=0), rng)
        lt = target.log_pi(pt, qt).reshape(n, k)
        best.offer(pt, qt, lt.ravel(), target.evaluations)
        w = np.exp(lt - np.max(lt, axis=1, keepdims=True))
        w = np.where(np.isfinite(w), w, 0.0)
        totals = w.sum(axis=1)
        pick = np.array([rng.choice(k, p=wi / s) if s > 0 else 0 for wi, s in zip(w, totals)])
        rows = np.arange(n) * k + pick
        py, qy, ly = pt[rows], qt[rows], lt[np.arange(n), pick]
        pr, qr = _move(target, np.repeat(py, k - 1, axis=0), np.repeat(qy, k - 1, axis=0), rng)
        lr = np.concatenate([target.log_pi(pr, qr).reshape(n, k - 1), lp[:, None]], axis=1)
        log_num = _logsumexp(lt)
        log_den = _logsumexp(lr)
        accept = np.log(rng.uniform(size=n)) < (log_num - log_den)
        p, q, lp = np.where(accept[:, None], py, p), np.where(accept[:, None], qy, q), np.where(accept, ly, lp)
    return best


def _logsumexp(a: np.ndarray) -> np.ndarray:
    m = np.max(a, axis=1)
    safe = np.where(np.isfinite(m), m, 0.0)
    return safe + np.log(np.sum(np.exp(a - safe[:, None]), axis=1))


def compare(tracker, depth_small, depth_m, T_base_camera, point, T_true, budget: int, seed: int) -> list[SamplerRun]:
    """Every sampler of SAMPLERS on this start (module docstring), each from its own generator."""
    vertices = tracker.mesh_vertices

    def errors(T):
        return 1e3 * metrics.add(T, T_true, vertices), float(np.degrees(metrics.rotation_error(T, T_true)))

    def success(p, q):
        add, rot = errors(se3.from_quat_trans(q, p))
        return add <= SUCCESS_MM and rot <= SUCCESS_DEG

    runs = []
    for name in SAMPLERS:
        rng = np.random.default_rng([seed, SAMPLERS.index(name)])
        cpu0 = time.process_time()
        if name in ("mh", "mtm"):
            target = Target(tracker, depth_small, T_base_camera, point, rng)
            best = (run_mh if name == "mh" else run_mtm)(target, budget, rng, success)
            T = se3.from_quat_trans(best.pose[1], best.pose[0])
            add, rot = errors(T)
            cpu, spent = time.process_time() - cpu0, target.evaluations
            q_true, p_true = se3.to_quat_trans(T_true)
            gap = best.log_pi - float(target.log_pi(np.asarray(p_true, float)[None], np.asarray(q_true, float)[None])[0])
            runs.append(SamplerRun(name, best.since is not None, best.since, spent, 0, add, rot, cpu, gap))
        elif name == "smc":
            runs.append(_smc(tracker, depth_small, T_base_camera, point, budget, rng, errors, cpu0))
        elif name == "smc_verified":
            runs.append(_smc_verified(tracker, depth_small, depth_m, T_base_camera, point, budget, rng, errors, cpu0))
        else:
            runs.append(_detector(tracker, depth_small, depth_m, T_base_camera, point, rng, errors, cpu0))
    return runs


def _smc_config(tracker, budget: int):
    from app.filter.smc_init import smc_config_for

    return smc_config_for(tracker.config, max_evaluations=budget, prior_draws=max(budget // 3, 1), restarts=1,
                          budget_s=3600.0)


def _smc_verified(tracker, depth_small, depth_m, T_base_camera, point, budget, rng, errors, cpu0) -> SamplerRun:
    from app.tracking.detector import SMCDetector

    detector = SMCDetector(tracker.backend, tracker.camera, tracker.mesh_vertices, tracker.mesh_faces,
                           _smc_config(tracker, budget), tracker.wide_search, rng)
    found = detector.detect(depth_small, depth_m, T_base_camera, point)
    evaluations, refinements = detector.last_work
    if found is None:
        return SamplerRun("smc_verified", False, None, evaluations, refinements, np.nan, np.nan,
                          time.process_time() - cpu0)
    add, rot = errors(found.T_base_bone)
    ok = add <= SUCCESS_MM and rot <= SUCCESS_DEG
    return SamplerRun("smc_verified", ok, evaluations if ok else None, evaluations, refinements, add, rot,
                      time.process_time() - cpu0)


def _smc(tracker, depth_small, T_base_camera, point, budget, rng, errors, cpu0) -> SamplerRun:
    from app.filter.smc_init import OnePointInitialiser

    smc = _smc_config(tracker, budget)
    result = OnePointInitialiser(tracker.backend, tracker.camera, tracker.mesh_vertices, tracker.mesh_faces, smc,
                                 rng).run(depth_small, T_base_camera, point)
    add, rot = errors(result.estimate.T_base_bone)
    ok = add <= SUCCESS_MM and rot <= SUCCESS_DEG
    return SamplerRun("smc", ok, int(result.evaluations) if ok else None, int(result.evaluations), 0, add, rot,
                      time.process_time() - cpu0)


def _detector(tracker, depth_small, depth_m, T_base_camera, point, rng, errors, cpu0) -> SamplerRun:
    from app.tracking.detector import SearchDetector

    detector = SearchDetector(tracker.wide_search, rng, tracker.config.detector)
    found = detector.detect(depth_small, depth_m, T_base_camera, point)
    evaluations, refinements = detector.last_work
    if found is None:
        return SamplerRun("detector", False, None, evaluations, refinements, np.nan, np.nan, time.process_time() - cpu0)
    add, rot = errors(found.T_base_bone)
    ok = add <= SUCCESS_MM and rot <= SUCCESS_DEG
    return SamplerRun("detector", ok, evaluations if ok else None, evaluations, refinements, add, rot,
                      time.process_time() - cpu0)


def sampler_table(rows: list[dict]) -> tuple[str, list[dict]]:
    """Per sampler over the starts: successes, evaluations to success (median of the successes),
    evaluations spent, CPU s (median), ADD of the estimate (median), log π gap (median). Markdown."""
    out = []
    for name in SAMPLERS:
        rs = [r for r in rows if r["sampler"] == name]
        if not rs:
            continue
        hits = [r["evaluations_to_success"] for r in rs if r["success"]]
        def med(k):
            values = [r[k] for r in rs if r[k] is not None and np.isfinite(r[k])]
            return float(np.median(values)) if values else None

        out.append({"sampler": name, "starts": len(rs), "successes": len(hits),
                    "evaluations_to_success_median": float(np.median(hits)) if hits else None,
                    "evaluations_median": med("evaluations"), "refinements_median": med("refinements"),
                    "cpu_s_median": med("cpu_s"), "add_mm_median": med("add_mm"),
                    "log_pi_gap_median": med("log_pi_gap") if name in ("mh", "mtm") else None})
    fmt = lambda v, f="{:.0f}": "-" if v is None else f.format(v)  # noqa: E731
    lines = [f"| sampler | success within {SUCCESS_MM:g} mm / {SUCCESS_DEG:g} deg | evaluations to success (median) | "
             "evaluations spent (median) | refinements | CPU s (median) | ADD of the estimate mm (median) | "
             "log π(estimate) - log π(truth) (median) |", "|---|---|---|---|---|---|---|---|"]
    for c in out:
        lines.append(f"| {c['sampler']} | {c['successes']} / {c['starts']} | {fmt(c['evaluations_to_success_median'])} | "
                     f"{fmt(c['evaluations_median'])} | {fmt(c['refinements_median'])} | {c['cpu_s_median']:.2f} | "
                     f"{fmt(c['add_mm_median'], '{:.1f}')} | {fmt(c['log_pi_gap_median'])} |")
    return "\n".join(lines), out
