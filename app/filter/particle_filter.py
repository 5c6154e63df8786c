"""The particle filter stepper: one call per frame through named stages.

Import as ``from app.filter.particle_filter import ParticleFilter``. DESIGN.md "The particle
filter"; the particles are poses ``T_base_bone`` (:mod:`app.filter.motion`), the likelihood and the
evidence for the status come from an :class:`app.filter.observation.ObservationModel` (the depth
backends, GL: ``app/render/likelihood.py``, CPU: ``app/render/cpu_likelihood.py``, or a
``CompositeObservation`` summing several), which sees ``T_camera_bone = inv(T_base_camera) @ T_base_bone``.

``step(depth, stamp, T_base_camera)``, with ΔT = stamp - previous stamp (``first_dt`` = 1/90 s on
the first frame; a non-increasing stamp gives ΔT = 0). ΔT is predicted in sub-steps of at most
``first_dt`` (the nominal frame time: the motion parameters are per frame), so dropped frames and
camera dropouts are predicted as the frames they replace (:meth:`ParticleFilter._predict`):

- sampling 'joint': predict (p, v, q, ω) → likelihood → weight → [resample]
- sampling 'blockwise' ((B) 7.2.3): predict (p, v) → likelihood → weight → [resample] →
  predict (q, ω) → likelihood → weight → [resample]
- weight: lw += log p(z | x) (NaN or +inf values set to -inf and counted, the one non-finite policy
  of :func:`app.filter.observation.finite_log_likelihood`),
  normalised with log-sum-exp; if every weight is -inf the weights are reset to uniform (logged).
- resample when ESS / N < ``resample_threshold`` ((B): 0.5) with the configured scheme
  (:mod:`app.filter.resampling`); the estimate is taken from the weighted particles of the last
  weighing, before that resampling (less noise).
- estimate: weighted mean pose and spread (:mod:`app.filter.estimate`); the observation model
  reports its evidence about the estimate (covered pixels, inlier fraction; ``model.evidence``);
  its speed comes from :mod:`app.filter.motion_gate`; status by :mod:`app.filter.status`.

A frame without a camera pose (None) or without any valid depth pixel is predicted only; its
status is at best uncertain. A frame in which occluders hide the bone (the model's evidence about the
last estimate in the new image says ``bone_hidden``; for depth: fewer than
``status.min_covered_pixels`` valid pixels not more than ``likelihood.occluder_margin`` in front
of it, a hand over the bone) is neither
predicted nor weighed: the particles are held where they were, because the only evidence left
would be the soft tissue and the table around the hidden bone, which pull the cloud away, and
the motion noise would spread it for nothing; the status is uncertain. Weighing resumes as soon
as the bone reappears. ``FilterOutput.timings`` gives seconds per stage: predict,
likelihood (render + likelihood in the backend), weight, resample, estimate.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from app.filter import motion
from app.filter import resampling as rs
from app.filter import weights as lw_ops
from app.filter.estimate import PoseEstimate, estimate, template_spread
from app.filter.motion_gate import MotionGate
from app.filter.observation import Evidence, ObservationModel, finite_log_likelihood
from app.filter.likelihood_ref import LikelihoodParams
from app.filter.motion import MotionParams, ParticleState
from app.filter.status import StatusInputs, StatusThresholds, TrackingStatus, verdict
from app.geometry import quaternion as quat
from app.geometry import se3

log = logging.getLogger(__name__)

SAMPLING_MODES = ("joint", "blockwise")
STAGES = ("predict", "likelihood", "weight", "resample", "estimate")


@dataclass
class FilterConfig:
    """Settings of the filter (``app.config.TrackerConfig`` extends this with the renderer's).

    particles : N; sampling : 'joint' | 'blockwise'; resample_threshold : ESS/N below which to
    resample; resampling : scheme name; first_dt : s, ΔT of the first frame; init_sigma_p (m) /
    init_sigma_r (rad) : spread of :meth:`ParticleFilter.initialise`.
    """

    particles: int = 200
    sampling: str = "joint"
    resample_threshold: float = 0.5
    resampling: str = rs.DEFAULT_SCHEME
    first_dt: float = 1.0 / 90.0
    init_sigma_p: float = 0.01
    init_sigma_r: float = 0.1
    motion: MotionParams = field(default_factory=MotionParams)
    likelihood: LikelihoodParams = field(default_factory=LikelihoodParams)
    status: StatusThresholds = field(default_factory=StatusThresholds)


@dataclass
class FilterOutput:
    """One frame's result.

    T_base_bone : (4, 4) weighted mean pose; position_spread (m); rotation_spread (rad);
    ess : effective sample size after the last weighing (N when not weighed); ess_ratio : ess / N;
    log_likelihood_max : max finite log-likelihood of the last weighing (NaN when not weighed);
    status : TrackingStatus (a str); inlier_fraction : inliers / valid covered pixels of the
    estimate (NaN when none); covered_pixels : that count; n_nan : NaN log-likelihoods this frame;
    resampled : whether any block resampled; dt : s; weighed : whether the depth was used;
    timings : seconds per stage (STAGES). Set by the tracker's local refinement
    (app/filter/refine_track.py): refine_fitness (NaN when not refined), template_std (m),
    refined : T_base_bone is the refined pose; competitor : a competing pose fits about as well;
    nearby : m, the template gap to a fit near the track that explains the image better (NaN: none found);
    refine_sharp : the best fit's consistent sharp share, kept or not (NaN when no fit converged).
    Set by the tracker's recovery (app/filter/recovery.py): reinitialised : the particles were
    re-initialised on this frame (a lost track). reasons : the rules and lifecycle states that kept the
    status below ok (app/filter/status.py ``Reason``: text with a ``code``; empty when ok); state : the
    tracker's lifecycle state (app/tracking/lifecycle.py; '' for the filter alone).
    """

    T_base_bone: np.ndarray
    position_spread: float
    rotation_spread: float
    ess: float
    ess_ratio: float
    log_likelihood_max: float
    status: TrackingStatus
    inlier_fraction: float
    covered_pixels: int
    n_nan: int
    resampled: bool
    dt: float
    weighed: bool
    timings: dict[str, float]
    refine_fitness: float = float("nan")
    template_std: float = float("inf")
    refined: bool = False
    competitor: bool = False
    nearby: float = float("nan")
    refine_sharp: float = float("nan")
    reinitialised: bool = False
    reasons: tuple = ()
    state: str = ""


class ParticleFilter:
    """The stepper (module docstring).

    Parameters
    ----------
    config : FilterConfig (or TrackerConfig)
    model : ObservationModel (a likelihood backend, or a CompositeObservation of several)
    rng : np.random.Generator, the only source of randomness
    """

    def __init__(self, config: FilterConfig, model: ObservationModel, rng: np.random.Generator):
        if config.sampling not in SAMPLING_MODES:
            raise ValueError(f"unknown sampling {config.sampling!r}; valid: {', '.join(SAMPLING_MODES)}")
        rs.check_scheme(config.resampling)
        self.config = config
        self.model = model
        self.rng = rng
        self.state: ParticleState | None = None
        self._first_stamp: float | None = None
        self._last_stamp: float | None = None
        self._last_pose_stamp: float | None = None
        self._last_estimate: PoseEstimate | None = None
        t = config.status
        self.motion_gate = MotionGate(t.motion_window_s, t.uncertain_speed)   # the tracker sets its points_bone
        # the motion test on the filter's mean can fire only with a finite speed or a settle time; with the
        # refinement the tracker switches both off (its own test reads its output pose, tracker._filter_config)
        self._motion_test = math.isfinite(t.uncertain_speed) or t.settle_s > 0

    # -- initialisation ---------------------------------------------------------------------
    def initialise(self, T_base_bone: np.ndarray, sigma_p: float | None = None,
                   sigma_r: float | None = None) -> None:
        """Particles around a coarse pose (defaults: config.init_sigma_p / init_sigma_r)."""
        c = self.config
        self.set_state(motion.initialise(T_base_bone, c.particles, c.init_sigma_p if sigma_p is None else sigma_p,
                                         c.init_sigma_r if sigma_r is None else sigma_r, self.rng))

    def set_state(self, state: ParticleState) -> None:
        """Start from a given particle set (e.g. the single-point SMC initialiser's result)."""
        self.state = state
        self._first_stamp = None
        self._last_stamp = None
        self._last_pose_stamp = None
        self.motion_gate.reset()
        self._last_estimate = None

    def shift_to(self, T_base_bone_new: np.ndarray, T_base_bone_old: np.ndarray) -> None:
        """Move the whole cloud rigidly by Δ = T_new T_old⁻¹ (T_j ← Δ T_j): a particle at T_old lands on
        T_new and the cloud keeps its shape about it (the refinement's feedback, refine_track.py).
        Velocities and weights are kept; the last estimate becomes T_new."""
        delta = T_base_bone_new @ se3.inverse(T_base_bone_old)
        poses = delta @ self.state.poses()
        self.state = replace(self.state, p=poses[:, :3, 3].copy(), q=from_matrix_runs(poses[:, :3, :3]))
        if self._last_estimate is not None:
            self._last_estimate = replace(self._last_estimate, T_base_bone=np.array(T_base_bone_new, float))

    # -- stages -----------------------------------------------------------------------------
    def _dt(self, stamp: float) -> float:
        if not np.isfinite(stamp):
            raise ValueError(f"frame stamp must be finite, got {stamp}")
        if self._last_stamp is None:
            return self.config.first_dt
        dt = stamp - self._last_stamp
        if dt <= 0:
            log.warning("non-increasing frame stamp (%.6f after %.6f): predicting with dt = 0", stamp, self._last_stamp)
            return 0.0
        return dt

    def _weigh(self, T_camera_base: np.ndarray, depth: np.ndarray, timings: dict) -> tuple[float, int]:
        """lw += log p(z | x) (non-finite values as -inf, counted: observation.finite_log_likelihood);
        returns (max finite log-likelihood, non-finite count)."""
        t = time.perf_counter()
        log_lik = self.model.log_likelihood(T_camera_base @ self.state.poses(), depth)
        t = _tick(timings, "likelihood", t)
        log_lik, n_nan = finite_log_likelihood(log_lik)
        finite = log_lik[np.isfinite(log_lik)]
        ll_max = float(finite.max()) if finite.size else float("nan")
        lw = self.state.lw + log_lik
        lse = lw_ops.log_sum_exp(lw)
        if lse == -np.inf:
            log.warning("every particle weight is zero after weighing: weights reset to uniform")
            lw = lw_ops.uniform_log_weights(len(lw))
            lse = lw_ops.log_sum_exp(lw)
        self.state.lw = lw - lse            # lw_ops.normalise_log_weights, its LSE computed once
        _tick(timings, "weight", t)
        return ll_max, n_nan

    def _maybe_resample(self, timings: dict, ess: float) -> bool:
        """Resample when ``ess`` (of the current weights) is below the threshold."""
        t = time.perf_counter()
        resampled = ess < self.config.resample_threshold * self.state.n
        if resampled:
            self.state = self.state.take(rs.resample(self.config.resampling, self.state.lw, self.rng))
        _tick(timings, "resample", t)
        return resampled

    def _predict(self, block: str, dt: float, timings: dict) -> None:
        """Predict ``dt`` seconds in sub-steps of at most one nominal frame (``first_dt``).

        The motion parameters are per frame (λ_v decays the velocity once per step, the noise is
        drawn once per step), so a gap of k frames is k steps: a 300 ms camera dropout spreads
        the cloud by about a centimetre instead of the ΔT²/2 σ_a ≈ 9 cm of one 300 ms step.
        """
        t = time.perf_counter()
        fn = {"joint": motion.predict, "position": motion.predict_position,
              "orientation": motion.predict_orientation}[block]
        n = substeps(dt, self.config.first_dt)
        for _ in range(n):
            self.state = fn(self.state, dt / n, self.config.motion, self.rng)
        _tick(timings, "predict", t)

    # -- one frame --------------------------------------------------------------------------
    def step(self, depth_meas: np.ndarray | None, stamp: float, T_base_camera: np.ndarray | None) -> FilterOutput:
        """Process one frame (module docstring): clock, gate, update (weigh / hold / predict),
        estimate, evidence, status.

        Parameters
        ----------
        depth_meas : (h, w) float32 metres at the model's resolution (0 / non-finite invalid), or None
        stamp : s, the frame's time stamp
        T_base_camera : (4, 4) camera pose in the base frame at the stamp, or None when unknown
        """
        if self.state is None:
            raise RuntimeError("ParticleFilter.step needs particles: call initialise(T_base_bone) or set_state() first")
        timings = dict.fromkeys(STAGES, 0.0)
        dt = self._advance_clock(stamp, T_base_camera)
        T_camera_base = se3.inverse(T_base_camera) if T_base_camera is not None else None
        weighed, hidden = self._gate(depth_meas, T_camera_base)
        if weighed:
            update = self._weigh_blocks(depth_meas, T_camera_base, dt, timings)
        elif hidden:
            update = _Update(ess=lw_ops.ess(self.state.lw))      # hold the particles where they are
        else:
            self._predict("joint", dt, timings)
            update = _Update(ess=lw_ops.ess(self.state.lw))
        t = time.perf_counter()
        pose = update.pose if update.pose is not None else estimate(self.state.p, self.state.q, self.state.lw)
        self._last_estimate = pose
        evidence = self._evidence(pose, depth_meas, T_camera_base) if weighed else NO_EVIDENCE
        status, reasons = self._status(pose, update, evidence, depth_meas, stamp, weighed)
        _tick(timings, "estimate", t)
        return FilterOutput(
            T_base_bone=pose.T_base_bone, position_spread=pose.position_spread, rotation_spread=pose.rotation_spread,
            ess=update.ess, ess_ratio=update.ess / self.state.n, log_likelihood_max=update.ll_max, status=status,
            inlier_fraction=evidence.inlier_fraction, covered_pixels=evidence.covered_pixels, n_nan=update.n_nan,
            resampled=update.resampled, dt=dt, weighed=weighed, timings=timings, reasons=tuple(reasons),
        )

    def _advance_clock(self, stamp: float, T_base_camera: np.ndarray | None) -> float:
        """ΔT of this frame; remembers the stamp (and the last stamp with a camera pose)."""
        dt = self._dt(stamp)
        self._last_stamp = stamp
        if self._first_stamp is None:
            self._first_stamp = stamp
        if T_base_camera is not None:
            self._last_pose_stamp = stamp
        return dt

    def _gate(self, depth_meas: np.ndarray | None, T_camera_base: np.ndarray | None) -> tuple[bool, bool]:
        """(weighed, hidden): weigh when there is a camera pose and a measurement, unless occluders
        hide the last estimate (the occlusion hold of the module docstring)."""
        if T_camera_base is None or depth_meas is None or not self.model.has_measurement(depth_meas):
            return False, False
        hidden = self._last_estimate is not None and self._evidence(
            self._last_estimate, depth_meas, T_camera_base).bone_hidden
        return not hidden, hidden

    def _weigh_blocks(self, depth_meas: np.ndarray, T_camera_base: np.ndarray, dt: float, timings: dict) -> _Update:
        """predict → weigh → [resample] per block ('joint', or position then orientation); the
        estimate is taken after the last weighing, before its resampling."""
        blocks = ("joint",) if self.config.sampling == "joint" else ("position", "orientation")
        update = _Update(ess=float(self.state.n))
        for i, block in enumerate(blocks):
            self._predict(block, dt, timings)
            update.ll_max, n_nan = self._weigh(T_camera_base, depth_meas, timings)
            update.n_nan += n_nan
            update.ess = lw_ops.ess(self.state.lw)
            if i == len(blocks) - 1:
                t = time.perf_counter()
                update.pose = estimate(self.state.p, self.state.q, self.state.lw)
                _tick(timings, "estimate", t)
            update.resampled |= self._maybe_resample(timings, update.ess)
        return update

    def _evidence(self, pose: PoseEstimate, depth_meas: np.ndarray, T_camera_base: np.ndarray) -> Evidence:
        """The observation model's evidence about ``pose`` in this frame (covered pixels, inliers, hidden)."""
        T_camera_bone = T_camera_base @ pose.T_base_bone
        return self.model.evidence(T_camera_bone, depth_meas, self.config.status.min_covered_pixels)

    def _status(self, pose: PoseEstimate, update: _Update, evidence: Evidence, depth_meas: np.ndarray | None,
                stamp: float, weighed: bool) -> tuple[TrackingStatus, list]:
        """(status, reasons): the status rules (app/filter/status.py) with the motion gate's speeds."""
        since = self._last_pose_stamp if self._last_pose_stamp is not None else self._first_stamp
        speed, since_motion = (self.motion_gate.update(stamp, pose.T_base_bone) if self._motion_test
                               else (0.0, math.inf))                       # the test is off: nothing to measure
        return verdict(StatusInputs(
            position_spread=pose.position_spread, rotation_spread=pose.rotation_spread,
            ess_ratio=update.ess / self.state.n, inlier_fraction=evidence.inlier_fraction,
            covered_pixels=evidence.covered_pixels,
            n_nan=update.n_nan, n_particles=self.state.n, weighed=weighed, seconds_without_pose=stamp - since,
            speed=speed, seconds_since_motion=since_motion,
            template_spread=template_spread(self.state.p, self.state.q, self.state.lw, self.motion_gate.points_bone,
                                            pose, self.config.status.lost_spread, self.motion_gate.reach),
        ), self.config.status)


NO_EVIDENCE = Evidence(covered_pixels=0, inliers=0, bone_hidden=False)   # a frame that was not weighed


@dataclass
class _Update:
    """What the frame's update stage reports: ESS after the last weighing (or of the held / predicted
    weights), max finite log-likelihood, non-finite count, whether it resampled, and the estimate
    taken before resampling (None: take it from the particles as they are)."""

    ess: float
    ll_max: float = float("nan")
    n_nan: int = 0
    resampled: bool = False
    pose: PoseEstimate | None = None


MAX_SUBSTEPS = 90


def substeps(dt: float, nominal: float) -> int:
    """Number of prediction sub-steps for a gap of ``dt`` s at a nominal frame time (>= 1, <= 90)."""
    if dt <= 0 or nominal <= 0:
        return 1
    return int(min(max(1, np.ceil(dt / nominal - 1e-6)), MAX_SUBSTEPS))


def from_matrix_runs(R: np.ndarray) -> np.ndarray:
    """quat.from_matrix(R) of (N, 3, 3) rotations, computed once per run of consecutive matrices equal
    bit for bit: the same (N, 4) values to the bit, since from_matrix takes each matrix alone
    (elementwise arithmetic and one LAPACK eigh per matrix; tests/test_estimate_fast.py).

    :meth:`ParticleFilter.shift_to` converts the whole cloud after every feedback, and the cloud it
    shifts was just resampled (systematic: an ancestor's copies side by side), so most rows repeat
    the one before: on crest_left_02 with 1,000 particles about 210 runs (BENCHMARKS.md "Filter
    rate and CPU"); the batched eigh was 1 ms of the frame.
    """
    R = np.ascontiguousarray(R, dtype=float)
    n = len(R)
    if n < 2:
        return quat.from_matrix(R)
    bits = R.reshape(n, 9).view(np.uint64)
    new = np.empty(n, dtype=bool)
    new[0] = True
    np.any(bits[1:] != bits[:-1], axis=1, out=new[1:])
    starts = np.flatnonzero(new)
    if len(starts) == n:
        return quat.from_matrix(R)
    return quat.from_matrix(R[starts])[np.cumsum(new) - 1]


def _tick(timings: dict, stage: str, t0: float) -> float:
    t1 = time.perf_counter()
    timings[stage] += t1 - t0
    return t1
