"""Tracking status ok / uncertain / lost, from the filter's own evidence.

Since issue 32 every rule that fires is returned as a :class:`Reason` (its text and a code of
app/tracking/reasons.py), written per frame to status.csv and rerun, and counted in the summaries.
The filter's own shares fitted to one simulator are gone (issue 32: the inlier share
``uncertain_inlier_fraction`` 0.7, the image share ``min_ok_fraction`` 1.2 % and the off-by-default
``min_ess_ratio``; app/config.py ``RENAMED``): ok needs the refinement's tests below, which measure the
noise in the image they judge (app/tracking/fit_test.py), and without the refinement
(``refine.enabled: false``) no frame is ok (app/pipeline/tracker.py ``_unrefined``: the
template's error is not predicted). The motion rule reads the tracker's output pose
(``DepthTracker._steady``).

Import as ``from app.filter import status``. The projector must never show a confident template on
a lost track (DESIGN.md "Output"), so the rules err towards caution. The status is per frame (it
does not latch): a track that regains evidence returns to ok.

Inputs (:class:`StatusInputs`): the particle spread (position m, rotation rad,
:mod:`app.filter.estimate`), the ESS ratio, the fraction of the estimate's rendered pixels with a
valid measurement that are inliers (|z - z*| < 3 σ(z*), :func:`app.filter.likelihood_ref.inlier_mask`,
computed by the caller), the number of those pixels, the number of NaN log-likelihoods this frame,
the seconds since the last frame with a camera pose, and whether this frame was weighed.

Rules, first match wins (defaults in :class:`StatusThresholds`):

LOST if
- no camera pose for more than ``lost_no_pose_s`` = 1 s (the robot's data stopped): the lifecycle's patience
  with a track that is not ok, ``recovery.after_uncertain_s`` (:class:`app.config.TrackerConfig` ties them;
  issue 32: it was its own key, ``status.lost_no_pose_s`` = 0.5 s, our choice, not measured), or
- the template's points spread over the particles by more than ``lost_spread`` = 5 mm (RMS, the largest over
  the points; :func:`app.filter.estimate.template_spread`): ``refine.competitor_distance``, the distance at
  which two poses are two answers, so the cloud holds no one answer (:class:`app.config.TrackerConfig` ties
  them; issue 32: it was its own key, 10 mm, the replay's lost frame ADD > 10 mm; before, 10 mm of the bone
  frame's origin or 10 deg), or
- every likelihood was NaN (n_nan >= n_particles), or
- the frame was weighed, the estimate covers at least ``min_covered_pixels`` valid pixels and
  fewer than ``lost_inlier_fraction`` = 20 % of them are inliers (the bone is not where we think:
  a full occlusion, or a lost track).
UNCERTAIN if
- the frame had no camera pose or no valid depth (prediction only), or
- fewer than ``min_covered_pixels`` = 30 covered valid pixels (the bone left the view or is
  hidden behind invalid pixels: too little evidence, at 80x60 the crest covers a few hundred), or
- any NaN log-likelihood, or
- the bone is moving: the largest speed of the template's points over ``motion_window_s`` = 0.2 s exceeds
  ``uncertain_speed`` = 30 mm/s (one speed since issue 32; it was 30 mm/s of the bone frame's origin or
  ``uncertain_angular_speed`` = 20 deg/s), or it did so less than
  ``settle_s`` = 0.3 s ago (:mod:`app.filter.motion_gate`: the estimate lags a moving bone, and
  along the crest's length the image hardly shows it; measured on or_fast_reposition).
OK otherwise.

The particles' spread only makes a frame lost (5 mm of the template's points: two answers apart, so the cloud
holds none; 10 mm, the replay's lost frame ADD > 10 mm, until issue 32's merge 10); a spread of a few millimetres no longer lowers an otherwise
ok frame (issue 32: the template's predicted error from the refined fit says how precise the output is;
``status.uncertain_position_spread`` / ``uncertain_rotation_spread`` are now ``refine.feedback_spread`` /
``feedback_spread_angle``, the cloud's convergence the feedback waits for). The lost inlier fraction comes from a synthetic
run (default crest mesh at 0.42 m, 80x60, 0.5 mm noise): 0.46-0.50 with the estimate 16 mm / 9°
off, 0.84-1.0 once converged.

Occluders: a pixel measured more than ``likelihood.occluder_margin`` = 20 mm in front of the estimate's
rendered depth sees a hand or an instrument over the bone: it neither confirms nor contradicts the
pose, so it is left out of both the inlier fraction and the covered-pixel count (the caller,
:meth:`app.filter.particle_filter.ParticleFilter._inliers`, applies the margin). A hand over 80 %
of the bone therefore leaves the status to the remaining 20 % (ok if they fit and are enough),
and a full occlusion leaves too few pixels: uncertain, never ok. Misfits of a wrong pose (soft
tissue, the table or the bone itself a few millimetres off the rendered surface) stay in.

With the refinement (``refine.enabled``, the default; app/filter/refine.py, refine_track.py,
combined by :func:`with_refinement` in app/pipeline/tracker.py): the filter's status above is
lowered to UNCERTAIN, never raised, when

- the refined fit confirms less than ``min_fitness`` = 0.6 of the bone's expected visible surface
  (the silhouette's pixels, occluders left out, whose measurement lies within 3 σ(z) of the refined
  model), or the frame was not refined (issue 12: on fifteen held-out scenes a fit below ~0.6
  flagged two thirds of the frames > 5 mm off without flagging a good frame; on the eight CT
  crests at 0.42 m the truth confirms 0.83-0.85, BENCHMARKS.md §6); the buried part of the bone
  is therefore not evidence against a pose, it only lowers what can be confirmed: a crest standing
  a few millimetres out of the tissue is never ok;
- the largest predicted standard deviation of the template's points, from the refinement's
  information matrix (Σ = ``covariance_inflation`` H⁻¹, inflated for correlated pixels and model
  error), exceeds ``max_template_std`` = 1 mm, the clinical tolerance (DESIGN.md): too little of
  the bone is seen to place the template. The points are the plan's template points when the tracker
  is given a plan (replay with its projector plan, a session with a projector output), else 300 of
  the mesh's vertices, a conservative bound (the summary's ``template_points`` says which). The inflation, 6, is calibrated against the measured
  error of 300 mesh vertices (scripts/template_coverage.py, BENCHMARKS.md §6: 1,521 refined frames of
  eleven trials, eight crests): the predicted bound covers the measured worst-point error on 90 %
  of the frames with inflation 2.9 on clear views at 0.42 m and 5.3 under a hand rising to 80 %;
  at 0.65 m the error was then mostly a bias (1.4-3.3x the predicted std) that 12.7 would have been
  needed for; since the far view is refined at stride 1 on a full-resolution z-buffer (BENCHMARKS.md
  §6d: 720 frames of the eight crests at 0.65 m) 5.8 covers 90 % there and 6 covers 91 %, the
  worst-point error median 0.35 mm, the bound 0.45-0.7 mm; on two clear trials at 0.42 m 0.9
  suffices now (6 is conservative there). It measures
  precision, not wrongness (issue 12: the smallest eigenvalue of H did not separate wrong from
  right poses at all);
- a competing pose explains the image about as well: the refinements from the own track and from
  the filter's estimate converged more than ``refine.competitor_distance`` = 5 mm of the template apart
  with their shares within 1 σ less than ``refine.nearby_margin`` sqrt(f) apart (one margin since issue 32;
  it was ``competitor_margin`` = 0.05: 0.015 changed none of 48 status runs; tests/test_refine_status.py
  builds such a frame).
- a pose near the track explains the image better: every ``refine.nearby_every`` = 10 frames
  the track refines from ``refine.nearby_starts`` = 4 poses drawn 2 mm / 2 deg about its pose, and a fit
  that moves the template by more than ``max_template_std`` = 1 mm (its largest point displacement)
  while its share within 1 σ less its excess behind exceeds the track's own by ``nearby_margin`` = 0.015
  keeps the status below ok until the next search finds none (app/filter/nearby_search.py
  ``NearbySearch``; its follow-ups about a better fit within 1 mm, §6k, were removed in issue 32: since
  the correlation correction and the validation their scene, crest_left_02 under residual tissue, is
  never ok while > 1 mm off without them). A 1 mm template error is the clinical tolerance;
  the 5 mm / 5 deg competitor above cannot see such a pose. Measured (BENCHMARKS.md §6j, 40 trials of the eight CT crests, the
  frames every other rule left ok, every 5th frame searched): as shipped it fired on 10 of the 15
  residual-tissue frames > 1 mm off and on 137 of the 145 nearer ones (their minimum is a plateau:
  the image does not place the template within 1 mm), on 0 of 416 static_clear, 416 static_far and
  222 static_occluded frames. Asking only "at least as well" (margin 0) held clean runs of the full
  matrix below ok for 16-60 frames (ties of a flat right minimum, +0.000 to +0.006); "about as well"
  (within 0.02) fired on 57 of the clean probe frames. Chosen on these frames: a hint; the matrix
  with the shipped rule is in §6j.
- more of the refined fit's measurements lie more than 1 σ *inside* the model (signed
  point-to-plane residual < −σ, app/filter/refine.py step 7) than the image's noise explains, by more
  than ``max_behind_excess`` = 0.2 % of them. Tissue, blood and instruments only ever lie in front
  of the bone, so a right pose leaves only the noise's tail behind it; a fit pulled part-way onto
  residual tissue, or slid along the crest under a hand, passes through the seen surface elsewhere.
  The noise's share is not a fixed number: σ_n is estimated on the fitted surface itself (the
  robust scale of the residuals' rough part behind the model, app/tracking/fit_test.py; issue 32:
  the former estimate, the second difference along the image's rows, halved the noise of a stereo
  camera whose noise is correlated over its matching window, and the rule then blocked right poses
  on 99.8 % of the frames), each measurement lies behind with probability
  e_i = Φ(−σ_i / (σ_n |n_i·r̂_i|)), and the bound is the Poisson-binomial mean plus
  z = 3 standard deviations (one-sided ``status.alpha`` = 0.135 %, app/tracking/levels.py) over the M measurements, the variance multiplied by
  the residuals' spatial correlation factor f = n / n_eff (fit_test.py; behind_noise.py
  ``behind_bound``; app/filter/refine_track.py ``behind_excess``; when fewer than 30 residuals behind the
  model estimate the noise, the test cannot run and the frame is not ok: issue 32 removed the fixed 2 % it fell back to). The 0.2 % margin covers what the noise model leaves out (the mesh's
  discretisation, the association): a right pose's share exceeds the bound by up to ~0.3 points.
  Measured (BENCHMARKS.md §6d, scripts/refine_evidence.py --analyse; the frames otherwise ok-able
  after 0.5 s; the margin was chosen on these same frames: a hint, not a held-out figure): with
  margin 0 / 0.2 / 0.3 / 0.5 %, static_clear (8 crests, 0.42 m) declined 88 / 7 / 2 / 0 of 1,768
  frames, static_far (8 crests x 3 seeds, 0.65 m) 28 / 2 / 0 / 0 of 2,119, and or_deep_tissue fits
  1.1-2.3 mm off were left ok while > 1 mm off in 0 / 1 / 5 / 29 of 712 frames (the fixed 2 % share
  of before: 16 on the same trials, 14 of them on crest_right_02). At 0.65 m the fixed share had
  declined right poses on most crests (their tail is 1-2 % there: ok on 0-64 % of the frames after
  1 s); the bound follows the depth's noise instead (ok on 97-100 %).
  The excess is also tested over the track's last ``refine.behind_frames`` = 30 fits together
  (app/filter/behind_pool.py: their counts, means and variances add, so the bound's share shrinks as
  1/sqrt(30)), and the larger of the two is compared. Why: with the refinement's tissue border
  (app/filter/refine.py step 5) a fit no longer slides onto residual tissue, but under it the track
  can sit in a minimum 1.3-1.8 mm / 2 deg off whose share behind is about its frame's own bound, every
  frame (crest_right_02 or_deep_tissue: 0.55 % against 0.59 %): one frame cannot tell it from chance,
  thirty can. Measured (BENCHMARKS.md §6i, 8 crests x 3 seeds).
- the static-bone prior (app/filter/static_prior.py) kept a pose that this frame's own fit contradicts:
  its Δχ² = δᵀ (H / ``covariance_inflation``) δ from the kept pose to the image's fit exceeds
  χ²₆(1 − ``status.alpha``) / ``covariance_inflation`` = 3.62 (it was ``max_held_chi2`` = 4, P ~ 5e-4, until
  issue 32 gave every statistical test one level) and the prior did not release onto the fit. Under the image's own inflated
  covariance Δχ² is χ²₆ / 6 (app/tracking/levels.py ``held_level``); the prior itself releases only at 25
  (``refine.prior_release_chi2``; 4 there was tried and not kept, static_prior.py). Why: a bone
  that starts to move slowly (bone_moves: 0.7 mm/s rising to 10 mm/s over 0.2 s) is fused, not
  released, for ~10 frames, and the held pose lagged it by up to 1.0-1.3 mm while every other rule
  said ok; the projected outline landed 1.5-3.2 mm off on the bone (33 mm where a ray slid off the
  ridge). Measured (BENCHMARKS.md §6f, five trials of four crests, release at 25): on ok frames at
  rest Δχ² was at most 1.08 (medians 0.1-0.24); on the lagging frames with ADD > 0.5 mm 3.0-25.

Caveat: with a peaked likelihood (hundreds of pixels, ESS / N near 1/N) the weighted spread of a
degenerate particle set is near zero even when the estimate is off; the inlier rules are what
catches a wrong estimate then. The pixel-count regularisation (likelihood.pixel_count_reg) makes
the weights, and so the spread, more informative.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from app.tracking import levels

LOST_NO_POSE_S = 1.0                 # recovery.after_uncertain_s's default: TrackerConfig ties them (issue 32)
LOST_SPREAD_M = 0.005                 # refine.competitor_distance's default: TrackerConfig ties them (issue 32)
LOST_INLIER_FRACTION = 0.2
MIN_COVERED_PIXELS = 30
UNCERTAIN_SPEED_M_S = 0.03
MOTION_WINDOW_S = 0.2
SETTLE_S = 0.3
MIN_FITNESS = 0.6
MAX_BEHIND_EXCESS = 0.002
MAX_TEMPLATE_STD_M = 0.001
COVARIANCE_INFLATION = 6.0


class TrackingStatus(enum.StrEnum):
    """The status shown to the surgeon; compares equal to its string value ('ok', ...)."""

    OK = "ok"
    UNCERTAIN = "uncertain"
    LOST = "lost"


class Reason(str):
    """One rule that lowered a frame's status: its text (a str, for people and logs) and its ``code``
    (app/tracking/reasons.py's table: the column written to status.csv and the summaries' shares)."""

    code: str

    def __new__(cls, code: str, text: str):
        obj = super().__new__(cls, text)
        obj.code = code
        return obj

    def __getnewargs__(self):
        return self.code, str(self)


def codes(reasons) -> tuple[str, ...]:
    """The distinct reason codes of ``reasons`` (Reason or plain str: 'other'), in first-seen order."""
    out: list[str] = []
    for r in reasons:
        code = getattr(r, "code", "other")
        if code not in out:
            out.append(code)
    return tuple(out)


@dataclass
class StatusThresholds:
    """Thresholds of the rules in the module docstring (metres, radians, seconds, fractions).

    ``lost_no_pose_s`` and ``lost_spread`` are not keys of their own: :class:`app.config.TrackerConfig` sets
    them to ``recovery.after_uncertain_s`` (one patience with a track that is not ok) and
    ``refine.competitor_distance`` (one distance between two answers; issue 32)."""

    lost_no_pose_s: float = LOST_NO_POSE_S
    lost_spread: float = LOST_SPREAD_M
    lost_inlier_fraction: float = LOST_INLIER_FRACTION
    min_covered_pixels: int = MIN_COVERED_PIXELS
    uncertain_speed: float = UNCERTAIN_SPEED_M_S
    motion_window_s: float = MOTION_WINDOW_S
    settle_s: float = SETTLE_S
    min_fitness: float = MIN_FITNESS
    max_behind_excess: float = MAX_BEHIND_EXCESS
    max_template_std: float = MAX_TEMPLATE_STD_M
    alpha: float = levels.ALPHA
    covariance_inflation: float = COVARIANCE_INFLATION


@dataclass
class StatusInputs:
    """What the classifier looks at (module docstring).

    position_spread : m; rotation_spread : rad; ess_ratio : ESS / N in (0, 1]
    inlier_fraction : inliers / covered valid pixels of the estimate (NaN when none)
    covered_pixels : the estimate's covered pixels with a valid measurement (occluders left out)
    n_nan : NaN log-likelihoods this frame; n_particles : N
    weighed : the frame had a camera pose and depth and was weighed
    seconds_without_pose : since the last frame that had a camera pose (0 when this one has)
    speed (m/s, the template's fastest point), seconds_since_motion (s): the estimate's motion
    (:mod:`app.filter.motion_gate`)
    template_spread : m, the template's points' spread over the particles (:func:`app.filter.estimate.template_spread`;
    NaN, unknown, is lost)
    """

    position_spread: float
    rotation_spread: float
    ess_ratio: float
    inlier_fraction: float
    covered_pixels: int
    n_nan: int
    n_particles: int
    weighed: bool
    seconds_without_pose: float
    speed: float = 0.0
    seconds_since_motion: float = math.inf
    template_spread: float = math.nan


def lost_reasons(s: StatusInputs, t: StatusThresholds) -> list[str]:
    """The LOST rules that fire (empty when none)."""
    reasons = []
    if s.seconds_without_pose > t.lost_no_pose_s:
        reasons.append(Reason("no_pose", f"no camera pose for {s.seconds_without_pose:.2f} s"))
    if not s.template_spread <= t.lost_spread:
        reasons.append(Reason("spread", f"the template's points spread {1e3 * s.template_spread:.1f} mm over the particles"))
    if s.n_particles > 0 and s.n_nan >= s.n_particles:
        reasons.append(Reason("nan", "every log-likelihood was NaN"))
    if s.weighed and s.covered_pixels >= t.min_covered_pixels and s.inlier_fraction < t.lost_inlier_fraction:
        reasons.append(Reason("misfit", f"inlier fraction {s.inlier_fraction:.2f}"))
    return reasons


def uncertain_reasons(s: StatusInputs, t: StatusThresholds) -> list[str]:
    """The UNCERTAIN rules that fire (empty when none)."""
    reasons = []
    if not s.weighed:
        reasons.append(Reason("not_weighed", "not weighed (no camera pose, no valid depth, or the bone hidden by an occluder)"))
    if s.weighed and s.covered_pixels < t.min_covered_pixels:
        reasons.append(Reason("unseen", f"{s.covered_pixels} covered valid pixels"))
    if s.n_nan > 0:
        reasons.append(Reason("nan", f"{s.n_nan} NaN log-likelihoods"))
    motion = motion_reason(s.speed, s.seconds_since_motion, t)
    if motion is not None:
        reasons.append(motion)
    return reasons


def motion_reason(speed: float, seconds_since_motion: float, t: StatusThresholds) -> Reason | None:
    """The steady test (app/filter/motion_gate.py's speed): the template's points moving faster than
    ``uncertain_speed`` (m/s), or less than ``settle_s`` since they did or since the start; None when still."""
    if speed > t.uncertain_speed:
        return Reason("moving", f"bone moving (the template at {1e3 * speed:.0f} mm/s)")
    if seconds_since_motion < t.settle_s:
        return Reason("moving", f"bone settling ({seconds_since_motion:.2f} s after moving or the start)")
    return None


@dataclass
class RefinementEvidence:
    """The local refinement's evidence (app/filter/refine_track.py) for :func:`with_refinement`.

    fitness : share of the bone's expected visible surface confirmed (NaN when not refined);
    template_std : m, largest predicted std of the template's points (inf when not refined);
    competitor : a pose > 5 mm / 5 deg away explains the image about as well;
    behind : share of the measurements lying more than 1 σ inside the refined model in excess of the
    share the image's noise explains (app/filter/refine_track.py ``behind_excess``; NaN: unknown);
    held_chi2 : the static prior's Δχ² from the pose it kept (held or fused) to this frame's own fit,
    when it did not release onto that fit (app/filter/static_prior.py; 0 when released, NaN without it);
    nearby : m, the template gap to a fit near the track that explains the image better
    (app/filter/nearby_search.py ``NearbySearch``; NaN when the last search found none);
    nearby_unanswered : the track's first nearby search has not finished (its work spread over frames,
    ``refine.nearby_per_frame``): whether a pose near the new track explains the image better is not
    known yet (inline, no frame of a track was ok before its first search had answered).
    """

    fitness: float
    template_std: float
    competitor: bool
    behind: float = float("nan")
    held_chi2: float = float("nan")
    nearby: float = float("nan")
    nearby_unanswered: bool = False


def refinement_reasons(r: RefinementEvidence, t: StatusThresholds) -> list[str]:
    """The refinement's UNCERTAIN rules that fire (module docstring, "With the refinement")."""
    reasons = []
    if not np.isfinite(r.fitness):
        reasons.append(Reason("not_refined", "the frame was not refined"))
    elif not r.fitness >= t.min_fitness:
        reasons.append(Reason("unconfirmed", f"refined fit {r.fitness:.2f} < {t.min_fitness:.2f} of the visible bone confirmed"))
    if not r.template_std <= t.max_template_std:
        reasons.append(Reason("imprecise", f"predicted template error {1e3 * r.template_std:.2f} mm"))
    if r.competitor:
        reasons.append(Reason("ambiguous", "a competing pose explains the image about as well"))
    if r.nearby > 0.0:
        reasons.append(Reason("ambiguous", f"a pose moving the template {1e3 * r.nearby:.1f} mm explains the image better"))
    if r.behind > t.max_behind_excess:
        reasons.append(Reason("behind", f"{100 * r.behind:.1f} % more of the seen bone lies inside the refined model "
                              "than the noise explains (slid onto tissue?)"))
    elif np.isfinite(r.fitness) and not np.isfinite(r.behind):
        reasons.append(Reason("behind", "the consistency test could not run: too few of the fit's measurements "
                              "lie behind the model to measure the image's noise"))
    held = levels.held_level(t.alpha, t.covariance_inflation)
    if r.held_chi2 > held:
        reasons.append(Reason("held", f"the image's own fit contradicts the held pose (Δχ² {r.held_chi2:.1f} > "
                              f"{held:.2f}; the bone starting to move?)"))
    if r.nearby_unanswered:
        reasons.append(Reason("ambiguous", "the search for a better pose near the new track has not finished"))
    return reasons


def with_refinement(status: TrackingStatus, r: RefinementEvidence, t: StatusThresholds) -> TrackingStatus:
    """The filter's status combined with the refinement's: ok only when both say so; never raised."""
    if status != TrackingStatus.OK:
        return status
    return TrackingStatus.UNCERTAIN if refinement_reasons(r, t) else TrackingStatus.OK


def classify(s: StatusInputs, t: StatusThresholds | None = None) -> TrackingStatus:
    """OK / UNCERTAIN / LOST by the rules of the module docstring."""
    return verdict(s, t)[0]


def verdict(s: StatusInputs, t: StatusThresholds | None = None) -> tuple[TrackingStatus, list[Reason]]:
    """(status, reasons): :func:`classify` with the rules that decided it (the LOST rules when any
    fires, else the UNCERTAIN ones; none for OK)."""
    t = t or StatusThresholds()
    lost = lost_reasons(s, t)
    if lost:
        return TrackingStatus.LOST, lost
    uncertain = uncertain_reasons(s, t)
    if uncertain:
        return TrackingStatus.UNCERTAIN, uncertain
    return TrackingStatus.OK, []
