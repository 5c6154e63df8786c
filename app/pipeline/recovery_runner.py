"""The recovery wired into the depth tracker: whether a due re-initialisation runs on this frame, and running it.

Import as ``from app.pipeline.recovery_runner import make_recovery``. The policy
(when a re-initialisation is due, which kind, the honesty rules) is app/filter/recovery.py's
:class:`~app.filter.recovery.RecoveryPolicy`; the wide search is app/filter/wide_search.py's. This
module does the policy's attempts on the tracker's parts (app/pipeline/tracker.py):

- **may it run** (:meth:`RecoveryRunner.may_run`): an attempt is due, the frame has a camera pose
  and valid depth, and the bone's expected silhouette at the last confident pose is not mostly
  hidden (:func:`app.filter.visibility.visible_share`, the policy's ``may_run``);
- **the attempt** (:meth:`RecoveryRunner.run`): the wide search (a found pose seeds the particles,
  FOUND_SIGMA_M / FOUND_SIGMA_RAD about it, and the refinement's track; nothing found changes
  nothing; the current estimate kept as the best explanation is moved onto its refined pose when
  its own fit is below the search's bar and that pose moves the template by more than
  status.max_template_std, and is otherwise left alone), a re-spread around the last confident pose, or the one-point SMC initialiser at the
  policy's point (a re-spread instead while that point is behind a hand,
  :func:`app.filter.visibility.point_visible`);
- **the work** the searches cost (searches, found, kept, likelihood evaluations, refinements, CPU and
  wall seconds) for the summaries (:meth:`RecoveryRunner.report`).
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np

from app.filter.recovery import FOUND_SIGMA_M, FOUND_SIGMA_RAD, RESPREAD, SEARCH, SMC, RecoveryPolicy
from app.filter.refine_track import RefinedTrack
from app.filter.visibility import point_visible, visible_share
from app.geometry.camera import PinholeCamera
from app.tracking import levels
from app.tracking.search_worker import SearchJob

log = logging.getLogger(__name__)


class RecoveryRunner:
    """The recovery's attempts on the tracker's filter, refinement and wide search (module docstring).

    Parameters
    ----------
    config : TrackerConfig
    policy : RecoveryPolicy
    wide_search : app.filter.wide_search.WideSearch, or None (``recovery.search`` off, no refinement)
    particle_filter : the tracker's ParticleFilter (its state is replaced, its generator drawn from)
    refined_track : the tracker's RefinedTrack, or None (refinement off)
    run_smc : ``(point_base, depth_small, T_base_camera, smc_config) -> result``: the tracker's
        one-point initialiser, which seeds the particles
    """

    def __init__(self, config, policy: RecoveryPolicy, wide_search, particle_filter,
                 refined_track: RefinedTrack | None, run_smc: Callable):
        self.config = config
        self.policy = policy
        self.wide_search = wide_search
        self.filter = particle_filter
        self.refined_track = refined_track
        self.run_smc = run_smc
        self.worker = None        # app/tracking/search_worker.py's SearchWorker: searches off the frame loop
        self.work = {"searches": 0, "found": 0, "kept": 0, "evaluations": 0, "refinements": 0, "cpu_s": 0.0, "wall_s": 0.0}

    def may_run(self, depth_small: np.ndarray, depth_m: np.ndarray, T_base_camera: np.ndarray | None) -> bool:
        """Whether the due attempt runs on this frame (module docstring)."""
        if self.policy.pending is None or self.searching or not usable_frame(depth_small, T_base_camera):
            return False
        if self.refined_track is None or self.policy.T_base_bone_confident is None:
            return True
        T_camera_bone = np.linalg.inv(T_base_camera) @ self.policy.T_base_bone_confident
        return self.policy.may_run(visible_share(self.refined_track.refiner, depth_m, T_camera_bone))

    def run(self, depth_small: np.ndarray, depth_m: np.ndarray, T_base_camera: np.ndarray, stamp: float,
            T_base_bone_now: np.ndarray | None) -> tuple[float, bool]:
        """The due attempt on this frame; returns (the seconds a wide search took, 0 otherwise; whether
        the track was re-initialised: not by a search that found nothing or kept the track).
        ``T_base_bone_now``: the last frame's estimate (the confident pose when there was none yet)."""
        policy = self.policy
        if policy.T_base_bone_confident is None:
            policy.set_start(T_base_bone_now)
        kind = policy.next_kind()
        if kind == SEARCH and self.wide_search is None:
            kind = SMC
        if kind == SEARCH:
            return self._search(depth_small, depth_m, T_base_camera, stamp, T_base_bone_now)
        if kind != RESPREAD and not self._smc_point_visible(depth_m, T_base_camera):
            kind = RESPREAD
        if kind == RESPREAD:
            self.filter.set_state(policy.respread_state(self.config.particles, self.filter.rng))
            if self.refined_track is not None:
                self.refined_track.seed(policy.T_base_bone_confident)
        else:
            self._smc_from(policy.smc_point(), depth_small, T_base_camera)
            if self.refined_track is not None:
                self.refined_track.reset()
        log.info("recovery at %.3f s: %s (%s)", stamp, kind, policy.pending)
        policy.done(stamp, kind)
        return 0.0, True

    def _search(self, depth_small: np.ndarray, depth_m: np.ndarray, T_base_camera: np.ndarray, stamp: float,
                T_base_bone_now: np.ndarray | None) -> tuple[float, bool]:
        """The wide search for a moved bone (app/filter/wide_search.py): inline, its outcome applied at
        once (:meth:`_searched`); or handed to the worker (app/tracking/search_worker.py), its outcome
        applied on a later frame (:meth:`take_search`), the track going on meanwhile (0 s, False)."""
        policy = self.policy
        if self.worker is not None and self.worker.safe():
            self.worker.submit(SearchJob(depth_small.copy(), depth_m.copy(), np.array(T_base_camera, float),
                                         np.array(policy.T_base_bone_confident, float), policy.track_poses(),
                                         None if T_base_bone_now is None else np.array(T_base_bone_now, float),
                                         float(stamp)))
            return 0.0, False
        wall0, cpu0 = time.perf_counter(), time.process_time()
        result = self.wide_search.run(depth_small, depth_m, T_base_camera, policy.T_base_bone_confident,
                                      policy.track_poses(), self.filter.rng, incumbent=T_base_bone_now)
        seconds = time.perf_counter() - wall0
        return self._searched(result, stamp, T_base_bone_now, seconds, time.process_time() - cpu0)

    @property
    def searching(self) -> bool:
        """A search handed to the worker has not been taken yet (the track goes on meanwhile)."""
        return self.worker is not None and self.worker.in_flight

    def take_search(self, stamp: float) -> tuple[float, bool] | None:
        """The worker's finished search applied on this frame (:meth:`_searched`), or None while it runs.
        A search that failed counts as one that found nothing."""
        if not self.searching or not self.worker.ready():
            return None
        job, outcome = self.worker.take()
        if outcome is None:
            self.work["searches"] += 1
            self.policy.declined()
            return 0.0, False
        seconds, reinitialised = self._searched(outcome.result, stamp, job.incumbent, outcome.wall_s, outcome.cpu_s)
        log.info("recovery at %.3f s: the search asked at %.3f s was taken (%.2f s on the worker)", stamp,
                 job.stamp, outcome.wall_s)
        return 0.0, reinitialised            # the frame loop did not wait: its seconds are the worker's

    def _searched(self, result, stamp: float, T_base_bone_now: np.ndarray | None, seconds: float,
                  cpu_s: float) -> tuple[float, bool]:
        """Apply a wide search's result: a found pose seeds the cloud (FOUND_SIGMA_M / _RAD about it) and
        the refinement's track (which resets the static prior: the old base-frame pose must not drag it
        back); nothing found changes nothing; a search that kept the current estimate (the incumbent
        explained the image best) moves the track onto the incumbent's refined pose when that lies away
        from it (:meth:`_refined_in_place`)."""
        policy = self.policy
        work = self.work
        work["searches"] += 1
        work["evaluations"] += result.evaluations
        work["refinements"] += result.refinements
        work["cpu_s"] += cpu_s
        work["wall_s"] += seconds
        if result.kept:
            work["kept"] += 1
            log.info("recovery at %.3f s: wide search kept the track (fit %.2f, sharp %.2f; best candidate %.2f)",
                     stamp, result.fitness, result.sharp, max((c[1] for c in result.candidates), default=float("nan")))
            self._refined_in_place(result.T_base_bone_kept, T_base_bone_now)
            policy.kept()
            return seconds, False
        if result.T_base_bone is None:
            log.info("recovery at %.3f s: wide search found nothing confirmed (best fit %.2f)", stamp, result.fitness)
            policy.declined()
            return seconds, False
        work["found"] += 1
        self.filter.set_state(policy.state_around(result.T_base_bone, self.config.particles, self.filter.rng,
                                                  FOUND_SIGMA_M, FOUND_SIGMA_RAD))
        self.refined_track.seed(result.T_base_bone, verified=True)
        log.info("recovery at %.3f s: wide search found a pose (fit %.2f, sharp %.2f, from the %s) (%s)", stamp,
                 result.fitness, result.sharp, result.source, policy.pending)
        policy.done(stamp, SEARCH)
        return seconds, True

    def _refined_in_place(self, T_base_bone_kept: np.ndarray | None, T_base_bone_now: np.ndarray | None) -> None:
        """A kept track whose own last fit is below the search's bar (:meth:`RecoveryPolicy.fit_below_bar`) moved onto its refined pose when that lies more than
        ``status.max_template_std`` (1 mm, the largest displacement of the template's points: a different answer;
        recovery.kept_move_m / kept_move_angle, 1 mm / 1 deg, before issue 32) from the current estimate: the cloud
        shifted onto it, the refined track seeded
        there (which resets its static prior, as a found pose does). The search verified the incumbent
        with a wider chain than the track's own refinement (width 0 from its last pose), and that
        chain can leave a local minimum: or_fast_reposition crest_left_05 seed 1 at the filter's
        seed 3 kept a track 3.3 mm / 4-6 deg off at a consistent sharp share of 0.26-0.30 through
        three searches whose chain refined it to 0.1 mm (0.91); 2.54 s, 0.36 s with the move
        (BENCHMARKS.md §6n). Without the bar test the wider chain also moved right tracks onto fits
        scoring a little higher: at that seed six runs were found later (refound mean 0.22 -> 0.35 s)."""
        if T_base_bone_kept is None or T_base_bone_now is None or self.refined_track is None:
            return
        if not self.policy.fit_below_bar():                          # the track's own fit passes the bar: left alone
            return
        if self.refined_track.template_gap(T_base_bone_now, T_base_bone_kept) <= self.config.status.max_template_std:
            return
        self.filter.shift_to(T_base_bone_kept, T_base_bone_now)
        self.refined_track.seed(T_base_bone_kept, verified=True)

    def _smc_from(self, point_base: np.ndarray, depth_small: np.ndarray, T_base_camera: np.ndarray) -> None:
        """The one-point initialiser with the recovery's budget (likelihood evaluations), one run."""
        from app.filter.smc_init import smc_config_for

        budget = self.config.recovery.smc_evaluations
        smc = smc_config_for(self.config, max_evaluations=budget, prior_draws=max(budget // 3, 1), restarts=1)
        self.run_smc(point_base, depth_small, T_base_camera, smc)

    def _smc_point_visible(self, depth_m: np.ndarray, T_base_camera: np.ndarray) -> bool:
        """Whether the SMC's pointed point is seen (not behind a hand): else a re-spread instead."""
        point_camera = (np.linalg.inv(T_base_camera) @ np.append(self.policy.smc_point(), 1.0))[:3]
        camera = self.refined_track.refiner.camera if self.refined_track is not None else None
        if camera is None or camera.width != depth_m.shape[1]:
            return True
        return point_visible(camera, depth_m, point_camera, self.config.likelihood.occluder_margin)

    def report(self) -> dict:
        """The policy's re-initialisations with the searches' work."""
        return {**self.policy.report(), "search": dict(self.work)}


def make_recovery(config, backend, camera: PinholeCamera, particle_filter, refined_track: RefinedTrack | None,
                  vertices: np.ndarray, run_smc: Callable) -> RecoveryRunner | None:
    """The runner with the policy (the mesh's centroid and the surface point nearest it) and the wide
    search (on the filter's backend at ``camera``, the filter's resolution, and the refinement's
    refiner), or None when ``recovery.enabled`` is false."""
    if not config.recovery.enabled:
        return None
    search = _wide_search(config, backend, camera, refined_track, vertices)
    search_bar = math.nan if search is None else search.config.min_sharp     # no search: the sixth trigger off
    return RecoveryRunner(config, _policy(config, vertices, search_bar), search, particle_filter, refined_track, run_smc)


def _policy(config, vertices: np.ndarray, search_bar: float) -> RecoveryPolicy:
    from app.pipeline.tracker import PLAN_POINTS

    centroid = vertices.mean(axis=0)
    surface_point = vertices[np.argmin(np.linalg.norm(vertices - centroid, axis=1))]
    st = config.status
    return RecoveryPolicy(config.recovery, centroid, surface_point, config.refine.enabled, st.min_fitness,
                          (st.uncertain_speed, st.motion_window_s),
                          (config.init_sigma_p, config.init_sigma_r), search_bar,
                          config.refine.competitor_distance,
                          levels.chi_level(st.alpha, 3), vertices[::max(1, len(vertices) // PLAN_POINTS)])


def _wide_search(config, backend, camera: PinholeCamera, refined_track: RefinedTrack | None, vertices: np.ndarray):
    """The recovery's wide search (app/filter/wide_search.py), or None (``recovery.search`` false, or
    no refinement to verify with)."""
    if not config.recovery.search or refined_track is None:
        return None
    return build_wide_search(config, backend, camera, refined_track.refiner, vertices)


def build_wide_search(config, backend, camera: PinholeCamera, refiner, vertices: np.ndarray):
    """The wide search with the configured budget and bars (``recovery.search_evaluations``,
    ``status.min_fitness`` and its share at 1 sigma, :func:`app.tracking.levels.sharp_bar`, ``refine.nearby_margin``, ``status.max_behind_excess``): the recovery's,
    and the detector's for a start without a pose (app/tracking/detector.py)."""
    from app.filter.wide_search import SearchConfig, WideSearch

    search = SearchConfig(evaluations=config.recovery.search_evaluations, min_fitness=config.status.min_fitness,
                          margin=config.refine.nearby_margin, max_behind_excess=config.status.max_behind_excess)
    return WideSearch(backend, camera, refiner, vertices, search)


def usable_frame(depth_small: np.ndarray, T_base_camera: np.ndarray | None) -> bool:
    """A frame an initialiser can use: a camera pose and at least one valid depth pixel (only
    checked when an initialisation is due, not every frame)."""
    return T_base_camera is not None and bool(np.any(np.isfinite(depth_small) & (depth_small > 0)))
