"""The depth tracker: the particle filter wired to the configured likelihood backend at the filter's resolution.

One object per session: it owns the backend (``render.backend``: GL resources are created on the
calling thread; app/render/backends.py), the
tracking mesh (decimated to ``config.mesh_triangles``) and the filter. ``process`` is the per-frame
entry point used by ``replay`` and ``track``: full-resolution depth in, estimate and status out.
A lost track re-initialises itself (``recovery.*``, app/filter/recovery.py); the
re-initialisations are in :meth:`DepthTracker.report` and each frame's ``FilterOutput.reinitialised``.
The status's predicted template error is computed over the plan's template points when the tracker
is given them (:meth:`DepthTracker.use_plan_points`: replay with a plan, a session with the
projector), else over ``PLAN_POINTS`` of the mesh's vertices (a conservative bound).
"""
from __future__ import annotations

import logging
import math
import time
from collections import defaultdict
from dataclasses import replace
from functools import partial

import numpy as np
import trimesh

from app.config import TrackerConfig
from app.depth_image import downsample_nearest
from app.filter.motion_gate import MotionGate
from app.filter.particle_filter import FilterOutput, ParticleFilter
from app.filter.refine import Refiner, RefineParams
from app.filter.refine_track import RefinedTrack
from app.filter.status import (Reason, RefinementEvidence, TrackingStatus, motion_reason, refinement_reasons,
                               with_refinement)
from app.metrics import STATUS_CODE
from app.tracking import levels
from app.tracking.lifecycle import Lifecycle, State, frame_event
from app.geometry.camera import PinholeCamera
from app.filter.recovery import FOUND_SIGMA_M, FOUND_SIGMA_RAD
from app.pipeline.recovery_runner import build_wide_search, make_recovery, usable_frame
from app.pipeline.stages import PARALLEL, StageWorker, stages_mode
from app.tracking.search_worker import INLINE, PROCESS, SearchWorker, search_worker_mode
from app.tracking.start import StartByDetection

log = logging.getLogger(__name__)


class DepthTracker:
    """Track ``T_base_bone`` from depth frames and camera poses.

    Parameters
    ----------
    config : TrackerConfig
    mesh : the bone mesh (bone frame, metres), decimated here for tracking
    camera : the depth camera's full-resolution PinholeCamera
    T_flange_camera : hand-eye (4, 4), only used for logging the flange
    """

    def __init__(self, config: TrackerConfig, mesh: trimesh.Trimesh, camera: PinholeCamera,
                 T_flange_camera: np.ndarray | None = None, live: bool = False):
        from app.mesh import outward_wound, prepare_mesh
        from app.render.backends import make_backend

        self.config = config
        self.T_flange_camera = T_flange_camera
        tracking_mesh = prepare_mesh(mesh, max_triangles=config.mesh_triangles, center=False)
        self.mesh_vertices = np.asarray(tracking_mesh.vertices)
        self.mesh_faces = np.asarray(tracking_mesh.faces)
        width, height = config.resolution
        self.camera = camera.resized(width, height)
        cull = config.cull_back_faces and outward_wound(tracking_mesh)
        self._mesh, self._camera_full, self._cull = mesh, camera, cull     # the search worker builds its own parts
        if config.cull_back_faces and not cull:
            log.warning("the mesh's triangles are not consistently wound outwards: back-face culling disabled (slower)")
        # gl_description names the backend that runs (and the GL renderer for gl); the summary and rerun show it
        self.backend, self.gl_description = make_backend(
            config.backend, self.mesh_vertices, self.mesh_faces, self.camera, config.particles, config.likelihood,
            near=config.near, far=config.far, cull_back_faces=cull)
        self.backend_name = self.backend.name
        self.filter = ParticleFilter(_filter_config(config), self.backend, np.random.default_rng(config.seed))
        self.refined_track = _refined_track(config, mesh, camera)
        self.stages = stages_mode(config.stages, self.refined_track is not None)
        self._stage_worker = StageWorker() if self.stages == PARALLEL else None     # app/pipeline/stages.py
        if self._stage_worker is not None:
            self.refined_track.nearby.map, self.refined_track.nearby.width = self._stage_worker.pairs, 2
        self._timings: dict[str, float] = defaultdict(float)
        self._frames = 0
        self._pending_point: np.ndarray | None = None
        self._started_from_point = False
        self.init_result = None
        self._start_detection: StartByDetection | None = None   # init.method auto without a pose (start_by_detection)
        self.recovery_runner = make_recovery(config, self.backend, self.camera, self.filter, self.refined_track,
                                             self.mesh_vertices, self._run_smc)
        mode = search_worker_mode(config.recovery.search_worker, live)
        if self.wide_search is not None and mode != INLINE:
            rng = np.random.default_rng(self.filter.rng.integers(2**63))
            build = partial(build_worker_search, config, self.mesh_vertices, self.mesh_faces, self.camera, cull,
                            np.asarray(mesh.vertices, float), np.asarray(mesh.faces), camera)
            self.recovery_runner.worker = SearchWorker(build, rng, process=mode == PROCESS)
            self.recovery_runner.worker.prepare()
        self.template_points = "mesh_vertices"
        self._T_base_bone_last: np.ndarray | None = None
        self._lifecycle = Lifecycle()        # without the recovery; with it, the recovery's (it drives the transitions)
        st = config.status
        self.motion_gate = MotionGate(st.motion_window_s, st.uncertain_speed, template_points(mesh))
        self.filter.motion_gate.points_bone = self.motion_gate.points_bone

    @property
    def recovery(self):
        """The recovery policy (app/filter/recovery.py), or None with ``recovery.enabled`` false."""
        return self.recovery_runner.policy if self.recovery_runner is not None else None

    @property
    def lifecycle(self) -> Lifecycle:
        """The tracker's lifecycle (app/tracking/lifecycle.py): the recovery's, which its triggers and
        attempts move, or the tracker's own without the recovery (moved by the frames' events alone)."""
        return self.recovery.lifecycle if self.recovery is not None else self._lifecycle

    def _new_lifecycle(self) -> None:
        """A start begins a fresh lifecycle: no search due, no hypothesis, never ok yet."""
        if self.recovery is not None:
            self.recovery.lifecycle, self.recovery.due_code = Lifecycle(), ""
        else:
            self._lifecycle = Lifecycle()

    @property
    def wide_search(self):
        """The recovery's wide search (app/filter/wide_search.py), or None."""
        return self.recovery_runner.wide_search if self.recovery_runner is not None else None

    def start(self, T_base_bone: np.ndarray) -> None:
        """Spread the particles around a coarse initial pose (the surgeon's alignment)."""
        self.filter.initialise(T_base_bone)
        self.motion_gate.reset()
        self._new_lifecycle()
        if self.refined_track is not None:
            self.refined_track.seed(T_base_bone, (self.config.init_sigma_p, self.config.init_sigma_r))
        if self.recovery is not None:
            self.recovery.set_start(T_base_bone)

    def set_point_prior(self, point_base: np.ndarray | None) -> None:
        """A point on the bone in the base frame (m; the trial's or session's ``point_prior``): the
        recovery's one-point initialiser starts from it (app/filter/recovery.py)."""
        if point_base is not None:
            point_base = np.asarray(point_base, dtype=float).reshape(3)
            if not np.all(np.isfinite(point_base)):
                raise ValueError(f"the point prior must be 3 finite numbers, got {point_base!r}")
        if self.recovery is not None:
            self.recovery.set_point_prior(point_base)

    def use_plan_points(self, points_bone: np.ndarray) -> None:
        """Bound the predicted error of these template points (bone frame, m; the plan's) in the status
        instead of the mesh's vertices (app/filter/status.py, ``max_template_std``)."""
        points_bone = np.asarray(points_bone, dtype=float).reshape(-1, 3)
        if self.refined_track is None or len(points_bone) == 0:
            return
        self.refined_track.plan_points = points_bone - self.refined_track.refiner.center
        self.template_points = "plan"
        self.motion_gate.points_bone = self.filter.motion_gate.points_bone = points_bone
        if self.recovery is not None:
            self.recovery.points_bone = points_bone      # the recovery's still test watches the same points

    def start_from_point(self, point_base: np.ndarray) -> None:
        """Start from one point on the bone (base frame, m): the one-point SMC initialiser runs on the
        first frame that has a camera pose and valid depth (app/filter/smc_init/); frames before it
        are reported lost.

        Experimental: on a CT crest in soft tissue the one-frame likelihood can prefer a wrong pose
        that the status rules do not catch (BENCHMARKS.md §5), so a tracker started this way reports
        uncertain at best, never ok (no template is projected). For evaluating the initialiser in
        replays, not for the operating room.
        """
        point = np.asarray(point_base, dtype=float).reshape(3)
        if not np.all(np.isfinite(point)):
            raise ValueError(f"the point on the bone must be 3 finite numbers, got {point_base!r}")
        self._pending_point = point
        self._new_lifecycle()
        self._started_from_point = True
        if self.recovery is not None and self.recovery.point_prior is None:
            self.recovery.set_point_prior(point)

    def start_by_detection(self, point_base: np.ndarray | None, point_source=None) -> None:
        """Start without a pose (``init.method: auto``; issue 33): the detector (app/tracking/detector.py,
        the wide search around the point, verified by the refinement) on the first usable frame, from
        ``point_base`` (base frame, m) when given, or from the first point ``point_source`` locates
        (app/tracking/start.py's PointSource, e.g. the session's pointed pixel: the frames before it has
        one are lost, 'initialising', with its reason), else over the whole image (experimental); retried
        every ``status.settle_s`` while it finds nothing (those frames are lost, 'initialising'). A found
        pose seeds the particles (the recovery's FOUND_SIGMA_M / _RAD about it) and the refined track as
        a verified fit, and is ok only once confirmed (RecoveryPolicy.set_found_start). Needs the
        refinement; without it (or without the recovery, which confirms) a point starts the one-point
        SMC instead (:meth:`start_from_point`, never ok)."""
        from app.tracking.detector import SearchDetector, prior_kind

        if self.refined_track is None or self.recovery is None:
            if point_base is None:
                from app.errors import ConfigError

                what = ("a point located live (bone.pointed_pixel, bone.pointer)" if point_source is not None else
                        "'auto' without a pose or a point searches the whole image, which")
                raise ConfigError("init.method", f"{what} needs refine.enabled and recovery.enabled true: enable "
                                  "them or give a pose")
            self.start_from_point(point_base)
            return
        prior_kind(point_base)                                        # a clear error for a malformed point
        point = None if point_base is None else np.asarray(point_base, float).reshape(3)
        search = self.wide_search or build_wide_search(self.config, self.backend, self.camera,
                                                       self.refined_track.refiner, self.mesh_vertices)     # recovery.search off: built alike
        self._new_lifecycle()
        self._start_detection = StartByDetection(SearchDetector(search, self.filter.rng, self.config.detector), point, point_source,
                                                 retry_s=self.config.recovery.search_retry_s)
        if self.recovery_runner is not None and self.recovery_runner.worker is not None:
            self._start_detection.worker = self.recovery_runner.worker      # a live session: off the frame loop
        if point is not None and self.recovery.point_prior is None:
            self.recovery.set_point_prior(point)

    @property
    def start_report(self) -> dict | None:
        """The detected start's work for the summaries (None for a start from a pose or the SMC)."""
        return None if self._start_detection is None else self._start_detection.report()

    def _initialise_from_point(self, depth_small: np.ndarray, depth_m: np.ndarray, T_base_camera: np.ndarray,
                               stamp: float) -> bool:
        """The pending start on a usable frame: the detector's (True when it found the bone) or the one-point SMC's."""
        detection = self._start_detection
        if detection is not None and detection.pending:
            T_found = detection.attempt(depth_small, depth_m, T_base_camera, stamp)
            if detection.source is not None and detection.point is not None and self.recovery.point_prior is None:
                self.recovery.set_point_prior(detection.point)        # the located point, kept for the recovery
            if T_found is None:
                return False
            self.filter.set_state(self.recovery.state_around(T_found, self.config.particles, self.filter.rng,
                                                             FOUND_SIGMA_M, FOUND_SIGMA_RAD))
            self.motion_gate.reset()
            self.refined_track.seed(T_found, verified=True)
            self.recovery.set_found_start(T_found)
            return True
        from app.filter.smc_init import smc_config_for

        self.init_result = self._run_smc(self._pending_point, depth_small, T_base_camera, smc_config_for(self.config))
        self._pending_point = None
        return True

    def _run_smc(self, point_base: np.ndarray, depth_small: np.ndarray, T_base_camera: np.ndarray, smc):
        """The one-point SMC initialiser (app/filter/smc_init/) with config ``smc`` around ``point_base``
        on this frame; the particles are seeded from its result, which is returned."""
        from app.filter.smc_init import OnePointInitialiser, seed_state

        initialiser = OnePointInitialiser(self.backend, self.camera, self.mesh_vertices, self.mesh_faces, smc,
                                          self.filter.rng)
        result = initialiser.run(depth_small, T_base_camera, point_base)
        self.filter.set_state(seed_state(result, self.config.particles, self.filter.rng))
        return result

    def process(self, depth_m: np.ndarray, stamp: float, T_base_camera: np.ndarray | None) -> FilterOutput:
        """One frame: full-resolution depth (H, W) metres, its stamp (s) and camera pose (None = unknown).

        The steps (DESIGN.md "The status as a test, and the tracker's lifecycle"): start from the point
        when one is pending; re-initialise when the recovery has one due; the particle filter's step;
        the refinement and its tests (seen, consistent, unique); the motion test (steady); the caps of
        a point start and of the recovery (hold, confirmation); the lifecycle's state; the timings."""
        width, height = self.config.resolution
        depth_small = downsample_nearest(depth_m, width, height)
        if self._pending_point is not None or (self._start_detection is not None and self._start_detection.pending):
            if not (usable_frame(depth_small, T_base_camera)
                    and self._initialise_from_point(depth_small, depth_m, T_base_camera, stamp)):
                return self._not_started(stamp)
        reinitialised = self._recover(depth_small, depth_m, T_base_camera, stamp)
        ahead = self._track_fit_ahead(depth_m, T_base_camera)
        try:
            result = self.filter.step(depth_small, stamp, T_base_camera)
        finally:
            track_fit = self._take(ahead)
        if self.refined_track is not None:
            if reinitialised:
                self.motion_gate.reset()
            result = self._steady(self._refine(result, depth_m, T_base_camera, track_fit), stamp)
        else:
            result = _unrefined(result)
        result = self._caps(result, stamp, reinitialised)
        state = self._state(result)
        result = replace(result, state=state.value,
                         reasons=result.reasons if result.status != TrackingStatus.OK else ())
        self._account(result)
        return result

    def _recover(self, depth_small, depth_m, T_base_camera, stamp: float) -> bool:
        """Run a due re-initialisation (app/pipeline/recovery_runner.py), or take the worker's finished
        search (app/tracking/search_worker.py); whether the track was re-initialised."""
        runner = self.recovery_runner
        if runner is None:
            return False
        taken = runner.take_search(stamp)
        if taken is not None:
            return taken[1]
        if not runner.may_run(depth_small, depth_m, T_base_camera):
            return False
        seconds, reinitialised = runner.run(depth_small, depth_m, T_base_camera, stamp, self._T_base_bone_last)
        self._timings["recovery_search"] += seconds
        return reinitialised

    def _caps(self, result: FilterOutput, stamp: float, reinitialised: bool) -> FilterOutput:
        """The lifecycle's caps on ok: a point start is never ok; the recovery holds the frames after a
        re-initialisation and a found pose until it is confirmed (app/filter/recovery.py)."""
        if self._started_from_point:
            result = replace(result, status=_at_most_uncertain(result.status),
                             reasons=result.reasons + (Reason("point_start", "started from a point: never ok"),))
        if self.recovery is None:
            return result
        status = self.recovery.update(result.status, result.weighed, result.refined, result.refine_fitness,
                                      result.T_base_bone, stamp, sharp=result.refine_sharp)
        cap = self.recovery.capped
        reasons = result.reasons + ((Reason(cap, f"{cap} after a re-initialisation"),) if cap else ())
        if self.recovery.lifecycle.state == State.SEARCHING:        # ok only in tracking: a due search caps it
            trigger = self.recovery.due_code if self.recovery.pending else "retrying"
            reasons += (Reason("searching", f"searching ({trigger or 'due'})"),)
            status = _at_most_uncertain(status)
        return replace(result, status=status, reinitialised=reinitialised, reasons=reasons)

    def _state(self, result: FilterOutput):
        """The frame's lifecycle state: the recovery stepped its lifecycle in ``_caps``; without it the
        frame's own event steps the tracker's."""
        if self.recovery is not None:
            return self.lifecycle.state
        return self._lifecycle.frame(frame_event(str(result.status), bool(result.weighed), False, False))

    def _account(self, result: FilterOutput) -> None:
        """Remember the frame's pose and add its stage timings."""
        self._T_base_bone_last = result.T_base_bone
        for stage, seconds in result.timings.items():
            self._timings[stage] += seconds
        for stage, seconds in self.backend.timings.items():
            self._timings[f"{self.backend_name}_{stage}"] += seconds
        self._frames += 1

    def _track_fit_ahead(self, depth_m: np.ndarray, T_base_camera: np.ndarray | None):
        """With ``filter.stages`` parallel: the refined track's refinement from its own pose
        (``RefinedTrack.track_fit``, which needs nothing of the filter's frame), started on the stage
        worker to run beside the filter's step (app/pipeline/stages.py); None when serial or when the
        frame has no camera pose (no refinement then)."""
        if self._stage_worker is None or T_base_camera is None:
            return None
        return self._stage_worker.submit(_timed, self.refined_track.track_fit, depth_m, T_base_camera)

    def _take(self, ahead):
        """The fit started by :meth:`_track_fit_ahead` (waited for; None when none was started or the
        track made none); its worker seconds are the ``refine_ahead`` timing, beside the filter's step."""
        if ahead is None:
            return None
        fit, seconds = ahead.result()
        self._timings["refine_ahead"] += seconds
        return fit

    def _refine(self, result: FilterOutput, depth_m: np.ndarray, T_base_camera: np.ndarray | None,
                track_fit=None) -> FilterOutput:
        """The local refinement on a weighed frame (app/filter/refine_track.py): the refined pose is
        the output, the cloud is shifted onto it (feedback, only once the filter's cloud has converged:
        a refinement started from an unconverged filter can lock onto a wrong fit that is nearly as
        good, and dragging the cloud there keeps it there; measured on crest_left_02, BENCHMARKS.md §6),
        and the status combines the filter's
        with the refinement's evidence (app/filter/status.py)."""
        if not result.weighed or T_base_camera is None:
            return result
        out = self.refined_track.update(depth_m, T_base_camera, result.T_base_bone, track_fit)
        c = self.config.refine
        st = self.config.status
        converged = (result.status != TrackingStatus.LOST and result.position_spread <= c.feedback_spread
                     and result.rotation_spread <= c.feedback_spread_angle)
        if (c.feedback and converged and out.T_base_bone is not None
                and out.fitness >= st.min_fitness and not out.competitor):
            self.filter.shift_to(out.T_base_bone, result.T_base_bone)
        evidence = RefinementEvidence(out.fitness, out.template_std, out.competitor, out.behind, out.held_chi2,
                                      out.nearby, out.nearby_unanswered)
        status = with_refinement(result.status, evidence, self.config.status)
        reasons = result.reasons + tuple(refinement_reasons(evidence, self.config.status))
        timings = {**result.timings, "refine": out.seconds}
        T_base_bone = out.T_base_bone if out.T_base_bone is not None else result.T_base_bone
        return replace(result, T_base_bone=T_base_bone, status=status, timings=timings, refine_fitness=out.fitness,
                       template_std=out.template_std, refined=out.T_base_bone is not None, competitor=out.competitor,
                       nearby=out.nearby, refine_sharp=out.sharp, reasons=reasons)

    def _steady(self, result: FilterOutput, stamp: float) -> FilterOutput:
        """The motion test on the tracker's output pose (the refined one; app/filter/motion_gate.py): the
        template's points moving faster than ``status.uncertain_speed``, or less than
        ``status.settle_s`` since it did or since the start, keeps the status below ok. With the
        refinement this replaces the filter's gate on its particle mean, which read the cloud's
        convergence from the coarse start as motion (0.2-0.5 s more not ok on every clean start). A failed
        held test (the image's fit contradicts the static prior's held pose) is motion too: the settle restarts."""
        speed, since = self.motion_gate.update(stamp, result.T_base_bone)
        if any(getattr(r, "code", "") == "held" for r in result.reasons):
            # the held test failed: the bone started to move under the held pose. Its settle restarts here, so
            # the frames after the prior releases are not ok while the estimate catches up (or_fast_reposition
            # crest_right_03 seed 3: ok at 1.5 and 2.6 mm off the 2-4 frames after a release, the bone
            # accelerating at 45-70 mm/s, its estimate's speed over the window still below 30 mm/s)
            self.motion_gate.mark(stamp)
            since = 0.0
        reason = motion_reason(speed, since, self.config.status)
        if reason is None:
            return result
        return replace(result, status=_at_most_uncertain(result.status), reasons=result.reasons + (reason,))

    def report(self) -> dict:
        """For the summaries: the re-initialisations (count, stamps, kinds, reasons) and which points
        the status's predicted template error was computed over ('plan' | 'mesh_vertices')."""
        recovery = self.recovery_runner.report() if self.recovery_runner is not None else \
            {"enabled": False, "reinitialisations": 0, "events": []}
        return {"recovery": recovery, "template_points": self.template_points}

    def _not_started(self, stamp: float) -> FilterOutput:
        """A lost result while the one-point initialiser waits for a frame it can use (the pose: the
        pointed point, identity rotation; a lost status blanks every output that would use it)."""
        T_base_bone = np.eye(4)
        detection = self._start_detection
        point = self._pending_point if detection is None else detection.point
        if point is not None:
            T_base_bone[:3, 3] = point
        why = ("waiting for a frame to start from the point" if detection is None else
               detection.waiting or ("waiting for a frame to locate the " + detection.source.description
                                     if detection.source is not None and detection.point is None else
                                     "the detector has not found the bone yet"))
        return FilterOutput(T_base_bone=T_base_bone, position_spread=float("inf"),
                            rotation_spread=float("inf"), ess=0.0, ess_ratio=0.0, log_likelihood_max=float("nan"),
                            status=TrackingStatus.LOST, inlier_fraction=float("nan"), covered_pixels=0, n_nan=0,
                            resampled=False, dt=0.0, weighed=False, timings={},
                            state=self.lifecycle.frame("waiting").value,
                            reasons=(Reason("initialising", why),))

    def particle_positions(self) -> np.ndarray:
        """(N, 3) particle positions in the base frame (metres); (0, 3) before the start has set any."""
        return self.filter.state.p if self.filter.state is not None else np.zeros((0, 3))

    def mean_timings_ms(self) -> dict[str, float]:
        return {k: 1e3 * v / max(self._frames, 1) for k, v in self._timings.items()}

    def release(self) -> None:
        if self.recovery_runner is not None and self.recovery_runner.worker is not None:
            self.recovery_runner.worker.close()
        if self._stage_worker is not None:
            self._stage_worker.close()
        self.backend.release()


def build_worker_search(c: TrackerConfig, vertices: np.ndarray, faces: np.ndarray, camera: PinholeCamera,
                        cull: bool, full_vertices: np.ndarray, full_faces: np.ndarray, camera_full: PinholeCamera):
    """The search worker's own wide search, built on its thread or in its process
    (app/tracking/search_worker.py): its own likelihood backend (a GL context belongs to its thread)
    on the tracking mesh (``vertices``, ``faces``) at the filter's ``camera``, and its own refiner on the
    full mesh at the full-resolution ``camera_full``, with the tracker's configuration ``c``. Module
    level and from picklable parts, so that a worker process can build it."""
    from app.render.backends import make_backend

    backend, _ = make_backend(c.backend, vertices, faces, camera, c.particles, c.likelihood, near=c.near, far=c.far,
                              cull_back_faces=cull)
    refiner = Refiner(full_vertices, full_faces, camera_full, refine_params(c), seed=c.seed)
    return build_wide_search(c, backend, camera, refiner, vertices)


def _timed(fn, *args):
    """(fn(*args), its wall seconds)."""
    t0 = time.perf_counter()
    return fn(*args), time.perf_counter() - t0


def _at_most_uncertain(status: TrackingStatus) -> TrackingStatus:
    """``status`` capped at uncertain (a lost frame stays lost; app/metrics.py ranks them)."""
    return max(status, TrackingStatus.UNCERTAIN, key=STATUS_CODE.get)


PLAN_POINTS = 300   # mesh vertices standing in for the template's points in the status's error bound


def _inner(tracker):
    """The DepthTracker behind a session plugin (app/pipeline/engine_tracker.py's ``engine``), or itself."""
    return tracker if hasattr(tracker, "report") else getattr(tracker, "engine", tracker)


def tracker_report(tracker) -> dict:
    """``DepthTracker.report()`` for a summary ({} for a tracker without one, e.g. the ICP baseline),
    with the detected start's report (``start``) when the tracker started by detection."""
    inner = _inner(tracker)
    report = inner.report() if hasattr(inner, "report") else {}
    start = getattr(inner, "start_report", None)
    return {**report, "start": start} if start is not None else report


def start_tracker(tracker, initial_pose: np.ndarray | None, point_prior: np.ndarray | None,
                  point_source=None) -> None:
    """Start a session's or a replay's tracker by its ``init.method`` (:func:`start_method`): from the
    coarse initial pose, from the point prior through the detector (DepthTracker.start_by_detection),
    or by the one-point initialiser (``point``: never ok, DepthTracker.start_from_point); the point
    prior is kept for the recovery either way. A tracker without ``init.method`` (the ICP baseline)
    starts from the pose.

    ``point_source`` (app/tracking/start.py's PointSource: the session's ``bone.pointed_pixel`` or
    ``bone.pointer``) is a point given live, located on the first frame that allows it: the detector
    starts from it, never from a pose or another point (the caller gives none with it), and only under
    ``init.method: auto``."""
    inner = _inner(tracker)
    if point_source is not None:
        _start_from_source(inner, initial_pose, point_prior, point_source)
        return
    if point_prior is not None and hasattr(inner, "set_point_prior"):
        inner.set_point_prior(point_prior)
    method = start_method(getattr(getattr(inner, "config", None), "init_method", "pose"), initial_pose, point_prior)
    if method == "pose" and initial_pose is not None:
        tracker.start(np.asarray(initial_pose, float))
    elif method == "detect" and hasattr(inner, "start_by_detection"):
        inner.start_by_detection(point_prior)
    elif point_prior is not None and hasattr(inner, "start_from_point"):
        inner.start_from_point(point_prior)
    else:
        from app.errors import ConfigError

        raise ConfigError("bone.initial_pose", "missing: this tracker starts from a coarse 4x4 T_base_bone "
                          "(or give bone.point_prior for the particle filter)")


def _start_from_source(inner, initial_pose, point_prior, point_source) -> None:
    """:func:`start_tracker` with a live point: the detector from the source's point (checked here: a
    pose or a point beside it, another init.method or a tracker without the detector are refused)."""
    from app.errors import ConfigError

    if initial_pose is not None or point_prior is not None:
        raise ConfigError("bone", "a live point (pointed_pixel, pointer) starts the tracker on its own: give no "
                          "initial_pose or point_prior with it")
    init_method = getattr(getattr(inner, "config", None), "init_method", None)
    if init_method != "auto" or not hasattr(inner, "start_by_detection"):
        raise ConfigError("init.method", f"a live point (bone.pointed_pixel, bone.pointer) needs the particle filter's "
                          f"init.method 'auto' (the detector), got {init_method!r}: set init.method: auto "
                          "in the tracker's config, or start from bone.initial_pose")
    inner.start_by_detection(None, point_source)


def start_method(init_method: str, initial_pose, point_prior) -> str:
    """How a tracker starts (``init.method``; issue 33): 'auto' takes the coarse pose when there is one
    ('pose'), else the detector from the point or, experimentally, over the whole image ('detect');
    'pose' and 'point' (the one-point SMC) as named."""
    if init_method != "auto":
        return init_method
    return "pose" if initial_pose is not None else "detect"


def use_plan(tracker, plan) -> None:
    """Give a tracker the plan's template points for its status bound (when it takes them)."""
    inner = _inner(tracker)
    if plan is not None and hasattr(inner, "use_plan_points"):
        inner.use_plan_points(plan.points())


def use_projector_plan(tracker, sinks, mesh=None) -> None:
    """A session: the plan of the first projector output (plugins/projector_output.py's ``sink.plan``),
    else, given the ``mesh``, the default projector configuration's plan on it
    (app/pipeline/replay.py ``known_plan``), as a replay does: the tracking never depends on which
    outputs a session has (issue 34)."""
    plans = (getattr(getattr(s, "sink", None), "plan", None) for s in sinks)
    plan = next((p for p in plans if p is not None), None)
    if plan is None and mesh is not None:
        from app.pipeline.replay import known_plan

        plan, _ = known_plan(None, mesh)
    use_plan(tracker, plan)


def _filter_config(config: TrackerConfig) -> TrackerConfig:
    """With the refinement on, the motion test moves to the tracker's output pose
    (:meth:`DepthTracker._steady`): the filter's gate on its particle mean is switched off."""
    if not config.refine.enabled:
        return config
    return replace(config, status=replace(config.status, uncertain_speed=math.inf, settle_s=0.0))


def template_points(mesh: trimesh.Trimesh) -> np.ndarray:
    """(N, 3) m, bone frame: ``PLAN_POINTS`` of the mesh's vertices, the template's points until a plan gives its
    own (:meth:`DepthTracker.use_plan_points`): the status's error bound and motion test, the recovery's still test."""
    vertices = np.asarray(mesh.vertices, float)
    return vertices[::max(1, len(vertices) // PLAN_POINTS)]


def _unrefined(result: FilterOutput) -> FilterOutput:
    """Without the refinement (``refine.enabled: false``) no frame is ok: the "seen" test, the template's
    predicted error from the fit's information (DESIGN.md), cannot be made, and the filter's own inlier and
    image shares that stood in for it were fitted to one simulator (issue 32: removed)."""
    if result.status != TrackingStatus.OK:
        return result
    return replace(result, status=TrackingStatus.UNCERTAIN, reasons=result.reasons + (
        Reason("not_refined", "the refinement is off (refine.enabled: false): the template's error is not predicted"),))


def refine_params(config: TrackerConfig) -> RefineParams:
    """The refinement's settings from the configuration (``refine.*``, and the likelihood's noise model
    and occluder margin, which the refinement shares)."""
    c, lk = config.refine, config.likelihood
    return RefineParams(stride=c.stride, iterations=c.iterations, samples=c.samples, k=lk.k,
                        sigma_base=lk.sigma_base, occluder_margin=lk.occluder_margin, outline_ring=c.outline_ring,
                        tissue_border=c.tissue_border, behind_z=levels.normal_level(config.status.alpha),
                        noise_window_px=c.noise_window_px)


def _refined_track(config: TrackerConfig, mesh: trimesh.Trimesh, camera: PinholeCamera) -> RefinedTrack | None:
    """The refinement on the full mesh at the camera's full resolution, or None when disabled."""
    c = config.refine
    if not c.enabled:
        return None
    vertices, faces = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    refiner = Refiner(vertices, faces, camera, refine_params(config), seed=config.seed)
    return RefinedTrack(refiner, c, template_points(mesh), config.status.covariance_inflation,
                        config.status.max_template_std)
