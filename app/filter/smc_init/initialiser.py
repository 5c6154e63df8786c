"""The one-point initialiser: restarts of the static SMC sampler, the symmetry check and the final
move to the filter's resolution (steps 1-4 of :mod:`app.filter.smc_init`)."""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from app.filter import resampling as rs
from app.filter import weights as lw_ops
from app.filter.estimate import PoseEstimate, estimate
from app.filter.motion import ParticleState
from app.filter.smc_init.geometry import measured_normal, mesh_symmetries
from app.filter.smc_init.levels import Budget, Level, make_levels, tempered
from app.filter.smc_init.prior import SurfacePrior
from app.filter.smc_init.tempering import Cloud, Tempered, Tempering, next_phi
from app.geometry import quaternion as quat
from app.geometry import se3

log = logging.getLogger(__name__)

# share of max_evaluations kept for the end at the filter's level when there are coarse levels: the
# runs share the rest, and the end gets this many from when it starts (the default run's end scores
# ~5,000 poses; a small budget, e.g. the recovery's 30,000 with one restart, would otherwise reach the
# end spent by the runs' last steps and the unbudgeted symmetry check, and jump to φ = 1 there)
FINISH_SHARE = 0.1


@dataclass
class SMCInitConfig:
    """Settings of the one-point initialiser.

    particles : N of the sampler ((B): ~100); sigma_t : m, how far the pointed point may lie off the
    surface (pointing error); sigma_r : rad, local orientation move; p_global : share of uniform
    orientation moves; mh_moves : MH sweeps per tempering step; target_ess : ESS / N kept by each
    tempering step; max_steps : tempering steps before φ jumps to 1; max_evaluations : poses scored
    (at any resolution) shared by the restarts (each run gets an equal share of what is left; past
    it φ jumps to 1): the budget, counted in work, so a run does the same on a loaded machine and a
    free one; budget_s : s, only a safety net against a stuck backend (a run past it jumps to φ = 1
    and says so in the log); surface_samples : points on the mesh for the prior's distance;
    prior_draws : poses drawn from the prior and scored before the first tempering step, of which
    ``particles`` go on (a wider first look at SO(3)); sigma_n : rad, the normal prior (0 = off,
    orientation uniform as in (B)); normal_radius : m, the measured points around the pointed point
    that give its normal; restarts : independent runs, the most likely one kept; symmetry_check :
    then search the mesh's half-turn symmetries of the result from a cloud of symmetry_sigma_p (m) /
    symmetry_sigma_r (rad) around each; coarse_levels : (divisor of the filter's resolution,
    triangle budget) of the cheaper likelihood levels (:func:`app.filter.smc_init.levels.make_levels`):
    the first draws at the coarsest, the tempering and the symmetry check at the next, the end at
    the filter's; () = everything at the filter's resolution and mesh.
    """

    particles: int = 200
    sigma_t: float = 0.005
    sigma_r: float = 0.15
    p_global: float = 0.2
    mh_moves: int = 4
    target_ess: float = 0.5
    max_steps: int = 40
    max_evaluations: int = 150_000
    budget_s: float = 600.0
    surface_samples: int = 4000
    prior_draws: int = 10000
    sigma_n: float = 0.35
    normal_radius: float = 0.01
    restarts: int = 3
    symmetry_check: bool = True
    symmetry_sigma_p: float = 0.005
    symmetry_sigma_r: float = 0.07
    coarse_levels: tuple[tuple[int, int], ...] = ((4, 250), (2, 500))


def smc_config_for(tracker_config, **overrides) -> SMCInitConfig:
    """The initialiser's settings from a TrackerConfig's ``init.*`` keys (point_sigma, restarts,
    budget_s), its particles capped at the filter's (the backend's capacity)."""
    values = dict(particles=min(SMCInitConfig.particles, tracker_config.particles),
                  sigma_t=tracker_config.init_point_sigma, restarts=tracker_config.init_restarts,
                  budget_s=tracker_config.init_budget_s)
    values.update({k: v for k, v in overrides.items() if v is not None})
    return SMCInitConfig(**values)


@dataclass
class SMCResult:
    """The sampler's outcome.

    p, q : (N, 3), (N, 4) the final cloud (equally weighted); log_likelihood : (N,) its p(z | x) at
    the filter's resolution; estimate : weighted-mean pose and spread; phis : the tempering schedule
    reached (every level's, one after the other); acceptance : mean MH acceptance per step;
    seconds : wall time; reached_target : φ got to 1 within the step and evaluation budgets by
    tempering (not by the final jump); symmetry_turned : the symmetry check replaced the sampler's
    cloud; evaluations : poses scored by the whole initialisation (every level); nonfinite : NaN or
    +inf log-likelihoods met (scored as -inf); levels : the likelihood levels used, coarse to fine.
    """

    p: np.ndarray
    q: np.ndarray
    log_likelihood: np.ndarray
    estimate: PoseEstimate
    phis: list[float] = field(default_factory=list)
    acceptance: list[float] = field(default_factory=list)
    seconds: float = 0.0
    reached_target: bool = True
    symmetry_turned: bool = False
    evaluations: int = 0
    nonfinite: int = 0
    levels: list[str] = field(default_factory=list)


def _result(t: Tempered, phis=None, acceptance=None, reached=True, symmetry_turned=False) -> SMCResult:
    """The SMCResult of a tempered cloud (equal weights), its schedule after ``phis`` (earlier levels')."""
    c = t.cloud
    return SMCResult(c.p, c.q, c.ll, estimate(c.p, c.q, lw_ops.uniform_log_weights(len(c.p))),
                     (phis or []) + t.phis, (acceptance or []) + t.acceptance, reached_target=reached and t.reached,
                     symmetry_turned=symmetry_turned)


class OnePointInitialiser:
    """The sampler of :mod:`app.filter.smc_init` over a likelihood backend (``log_likelihood(T_camera_bone, depth)``).

    Parameters
    ----------
    backend : the particle filter's LikelihoodBackend (its capacity must be >= config.particles);
        with ``backend.resized(camera)`` (the CPU backend) the coarse levels run on copies of it
    camera : the PinholeCamera of the backend's images (the filter's resolution)
    vertices, faces : the tracking mesh (bone frame, m, outward normals)
    config : SMCInitConfig
    rng : np.random.Generator
    """

    def __init__(self, backend, camera, vertices: np.ndarray, faces: np.ndarray, config: SMCInitConfig,
                 rng: np.random.Generator):
        self.backend, self.camera, self.vertices, self.faces = backend, camera, vertices, faces
        self.config, self.rng = config, rng

    def run(self, depth: np.ndarray, T_base_camera: np.ndarray, point_base: np.ndarray,
            sigma_t: float | None = None) -> SMCResult:
        """Sample π from the depth image (filter resolution), the camera pose and the pointed point.

        ``restarts`` independent runs on the coarse levels; the one whose cloud has the highest mean
        log-likelihood wins (a run in a wrong basin, e.g. the crest turned end for end, scores
        hundreds of nats lower); the symmetry check; then the move to the filter's level.
        ``max_evaluations`` is shared by the runs, :data:`FINISH_SHARE` of it kept for the end (the
        symmetry check is not budgeted; each budgeted stage overshoots by at most a step and its
        final sweeps; ``budget_s``: the wall-time safety net).
        """
        c, t_start = self.config, time.perf_counter()
        budget = Budget(deadline=t_start + c.budget_s)
        tempering = Tempering(self._prior(depth, T_base_camera, point_base, sigma_t), c, budget, self.rng)
        levels = make_levels(self.backend, self.camera, depth, T_base_camera, c.coarse_levels)
        coarse = levels[:-1] or levels
        finish_reserve = int(FINISH_SHARE * c.max_evaluations) if len(levels) > 1 else 0
        runs_budget = c.max_evaluations - finish_reserve
        best: SMCResult | None = None
        restarts = max(1, c.restarts)
        for k in range(restarts):
            left = runs_budget - budget.evaluations
            if best is not None and (left <= 0 or budget.late()):
                break
            budget.limit = budget.evaluations + left // (restarts - k)
            result = self._run_once(tempering, coarse)
            if best is None or np.mean(result.log_likelihood) > np.mean(best.log_likelihood):
                best = result
        if c.symmetry_check:
            best = self._symmetry_check(best, tempering, coarse[-1])
        if len(levels) > 1:   # the end's own share, whatever the runs' last steps and the symmetry check spent
            budget.limit = budget.evaluations + finish_reserve
            best = self._finish(best, tempering, coarse[-1], levels[-1])
        best.seconds = time.perf_counter() - t_start
        best.evaluations, best.nonfinite, best.levels = budget.evaluations, budget.nonfinite, [v.name for v in levels]
        return best

    def _prior(self, depth, T_base_camera, point_base, sigma_t) -> SurfacePrior:
        """The prior of the pointed point, with the measured normal when the image gives one."""
        c = self.config
        prior = SurfacePrior(self.vertices, self.faces, point_base, c.sigma_t if sigma_t is None else sigma_t,
                             c.surface_samples, self.rng)
        normal = measured_normal(depth, self.camera, T_base_camera, prior.point_base, c.normal_radius) \
            if c.sigma_n > 0 else None
        if c.sigma_n > 0 and normal is None:
            log.warning("one-point initialisation: too few measured points at the pointed point for its normal: "
                        "orientation prior uniform")
        prior.set_normal(normal, c.sigma_n)
        return prior

    def _run_once(self, tempering: Tempering, levels: list[Level]) -> SMCResult:
        """One run (steps 1-3): ``prior_draws`` poses scored at ``levels[0]``, ``particles`` of them
        kept at the first φ, moved up the levels, tempered to φ = 1 at ``levels[-1]``."""
        c, rng, t_start = self.config, self.rng, time.perf_counter()
        p, q = tempering.prior.sample(max(c.prior_draws, c.particles), rng)
        cloud = tempering.score(levels[0], p, q)
        phi = next_phi(0.0, cloud.ll, c.target_ess * c.particles / len(p))
        cloud = cloud.take(rs.systematic(tempered(phi, cloud.ll), rng.random(), c.particles))
        for level_from, level_to in zip(levels[:-1], levels[1:]):
            cloud, phi = tempering.switch(cloud, phi, level_from, level_to)
        result = _result(tempering.temper(cloud, phi, levels[-1]))
        pose = result.estimate
        log.info("one-point initialisation: %d tempering steps at %s, %.2f s, spread %.1f mm / %.1f deg%s",
                 len(result.phis) - 1, levels[-1].name, time.perf_counter() - t_start, 1e3 * pose.position_spread,
                 np.degrees(pose.rotation_spread), "" if result.reached_target else " (budget reached: φ jumped to 1)")
        return result

    def _finish(self, result: SMCResult, tempering: Tempering, level_from: Level, level_to: Level) -> SMCResult:
        """The cloud at φ = 1 of the coarse level moved to the filter's level and tempered to its φ = 1."""
        cloud = Cloud(result.p, result.q, result.log_likelihood, tempering.prior.log_density(result.p, result.q))
        cloud, phi = tempering.switch(cloud, 1.0, level_from, level_to)
        t = tempering.temper(cloud, phi, level_to)
        t.phis = t.phis[1:]                     # the schedule goes on from the coarse level's (no second 0)
        return _result(t, result.phis, result.acceptance,
                       result.reached_target, result.symmetry_turned)

    def _symmetry_check(self, result: SMCResult, tempering: Tempering, level: Level) -> SMCResult:
        """Look for the bone turned by one of the mesh's half-turn symmetries, and keep it if likelier.

        A ridge turned end for end covers much of its own visible surface, and the sampler's
        restarts can all settle there (hundreds of nats below the true pose, which the status rules
        then fail to tell apart). For each symmetry S of :func:`mesh_symmetries` (and S⁻¹), a cloud
        of N poses around x S (x: the result's mean pose; spread ``symmetry_sigma_p`` /
        ``symmetry_sigma_r``, because the visible part's symmetry differs from the whole mesh's by
        millimetres and degrees) is tempered at ``level`` from φ = 0 with local moves only. The
        candidate cloud replaces the result when its mean log-likelihood is higher.
        """
        c, rng = self.config, self.rng
        x, n = result.estimate.T_base_bone, len(result.p)
        best = result
        for S in mesh_symmetries(self.vertices, self.faces):
            for S_k in (S, se3.inverse(S)):
                q0, t0 = se3.to_quat_trans(x @ S_k)
                p = t0 + rng.normal(0.0, c.symmetry_sigma_p, (n, 3))
                q = quat.normalize(quat.multiply(quat.exp_map(rng.normal(0.0, c.symmetry_sigma_r, (n, 3))),
                                                 np.repeat(q0[None], n, axis=0)))
                cloud = tempering.score(level, p, q)
                phi = next_phi(0.0, cloud.ll, c.target_ess)
                cloud = cloud.take(rs.systematic(tempered(phi, cloud.ll), rng.random()))
                t = tempering.temper(cloud, phi, level, local=True, budgeted=False)
                mean_ll = np.mean(t.cloud.ll)
                log.debug("symmetry check: candidate %.0f vs result %.0f (mean log-likelihood)", mean_ll,
                          np.mean(best.log_likelihood))
                if t.reached and mean_ll > np.mean(best.log_likelihood):
                    log.info("one-point initialisation: the bone turned by a symmetry of its mesh explains the "
                             "image better (mean log-likelihood %.0f vs %.0f): taken", mean_ll,
                             np.mean(best.log_likelihood))
                    best = _result(Tempered(t.cloud), result.phis, result.acceptance, result.reached_target,
                                   symmetry_turned=True)
        return best


def seed_state(result: SMCResult, n: int, rng: np.random.Generator) -> ParticleState:
    """The filter's N particles drawn from the sampler's cloud (systematic), at rest, equally weighted."""
    idx = rs.systematic(lw_ops.uniform_log_weights(len(result.p)), rng.random(), n)
    return ParticleState(result.p[idx].copy(), np.zeros((n, 3)), result.q[idx].copy(), np.zeros((n, 3)),
                         lw_ops.uniform_log_weights(n))
