"""Automatic recovery of a lost track: when to re-initialise the filter, and around what.

**Where the mode lives.** The tracker's mode (a search due and its reason, a pose awaiting its
evidence, whether the track was ever ok) is the lifecycle's (app/tracking/lifecycle.py: explicit
states, one transition table); this policy owns it (:attr:`RecoveryPolicy.lifecycle`) and moves it
only by the table's events. The triggers below are the table's transitions into ``searching``, one
ordered table of named tests (app/tracking/triggers.py); this policy counts their evidence (the runs
of bad, not-ok, unseen, outside and below-bar frames) and the cooldown's backoff.

Import as ``from app.filter.recovery import RecoveryPolicy``. Run on the tracker's parts by
app/pipeline/recovery_runner.py in :class:`app.pipeline.tracker.DepthTracker` (issue 12, item 4), so
replay, ``osteonav track`` and the bench all get it (``recovery.enabled``, **on by default** since
the wide search: harmless on the eight CT crests, finds a moved bone; before it, re-spreads under a
hand lost tracks: BENCHMARKS.md §6b).

**Trigger.** A frame is *bad* when its status is lost, or (with the refinement on) it was weighed
and the refined fit no longer confirms the visible bone: not refined at all (refine_track.py kept no
fit confirming ``refine.keep_fitness``) or its fitness is below ``status.min_fitness`` (the status
rule's 0.6; a crest turned 90 deg on the synthetic trial of tests/test_recovery.py stayed refined at
a lower fit, uncertain, never lost). A weighed frame that is neither resets the count; a frame that
was not weighed and not lost (the bone hidden by a hand, no camera pose) neither counts nor resets:
the particles are held there (particle_filter.py), and the recovery waits for the bone to be
visible. After ``after_lost_s`` of bad frames in a row a re-initialisation is due. A second,
slower trigger: ``after_uncertain_s`` of weighed frames in a row that are not ok while the
estimate is still (0 = off): on the CT crests under a rising hand the filter and the refinement slid
together along the crest to 47 mm off with a fit of 0.65-0.9, uncertain (the predicted template
error), never lost (BENCHMARKS.md §6b). The estimate is still when it moved less than
``status.uncertain_speed`` (the template's fastest point; issue 32) over ``STILL_WINDOW_S`` = 0.5 s (longer
than the status's 0.2 s: a wrong track's refined pose jumps a few millimetres between frames, which
over 0.2 s read as motion and kept the count at 0 on crest_left_02 while 64-100 mm off); a moving
estimate restarts that count, and it needs an ok frame since the start (a track that was never ok,
e.g. or_deep_tissue, sits ~5 mm from the coarse start pose it converged from; measured: it fired 2-3
times there per run for nothing, BENCHMARKS.md §6b) unless the never-ok estimate lies outside the
start's own prior: farther than ``START_SIGMAS`` = 3.95 (χ²₃'s point at ``status.alpha``, 0.135 %, √15.6;
4.03, the 99.9 % point, before issue 32 gave every statistical test one level) times
``init.sigma_p`` / ``sigma_r`` from the start pose (or_coarse_start crest_left_03 seed 1 sat 45 mm /
80 deg off, uncertain, refined at a fit of 0.85, never searched; BENCHMARKS.md §6b). Such an
estimate is searched for after ``after_lost_s`` of weighed frames outside that prior in any case,
moving or not (or_coarse_start crest_left_04 seed 1 slid from 7 to 33 mm / 70 deg within 0.3 s,
which restarted the slow count, and was searched for 1.5 s later; BENCHMARKS.md §6e), until the
first re-initialisation: a pose the search found may rightly lie outside the start's prior (a bone
moved before it was ever ok), and its settling frames must not search again. A bone being
repositioned is uncertain for seconds (status.py's motion rule), and a re-spread around its pose
before the move would lose it. The low-fit and the slow trigger also need the estimate more than
FAR = 5 mm (``refine.competitor_distance``, the competitor gap: the template's largest displacement
between the two poses, :attr:`RecoveryPolicy.points_bone`; 5 mm / 5 deg of the bone frame's origin
before issue 32) from the last confident pose: under an 80 % hand a correct track is uncertain for seconds (the predicted template error),
and re-initialising it there raised crest_left_05's lost share from 1.6 to 16 %. It did not save
crest_right_04 / _05, whose tracks had been > 5 mm off for a moment (and came back by themselves
without recovery; BENCHMARKS.md §6b). A third: a weighed frame after at least ``after_lost_s`` of
frames not weighed (the estimate out of the image or hidden) while not ok and more than FAR
from the last confident pose: a bone moved out of view and back (or_fast_reposition) is searched for
as soon as it is seen again; the slow trigger took 1.5 s more there. The re-initialisation runs on
the next frame that has a camera pose and valid depth. A fourth, once: a track never ok since the start, still, weighed
and not ok for ``after_uncertain_s`` (1 s; the slow trigger's wait), before any re-initialisation or declined search, gets one
wide search, wherever it lies (or_coarse_start crest_left_02 seed 1 converged into a wrong minimum
11.9 mm off, fit 0.64, within the start's prior and 5 mm of the start; it escaped by chance at
0.65 s, and with the static prior's release at 4 (tried) sat there for the whole 4 s: found at
1.1 s with this rule. On or_deep_tissue it runs one search that finds nothing better:
7 of 8 crests, ADD within 0.12 mm of before, never ok; static_far seed 1: identical; BENCHMARKS.md §6f).
A fifth: SLIDING_FACTOR (2) times ``after_uncertain_s`` of weighed frames in a row not ok, more than
FAR from the last confident pose, moving or not (with the slow trigger's own condition:
an ok frame since the start, or outside the start's prior). A wrong track that slides over the
tissue at a good fit restarts the slow trigger's count with every move, and nothing else fired:
or_fast_reposition crest_left_03 seed 2 slid from 76 to 175 mm off over 5 s at a fit of 0.77-0.95,
never searched, never found again (BENCHMARKS.md §6g). A bone is repositioned in about a second
(or_fast_reposition 0.9 s, bone_moves 0.8 s); a search while it still moves is no harm: it keeps
the track unless it finds a pose that explains the image better (wide_search.py, 6). While the
track is a found or kept pose awaiting its confirmation ("Honesty" below) the factor is 1: such a
pose is a hypothesis, and one the rules have not found ok for ``after_uncertain_s`` is searched
again, moving or not (or_fast_reposition crest_left_05 seed 4: a search confirmed a pose 68 mm off
at a sharp share of 0.515 with a fifth of the crest in view, the rules never found it ok, and the
sliding trigger searched again 2 s later, which found the bone: 2.03 s after it was in view, 1.02 s
with the factor 1; BENCHMARKS.md §6m). Searching again costs only CPU there: a kept pose's
confirmation count under way goes on (:meth:`RecoveryPolicy.kept`).
A sixth: a found or kept pose awaiting its confirmation whose refined fit falls below the bar the
wide search found it by (``search_bar``, wide_search.MIN_SHARP: a consistent sharp share of 0.411, status.min_fitness at 1 σ;
the frame's best fit, kept or not) on ``after_lost_s`` of weighed frames in a row that the rules do
not find ok, far from the last ok pose: the search would not accept it on this image. On
or_fast_reposition crest_right_02 seed 3 at the filter's seed 1, a pose found 11 mm / 34 deg off at
0.502 with a third of the crest in view explained ~1,250 pixels of a silhouette that grew to
~4,150 as the rest came into view (a share of 0.30), and waited 1 s for the sliding trigger: found
2.52 s after the bone was in view, 2.02 s with this rule. Over the 48 fast repositions at three
filter seeds: 143 of 144 within 2 s (141 without it; BENCHMARKS.md §6n). It uses the cooldown's
backoff like the others.

**When.** A due attempt waits while the bone is mostly hidden: it runs only on a frame where at
least ``status.min_fitness`` (0.6) of the model's expected silhouette at the last confident pose is
not hidden by an occluder (:func:`app.filter.visibility.visible_share`: valid depth, not more than
the likelihood's ``occluder_margin`` in front of the model). A pose found on less could never be ok:
ok needs the refined fit to confirm that share of the expected surface (it was
``recovery.min_visible_share``, the same 0.6, until issue 32). Re-spreading while 80 % of the crest is
under the hand is what lost crest_right_04 and _05 in BENCHMARKS.md §6b: the filter and the
refinement settled on a wrong fit of the visible 20 %. An SMC attempt while the pointed point is
hidden (:func:`app.filter.visibility.point_visible`) is replaced by a re-spread (§6b: with the point
under the hand the SMC put crest_left_03 78-105 mm off with a fit of 0.95).

**What.** Attempts since the last ok frame are numbered k = 0, 1, ...; attempt k is

- a *re-spread* when k mod (``respreads`` + 1) < ``respreads``: the particles drawn around the last
  confident (ok) pose, wider than the start (``respread_sigma_p`` per axis; a rotation
  r ~ N(0, ``respread_sigma_r``² I) about the bone's centroid c in the base frame, so that
  p' = c + R(r)(p - c) + ε, q' = exp(r) ⊗ q: turning about the bone frame's origin, which need not
  lie on the bone, would throw the crest centimetres away); cheap: no extra likelihood evaluation.
  Not around the current estimate too: on crest_left_03 (static_occluded) half of the particles
  there kept a wrong pose 105 mm off alive, and the filter and the refinement went back to it
  after the re-spread had found the bone (0.2 mm);
- else (``search``, the default) the *wide search for a moved bone* (app/filter/wide_search.py):
  candidates from the image (where its height map stands out, the crest's ridge put there, turned
  about up) and from the track's recent not-lost estimates (:meth:`RecoveryPolicy.track_poses`: it
  followed part of the move), scored by the likelihood backend, searched locally and verified by
  the refinement; ``search_evaluations`` likelihood evaluations plus 28 refinements (work, never
  seconds). A found pose seeds the cloud (FOUND_SIGMA_M / FOUND_SIGMA_RAD about it) and the
  refinement's track (RefinedTrack.seed, which resets the static-bone prior: its held base-frame
  pose is where the bone WAS and must not drag the track back; the found pose is the search's
  verified fit, so the track's first frame refines it at width 0, not with the seed's wide steps,
  which slid a pose found 0.4 mm off to 16-26 deg off on or_fast_reposition crest_right_02 seed 3,
  BENCHMARKS.md §6o). A search that confirms nothing
  (the bone out of view) changes nothing and is no attempt (:meth:`RecoveryPolicy.declined`): it
  is retried every SEARCH_RETRY_S on weighed frames away from the last ok pose until a frame
  is ok or a search finds a pose, whether or not the trigger still holds (a wrong track sliding
  over the tissue restarts the slow trigger's count). A search whose best verified pose is the
  tracker's current estimate (refined in place; wide_search.py, 6) keeps the track
  (:meth:`RecoveryPolicy.kept`): no attempt, retried after the backed-off cooldown; the track moves
  only onto its own refined pose when its own fit is below the search's bar and that pose moves the
  template by more than status.max_template_std (app/pipeline/recovery_runner.py; 1 mm / 1 deg before issue 32:
  the search's wider chain left the local minimum the track's own refinement sat in;
  or_fast_reposition crest_left_05 seed 1 at the filter's seed 3, BENCHMARKS.md §6n) (a track
  0.8 mm off with a quarter of the crest in view was replaced by a pose 9 mm off that explained
  the image less well: or_fast_reposition crest_right_04 seed 0, BENCHMARKS.md §6g). Re-spreading around the last ok
  pose and the SMC from the trial's point prior both search where the bone was: on
  or_fast_reposition (12 cm / 45 deg) neither found it (BENCHMARKS.md §6);
- or, with ``search: false``, the *one-point SMC initialiser* (app/filter/smc_init/) around a point
  on the bone: the trial's / session's ``point_prior`` when given, else the last confident pose's
  surface point nearest the bone's centroid; its budget is ``smc_evaluations`` pose likelihood
  evaluations (work, never seconds).

Without any ok frame yet, the last confident pose is the start pose. After attempt k the next one
waits at least min(``after_lost_s`` · 2^k, ``after_uncertain_s``) (a scene that can never be tracked, e.g. a
crest buried in tissue, is not re-initialised every few frames; no retry waits longer than the slow
trigger's own wait for a track not ok; it was capped at 2^3 by ``recovery.max_backoff_doublings``
until issue 32). One reaction time since issue 32: the base was ``recovery.cooldown_s`` (0.16 s), now the
0.11 s of bad frames a re-initialisation waits for (the 48-run recovery matrix: every bone found within
2 s, none ok while more than 1 mm off; BENCHMARKS.md "Decision numbers"). A declined search is retried after
``status.settle_s`` (0.3 s), the time the motion test gives a bone to settle (issue 32, merge 11: it was
``search_retry_s``, 0.33 s; retrying after the cooldown's 0.16 s, one retry period for both, or both at
0.33 s found a moved bone later on 2 and 3 of the 8 fast repositions of BENCHMARKS.md "Decision numbers":
an earlier search on a partial view found a wrong pose). The slow trigger counts only
frames the rules do not find ok: a found pose awaiting its confirmation (below) is reported
uncertain, and counting those frames fired a re-spread at the old pose before it was confirmed.

**Honesty.** Right after a re-initialisation the status is at most uncertain for ``status.settle_s``
(0.3 s): the tracker restarts its motion test, and the estimate's jump is motion (app/pipeline/tracker.py;
until issue 32 a separate hold of ``recovery.hold_frames`` = 15 weighed frames did this); then the usual
rules (status.py, with the refinement's fit, predicted template error and competitor check) decide. That
alone was not enough: on crest_right_05 the wrong pose a re-spread settled on was ok in 81 frames after
the hold (BENCHMARKS.md §6b). So
after a re-initialisation a pose is ok only when it agrees with the last ok pose (within FAR: the
bone is usually static in the robot's base frame), or, away from it (the bone was
moved while hidden), after ``confirm_frames`` (90, ~1 s) weighed frames in a row that the rules
find ok: evidence, not a timer.

**Seconds and frames.** The triggers' and the cooldown's durations are seconds, counted in the
frames the tracker processes: a duration T is ``ceil(T / period)`` frames in a row, with ``period``
the median of the last PERIOD_FRAMES - 1 stamp differences of the frames the policy saw
(:class:`FramePeriod`; NOMINAL_PERIOD_S, the D415's 90 Hz, until two stamps are known). So a live
session that processes 30 frames/s fires after the same seconds as a 90 Hz replay, where counting
frames waited 3x as long (1 s became 3 s; ``after_uncertain_frames`` before 2026-11-24), and a
camera dropout (one long gap) does not count as many frames. ``confirm_frames`` stays a count: it asks
for evidence (weighed frames the rules judge), which a slower rate gives more slowly; the wait grows with
it, on the safe side.

Each re-initialisation is recorded as (stamp, kind, reason); :meth:`RecoveryPolicy.report` gives
them for the summaries.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from app import metrics
from app.filter.motion import ParticleState, draws_about_centroid
from app.filter.motion_gate import template_speed
from app.filter.refine_track import RefineConfig, pose_gap
from app.filter.status import SETTLE_S, TrackingStatus
from app.filter.weights import uniform_log_weights
from app.geometry import quaternion as quat
from app.tracking.lifecycle import Lifecycle, frame_event
from app.tracking.triggers import Evidence, first_trigger
from app.tracking import levels

RESPREAD, SMC, SEARCH = "respread", "smc", "search"
FOUND_SIGMA_M, FOUND_SIGMA_RAD = 0.003, math.radians(3.0)   # the cloud about a pose the wide search found
NOMINAL_PERIOD_S = 1.0 / 90.0        # the frame period until two stamps are known (the D415's 90 Hz, the trials')
SEARCH_RETRY_S = SETTLE_S            # s between two wide searches that found nothing: status.settle_s (TrackerConfig ties them; 0.33 s until issue 32)
PERIOD_FRAMES = 31                   # the period is the median of the last 30 stamp differences
TRACK_FRAMES, TRACK_POSES = 90, 8      # the search's track candidates: up to 8 of the last 90 not-lost estimates
SLIDING_FACTOR = 2.0                 # x after_uncertain_s: not ok this long, far, moving or not: a search
START_SIGMAS = levels.chi_level(levels.ALPHA, 3)   # status.alpha's chi, 3 dof: a never-ok track this many start sigmas off
STILL_WINDOW_S = 0.5


@dataclass
class RecoveryConfig:
    """``recovery.*`` of the configuration (module docstring). enabled; after_lost_s (s of bad frames
    in a row before a re-initialisation); after_uncertain_s (s of weighed frames not ok in a row
    before one; 0 = off); respread_sigma_p (m) / respread_sigma_r (rad); respreads
    (re-spreads before each SMC attempt); smc_evaluations (the initialiser's likelihood evaluations);
    after_lost_s is also the wait between two, doubled
    per attempt (recovery.cooldown_s until issue 32); the seconds are counted in processed frames (module docstring, "Seconds and frames");
    confirm_frames (after one,
    weighed frames in a row that the rules find ok before a pose away from the last ok one may be ok);
    search (the wide search, app/filter/wide_search.py, replaces the one-point SMC attempts);
    search_evaluations (its likelihood evaluations per search; its bar on a found fit's consistent sharp
    share, below which a found pose is searched again, is status.min_fitness at 1 sigma since issue 32:
    wide_search.MIN_SHARP); the triggers' numbers (module
    docstring, "Trigger"; defaults the module constants): sliding_factor,
    still_window_s. After attempt k the next waits min(after_lost_s 2^k, after_uncertain_s) (issue 32: the
    cap was recovery.max_backoff_doublings, 3; the base recovery.cooldown_s).
    Since issue 32 the "far" gap is ``refine.competitor_distance`` of the template's points (it was
    recovery.far_m / far_angle, 5 mm / 5 deg of the bone frame's origin; :class:`RecoveryPolicy`'s ``far``) and the never-ok
    track's one search waits ``after_uncertain_s`` (it was recovery.never_ok_search_s, the same 1 s)."""

    enabled: bool = True
    after_lost_s: float = 0.11
    after_uncertain_s: float = 1.0
    respread_sigma_p: float = 0.015
    respread_sigma_r: float = math.radians(10.0)
    respreads: int = 0
    smc_evaluations: int = 30_000
    confirm_frames: int = 90
    search: bool = True
    search_evaluations: int = 4000
    search_retry_s: float = SEARCH_RETRY_S
    sliding_factor: float = SLIDING_FACTOR
    still_window_s: float = STILL_WINDOW_S
    search_worker: str = "auto"
    confirm_moved: bool = True


class FramePeriod:
    """The period of the frames the policy sees (module docstring, "Seconds and frames"): the median
    of the last PERIOD_FRAMES - 1 positive stamp differences, NOMINAL_PERIOD_S before there is one."""

    def __init__(self):
        self._stamps: collections.deque = collections.deque(maxlen=PERIOD_FRAMES)
        self.seconds = NOMINAL_PERIOD_S

    def add(self, stamp: float) -> None:
        """One processed frame's stamp (s); a stamp not after the last one is ignored."""
        stamp = float(stamp)
        if not math.isfinite(stamp) or (self._stamps and stamp <= self._stamps[-1]):
            return
        self._stamps.append(stamp)
        if len(self._stamps) >= 2:
            self.seconds = float(np.median(np.diff(self._stamps)))

    def frames(self, seconds: float) -> int:
        """The frames in a row that span ``seconds`` at this period: ceil(seconds / period), at least 1;
        a hundredth of a frame over an integer counts as it (stamps in microseconds make the 90 Hz
        period 0.011111 s: 1.0 s is 90 frames, not 91)."""
        return max(1, math.ceil(seconds / self.seconds - 0.01))


@dataclass
class Reinitialisation:
    """One re-initialisation: stamp (s, the frame it ran on), kind ('respread' | 'smc' | 'search'), reason,
    and the trigger's code (app/tracking/triggers.py; '' for one made due from outside)."""

    stamp: float
    kind: str
    reason: str
    trigger: str = ""


class RecoveryPolicy:
    """The policy of the module docstring; the tracker asks it each frame.

    Parameters
    ----------
    config : RecoveryConfig
    centroid_bone : (3,) m, the bone's centroid in the bone frame (the re-spread's centre of rotation)
    surface_point_bone : (3,) m, a point on the bone surface near the centroid (bone frame)
    refine_enabled : whether an unrefined weighed frame counts as bad
    min_fitness : a refined fit below this counts as bad (status.min_fitness)
    still : (speed m/s, window s) below which the estimate is still: the largest speed of ``points_bone``
        (status.uncertain_speed, motion_window_s; the window at least STILL_WINDOW_S)
    far : m, a pose that moves the template's points (``points_bone``) by more than this from the last ok one
        is "far" (``refine.competitor_distance``: two poses this far apart are different answers; default
        RefineConfig's)
    start_level : the never-ok track's outside_start radius in start sigmas (chi, 3 dof, at status.alpha)
    points_bone : (N, 3) m, bone frame: the template's points whose speed the still test watches (default: the
        bone frame's origin)
    """

    def __init__(self, config: RecoveryConfig, centroid_bone: np.ndarray, surface_point_bone: np.ndarray,
                 refine_enabled: bool, min_fitness: float = 0.6,
                 still: tuple[float, float] = (0.03, 0.2),
                 start_sigmas: tuple[float, float] = (math.inf, math.inf), search_bar: float = math.nan,
                 far: float | None = None, start_level: float = START_SIGMAS,
                 points_bone: np.ndarray | None = None):
        self.config = config
        self.far = RefineConfig.competitor_distance if far is None else float(far)
        self.search_bar = search_bar           # the wide search's MIN_SHARP: a found pose below it is searched again
        self.start_sigmas = start_sigmas       # init.sigma_p (m), sigma_r (rad): the start pose's prior
        self.start_level = start_level         # k: chi_3 at status.alpha (app/tracking/levels.py)
        self.centroid_bone = np.asarray(centroid_bone, float).reshape(3)
        self.surface_point_bone = np.asarray(surface_point_bone, float).reshape(3)
        self.refine_enabled = refine_enabled
        self.min_fitness = min_fitness
        self.still = still
        self.points_bone = np.zeros((1, 3)) if points_bone is None else np.asarray(points_bone, float).reshape(-1, 3)
        self._recent: collections.deque = collections.deque()   # (stamp, T_base_bone) over the window
        self.point_prior: np.ndarray | None = None
        self.T_base_bone_confident: np.ndarray | None = None
        self.T_base_bone_start: np.ndarray | None = None
        self.events: list[Reinitialisation] = []
        self.lifecycle = Lifecycle()           # the mode: a due search, a hypothesis awaiting evidence, ever ok
        self.due_code = ""                     # the code of the trigger that made the due search due
        self._bad = 0
        self._not_ok = 0                       # weighed frames not ok in a row (while still)
        self._not_ok_moving = 0                # weighed frames not ok in a row, moving or not
        self._attempts = 0                     # since the last ok frame
        self._since = 10**9                    # frames since the last re-initialisation
        self._wait = 0                         # frames the next one waits after it (_due)
        self._ok_run = 0                       # weighed frames in a row the rules find ok (after the hold)
        self._followed = True                  # every frame since the last ok one weighed with the fit held (_confirmed)
        self._track: collections.deque = collections.deque(maxlen=TRACK_FRAMES)   # recent not-lost estimates
        self._unseen = 0                       # not-weighed frames in a row while not ok
        self.declined_searches = 0
        self.kept_searches = 0                 # searches that kept the track (no better pose found)
        self._outside = 0                      # weighed frames in a row never ok and outside the start's prior
        self._below_bar = 0                    # weighed frames in a row an unconfirmed pose's fit is below search_bar
        self.last_sharp = math.nan             # the last weighed frame's refined fit's consistent sharp share
        self.period = FramePeriod()            # the processed frames' period: seconds to frames
        self.capped = ""                       # this frame's cap on ok: '' | 'holding' | 'confirming' (the reason code)

    # -- inputs ------------------------------------------------------------------------------
    def set_start(self, T_base_bone: np.ndarray) -> None:
        """The start pose: the confident pose until a frame is ok."""
        self.T_base_bone_confident = np.array(T_base_bone, float)
        self.T_base_bone_start = np.array(T_base_bone, float)

    def set_found_start(self, T_base_bone: np.ndarray) -> None:
        """A start the detector found (app/tracking/detector.py, no coarse pose given): the start pose, and,
        as a pose the wide search found, ok only once confirmed ("Honesty": ``confirm_frames`` weighed
        frames in a row that the rules find ok); agreeing with the start pose is no evidence here, the
        start being the hypothesis itself."""
        self.set_start(T_base_bone)
        self._ok_run = 0
        self.lifecycle.detected()

    def set_point_prior(self, point_base: np.ndarray | None) -> None:
        """A point on the bone in the base frame (m; trial or session ``point_prior``), or None."""
        self.point_prior = None if point_base is None else np.asarray(point_base, float).reshape(3)

    # -- per frame ---------------------------------------------------------------------------
    def update(self, status: TrackingStatus, weighed: bool, refined: bool, fitness: float,
               T_base_bone: np.ndarray, stamp: float, sharp: float = math.nan) -> TrackingStatus:
        """One frame's final status in, the status to report out (capped at uncertain while holding);
        remembers the confident pose and decides whether a re-initialisation is due (``pending``).
        ``sharp``: the frame's best refined fit's consistent sharp share, kept or not (NaN when no fit
        converged; the sixth trigger)."""
        self.period.add(stamp)
        self._since += 1
        rules_ok = status == TrackingStatus.OK
        if status != TrackingStatus.LOST:
            self._track.append(np.array(T_base_bone, float))
        self._followed = self._followed and self._fit_held(status, weighed, refined, fitness)
        status = self._capped(status, weighed, T_base_bone)
        if status == TrackingStatus.OK:
            self.lifecycle.passed()
            self.T_base_bone_confident = np.array(T_base_bone, float)
            self._followed = True
            self._attempts, self._bad, self._not_ok, self._unseen, self._not_ok_moving = 0, 0, 0, 0, 0
            return self._frame(status, weighed)
        back = self._back_in_view(weighed)
        moving = self._moving(stamp, T_base_bone)
        beyond = self._beyond_start(T_base_bone)
        if weighed:                            # until the first re-initialisation (module docstring, "Trigger")
            self._outside = self._outside + 1 if beyond and not self.events else 0
        self._not_ok = 0 if moving or rules_ok else (self._not_ok + 1 if weighed else self._not_ok)
        self._not_ok_moving = 0 if rules_ok else self._not_ok_moving + int(weighed)
        if weighed:
            self.last_sharp = float(sharp)
            self._below_bar = self._below_bar + 1 if self._unconfirmed and not rules_ok and self.fit_below_bar() else 0
        reason = self._bad_reason(status, weighed, refined, fitness, T_base_bone)
        if reason is not None:
            self._bad += 1
        elif weighed:
            self._bad = 0
        evidence = self._evidence(reason, back, beyond, weighed, rules_ok, T_base_bone, sharp)
        trigger = first_trigger(evidence)
        if trigger is not None:
            self._due(trigger.text(evidence), trigger.code)
        return self._frame(status, weighed)

    def _frame(self, status: TrackingStatus, weighed: bool) -> TrackingStatus:
        """Step the lifecycle by the frame's own event (app/tracking/lifecycle.py ``frame_event``)."""
        self.lifecycle.frame(frame_event(str(status), weighed, self.pending is not None, bool(self.capped)))
        return status

    def _capped(self, status: TrackingStatus, weighed: bool, T_base_bone: np.ndarray) -> TrackingStatus:
        """The lifecycle's cap on ok (module docstring, "Honesty"): the hypothesis' confirmation; ``capped``
        names it when it applied ('' | 'confirming')."""
        self.capped = ""
        confirmed = self._confirmed(status, weighed, T_base_bone)
        if confirmed != status:
            self.capped = "confirming"
        return confirmed

    def _evidence(self, bad_reason: str | None, back: int, beyond: bool, weighed: bool, rules_ok: bool,
                  T_base_bone: np.ndarray, sharp: float) -> Evidence:
        """This frame's evidence for the triggers (app/tracking/triggers.py)."""
        c, frames = self.config, self.period.frames
        gap_m, gap_rad = self._gap(T_base_bone) if self.T_base_bone_confident is not None else (math.nan, math.nan)
        return Evidence(
            bad_reason=bad_reason, bad=self._bad, outside=self._outside, back=back, not_ok=self._not_ok,
            not_ok_moving=self._not_ok_moving, below_bar=self._below_bar,
            far=self._far(T_base_bone), beyond=beyond,
            ever_ok=self.lifecycle.ever_ok, retrying=self.lifecycle.retrying,
            untried=not self.events and not self.declined_searches and not self.kept_searches,
            weighed=weighed, rules_ok=rules_ok, after_lost=frames(c.after_lost_s),
            uncertain=frames(c.after_uncertain_s) if c.after_uncertain_s else 0,
            sliding=frames(self._sliding_factor() * c.after_uncertain_s),
            gap_m=gap_m, gap_rad=gap_rad, sharp=float(sharp), search_bar=self.search_bar,
            declined=self.declined_searches, kept=self.kept_searches, unseen=self._unseen)

    def fit_below_bar(self) -> bool:
        """Whether the last weighed frame's refined fit scored below ``search_bar`` (the share the wide
        search confirms a pose by; False without a bar or a fit)."""
        return self.last_sharp < self.search_bar

    def _sliding_factor(self) -> float:
        """The sliding trigger's factor on ``after_uncertain_s`` (module docstring, "Trigger", the fifth):
        1 while the track is a found or kept pose awaiting its confirmation, else SLIDING_FACTOR."""
        return 1.0 if self._unconfirmed else self.config.sliding_factor

    def _back_in_view(self, weighed: bool) -> int:
        """The count of not-weighed frames (not ok) just ended by a weighed one when it reached
        ``after_lost_s`` (in frames), else 0: the estimate is in view again after the bone was out of it
        (or hidden); far from the last ok pose, a moved bone is searched for at once instead of
        after the slow trigger's ``after_uncertain_s`` (module docstring, "Trigger")."""
        if not weighed:
            self._unseen += 1
            return 0
        back = self._unseen if self._unseen >= self.period.frames(self.config.after_lost_s) else 0
        self._unseen = 0
        return back

    def _confirmed(self, status: TrackingStatus, weighed: bool, T_base_bone: np.ndarray) -> TrackingStatus:
        """After a re-initialisation (module docstring, "Honesty"): ok only at a pose that agrees with
        the last ok pose (within FAR: the bone is usually static in the base frame), or
        after ``confirm_frames`` weighed frames in a row that the rules find ok. A track that comes back
        to ok far from the last ok pose without any re-initialisation (it followed or slid with a
        moved bone while not ok) is such a hypothesis too (``recovery.confirm_moved``): on the
        device's or_fast_reposition trials two tracks slid 36 and 51 mm off with the bone and were ok
        there for 77 and 46 frames (the rules found the wrong fit consistent; 2026-11-27, BENCHMARKS.md
        "Recovery"). The start is no ok pose: this applies once the track has been ok. A track whose fit held
        on every frame since it was last ok (:meth:`_fit_held`: weighed, refined, at least ``min_fitness``; only
        the motion test, the held pose or the template's precision kept it below ok) followed the bone with
        evidence on every frame, and is no hypothesis (issue 32: bone_moves, 8 crests x 3 seeds, waited
        confirm_frames after every tracked move, ok on 69-87 % of the eligible frames; the slid tracks above
        were lost and misfit on their way off)."""
        if (status == TrackingStatus.OK and not self._unconfirmed and self.lifecycle.ever_ok
                and self.config.confirm_moved and self._far(T_base_bone) and not self._followed):
            self.lifecycle.moved()             # back to ok far from the last ok pose without a detection
            self._ok_run = 0
        if not self._unconfirmed or status != TrackingStatus.OK:
            if weighed and status != TrackingStatus.OK:
                self._ok_run = 0
            return status
        if not self._far(T_base_bone) and not self.lifecycle.hypothesis.evidence_only:
            return status                      # agrees with the last ok pose: confirmed (the lifecycle's passed)
        self._ok_run += 1 if weighed else 0
        if self._ok_run >= self.config.confirm_frames:
            return status
        return TrackingStatus.UNCERTAIN

    def _fit_held(self, status: TrackingStatus, weighed: bool, refined: bool, fitness: float) -> bool:
        """Whether this frame is evidence that the track is on the bone: weighed, and nothing that
        :meth:`_bad_reason` calls bad, wherever the track is. A hidden frame is no evidence: the bone may have
        moved unseen."""
        return weighed and self._bad_reason(status, weighed, refined, fitness) is None

    def _gap(self, T_base_bone: np.ndarray) -> tuple[float, float]:
        return pose_gap(self.T_base_bone_confident, T_base_bone)

    def _far(self, T_base_bone: np.ndarray) -> bool:
        """Whether the estimate moves the template's points by more than FAR (``far``,
        refine.competitor_distance) from the last confident pose (far when there is none)."""
        if self.T_base_bone_confident is None:
            return True
        return metrics.mdd(self.T_base_bone_confident, T_base_bone, self.points_bone) > self.far

    def _beyond_start(self, T_base_bone: np.ndarray) -> bool:
        """Never ok and outside the start's prior: more than ``start_level`` start sigmas from it (k² the
        χ²₃ point at status.alpha, app/tracking/levels.py)."""
        if self.lifecycle.ever_ok or self.T_base_bone_start is None:
            return False
        dist, angle = pose_gap(self.T_base_bone_start, T_base_bone)
        k = self.start_level
        return dist > k * self.start_sigmas[0] or angle > k * self.start_sigmas[1]

    def _moving(self, stamp: float, T_base_bone: np.ndarray) -> bool:
        """Whether the template's points moved faster than ``still`` over the window (ending at this frame)."""
        speed, window = self.still
        window = max(window, self.config.still_window_s)
        self._recent.append((float(stamp), np.array(T_base_bone, float)))
        while len(self._recent) > 2 and stamp - self._recent[1][0] >= window:
            self._recent.popleft()
        t0, T0 = self._recent[0]
        return template_speed(T0, T_base_bone, self.points_bone, stamp - t0) > speed

    def _due(self, reason: str, code: str = "") -> None:
        """A trigger fired: the lifecycle's ``search_due``, unless the cooldown runs or one is due already."""
        if self._since >= self._wait and self.pending is None:
            self.lifecycle.search_due(reason)
            self.due_code = code

    @property
    def pending(self) -> str | None:
        """The reason of a due re-initialisation (the lifecycle's ``due``), or None."""
        return self.lifecycle.due

    @pending.setter
    def pending(self, reason: str | None) -> None:
        """Make one due (tests, and the tracker's own start), or none."""
        self.due_code = ""
        if reason is None:
            self.lifecycle.due = None
        else:
            self.lifecycle.search_due(reason)

    @property
    def _unconfirmed(self) -> bool:
        """A found or kept pose awaits its evidence (the lifecycle's hypothesis)."""
        return self.lifecycle.hypothesis is not None

    def _bad_reason(self, status: TrackingStatus, weighed: bool, refined: bool, fitness: float,
                    T_base_bone: np.ndarray | None = None) -> str | None:
        """Why this frame counts as bad (None: it does not): lost, or weighed with the refinement's track broken,
        or refined below ``min_fitness`` far from the last ok pose (anywhere when ``T_base_bone`` is None)."""
        if status == TrackingStatus.LOST:
            return "lost"
        if weighed and self.refine_enabled and not refined:
            return "refined track broken while the bone is visible"
        if (weighed and self.refine_enabled and not fitness >= self.min_fitness
                and (T_base_bone is None or self._far(T_base_bone))):
            return f"refined fit {fitness:.2f} below {self.min_fitness:.2f}"
        return None

    def _cooldown(self) -> int:
        """After attempt k (attempts counts it already): after_lost_s * 2^k in frames, at most the slow trigger's
        after_uncertain_s (no retry waits longer than a track not ok waits for its search). One reaction time
        since issue 32: the cooldown's base was recovery.cooldown_s (0.16 s), now the bad frames' wait."""
        k = max(self._attempts - 1, 0)
        frames = self.period.frames
        base = frames(self.config.after_lost_s)       # the cooldown's base (recovery.cooldown_s until issue 32)
        return max(min(base * 2 ** min(k, 30), frames(self.config.after_uncertain_s)), base)

    def next_kind(self) -> str:
        """The kind of the due attempt (module docstring)."""
        c = self.config
        if self._attempts % (c.respreads + 1) < c.respreads:
            return RESPREAD
        return SEARCH if c.search else SMC

    def track_poses(self) -> list[np.ndarray]:
        """Up to TRACK_POSES of the last TRACK_FRAMES not-lost estimates (base frame), evenly spaced:
        the wide search's candidates from the track (it followed part of a move)."""
        poses = list(self._track)
        step = max(len(poses) // TRACK_POSES, 1)
        return poses[::-1][::step][:TRACK_POSES]

    def declined(self) -> None:
        """The due wide search found nothing confirmed (the bone out of view): nothing was changed, so
        it is no attempt (no hold, no backoff step, the bad-frame counts kept); the next search runs
        SEARCH_RETRY_S later, and keeps being retried so, on weighed frames away from the last ok
        pose, until a frame is ok or a search finds a pose: the trigger found the track suspect, and a
        wrong track that moves (sliding over the tissue) or fits the tissue well is no less so
        (or_fast_reposition crest_left_03 seed 1: with the retry tied to the trigger, the bone was not
        searched for again for 2.4 s; BENCHMARKS.md §6e). A track the filter holds as hidden (not weighed)
        is retried too, once unseen for ``after_uncertain_s`` (trigger ``still_unseen``): counting weighed
        frames only, a hold that never ended was never searched again (a live session on or_fast_reposition
        held its estimate for 20 s with the bone in view elsewhere; BENCHMARKS.md "Recovery")."""
        self.lifecycle.declined()
        self.declined_searches += 1
        self._not_ok_moving = 0
        self._since, self._wait = 0, self.period.frames(self.config.search_retry_s)

    def kept(self) -> None:
        """The due wide search kept the track: the current estimate, refined in place, explained the
        image at least as well as every pose the search found (app/filter/wide_search.py, 6). Nothing
        was changed, so it is no re-initialisation (no hold). The kept pose is treated as a found one
        (module docstring, "Honesty"): away from the last ok pose it is ok only after
        ``confirm_frames`` weighed frames in a row that the rules find ok (a count under way goes on,
        and the retry below waits while the rules find the frames ok: a search about once a second
        must not restart a count of 90 frames). Before, a search that declined left such a track ok
        at once; after a fast reposition the right crests are ok on 16-27 % of the frames instead of
        17-42 % (BENCHMARKS.md §6g). The track stays suspect:
        a wrong track can explain an image that does not show the bone yet (or_fast_reposition
        crest_left_02 seed 0 at 3.7 s: 77 mm off at a sharp share of 0.60, the bone out of view; kept
        and not searched again, it was found 1.4 s after the bone came into view), so the search is
        retried as after a declined one, on weighed frames away from the last ok pose, but only
        after the cooldown, backed off as after an attempt (0.16 s doubling up to after_uncertain_s, 1 s): a right track
        the image cannot make ok (a quarter of the crest in view) is checked about once a second,
        not every frame. A track never ok is not retried so (its "last ok pose" is the start: the
        residual-tissue tracks 2 mm from the truth lie 5 mm from their start, and were searched
        four times in 3.5 s for nothing; the triggers above still apply).
        A track that followed the bone with its fit held on every frame since it was last ok (:meth:`_confirmed`)
        is no hypothesis without a search, and the search's keeping it adds evidence: it stays none (issue 32:
        bone_moves crest_right_02 seed 2, the slow trigger searched during a 2 s move, three searches kept the
        track 0.2-0.35 mm off, and it waited confirm_frames, ok on 79 % of the eligible frames)."""
        # retried if ever ok (a never-ok track has no last ok pose to be far from: its one search is spent); a kept
        # pose needs evidence, as a found one (a count under way goes on), unless the track followed the bone
        followed = self._followed and self.lifecycle.ever_ok and self.lifecycle.hypothesis is None
        self.lifecycle.kept(hypothesis=not followed)
        self.kept_searches += 1
        self._attempts += 1
        self._bad, self._not_ok, self._not_ok_moving, self._below_bar = 0, 0, 0, 0
        self._since, self._wait = 0, self._cooldown()

    def smc_point(self) -> np.ndarray:
        """The point on the bone (base frame) the one-point initialiser starts from."""
        if self.point_prior is not None:
            return self.point_prior
        T = self.T_base_bone_confident
        return T[:3, :3] @ self.surface_point_bone + T[:3, 3]

    def done(self, stamp: float, kind: str) -> None:
        """Record the re-initialisation that just ran; hold the status and restart the counts."""
        self.events.append(Reinitialisation(float(stamp), kind, self.pending or "", self.due_code))
        self.lifecycle.reinitialised()
        self._attempts += 1
        self._since, self._bad, self._not_ok, self._not_ok_moving, self._below_bar = 0, 0, 0, 0, 0
        self._wait = self._cooldown()
        self._recent.clear()
        self._ok_run, self._outside = 0, 0

    # -- when a due attempt may run ------------------------------------------------------------
    def may_run(self, visible_share: float) -> bool:
        """Whether the due attempt may run on this frame: ``visible_share`` of the bone's expected
        silhouette at the last confident pose is not hidden (:func:`visible_share`), at least
        ``min_fitness`` (status.min_fitness: less could never be confirmed); under the hand
        it waits (module docstring, "When"). A wide search also runs where the last confident pose is
        out of the image (``visible_share`` NaN): the camera has moved away from where the bone was,
        and the search looks everywhere (crest_left_02 seed 1, or_fast_reposition: it waited 2.4 s)."""
        if self.pending is None:
            return False
        if math.isnan(visible_share):
            return self.next_kind() == SEARCH
        return visible_share >= self.min_fitness

    # -- the re-spread -----------------------------------------------------------------------
    def respread_state(self, n: int, rng: np.random.Generator) -> ParticleState:
        """n particles around the last confident pose (module docstring: rotations about the bone's
        centroid), at rest, equally weighted."""
        return self.state_around(self.T_base_bone_confident, n, rng)

    def state_around(self, T_base_bone: np.ndarray, n: int, rng: np.random.Generator,
                     sigma_p: float | None = None, sigma_r: float | None = None) -> ParticleState:
        """n particles around ``T_base_bone`` (default spread: the re-spread's), at rest, equally weighted."""
        c = self.config
        p, q = self._around(T_base_bone, n, rng, c.respread_sigma_p if sigma_p is None else sigma_p,
                            c.respread_sigma_r if sigma_r is None else sigma_r)
        return ParticleState(p, np.zeros((n, 3)), q, np.zeros((n, 3)), uniform_log_weights(n))

    def _around(self, T_base_bone: np.ndarray, n: int, rng: np.random.Generator, sigma_p: float,
                sigma_r: float) -> tuple[np.ndarray, np.ndarray]:
        """:func:`draws_about_centroid` of ``T_base_bone``, c = R0 c_bone + t0."""
        R0, t0 = T_base_bone[:3, :3], T_base_bone[:3, 3]
        return draws_about_centroid(R0 @ self.centroid_bone + t0, t0, quat.from_matrix(R0), n, sigma_p, sigma_r, rng)

    def report(self) -> dict:
        """The re-initialisations for the summaries: count, stamps, kinds and reasons."""
        return {"enabled": self.config.enabled, "reinitialisations": len(self.events),
                "declined_searches": self.declined_searches, "kept_searches": self.kept_searches,
                "events": [{"stamp": e.stamp, "kind": e.kind, "reason": e.reason, "trigger": e.trigger}
                           for e in self.events]}
