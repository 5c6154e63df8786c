"""The refinement's own track beside the particle filter: which pose to refine, which to keep.

Import as ``from app.filter.refine_track import RefinedTrack``. DESIGN.md "Local refinement and the
estimate's uncertainty"; the policy is issue 12's "fourth variant" (measured there on fifteen
held-out scenes: ICP's precision on 14, no frame ok while > 5 mm off):

- the refinement keeps its own track: each weighed frame it refines (app/filter/refine.py) from
  its last refined pose while that pose's fitness holds (>= ``keep_fitness``, 0.3);
- it also refines from the filter's estimate when it has no track, when the track's fitness is
  below ``reseed_fitness`` (0.6), or when the filter's estimate moves the template's points by more than
  ``competitor_distance`` (5 mm; 5 mm / 5 deg of the bone frame's origin before issue 32) from the track (a candidate that
  could compete; nearer, the filter's 160x120 estimate is only less precise: refining it too, as
  at 3 mm / 1.7 deg first, doubled the refinement's cost on the CT crests), and keeps the better fit (the
  higher share within 1 σ, ``RefineResult.sharp``: the 3 σ fitness barely separates two fits a few
  millimetres apart on a crest; less the share behind the model beyond the noise's bound,
  :func:`consistent_sharp`: at 0.65 m a fit 17 deg off was 0.002 sharper than one 3 deg off but left
  16 % of the measurements behind the model against 4 %, BENCHMARKS.md §6d);
- when both refinements ran, converged more than ``competitor_distance`` (5 mm of the template) apart and
  the loser's sharp share is within :func:`share_margin` (``nearby_margin`` sqrt(f); it was
  ``competitor_margin``, 0.05, before issue 32) of the winner's, a competing pose
  explains the image about as well: the frame is ambiguous (the status cannot be ok, status.py);
- the track starts at the coarse initial pose (:meth:`RefinedTrack.seed`): the filter's first
  weighing can jump far (measured on crest_left_03, static_occluded: 17.8 mm off after the first
  frame from a start 5 mm off, with the filter alone too), and the refinement from the start pose
  then competes with the one from the filter's estimate; from the start pose it refines at the
  default first Tukey width and twice it (at 0.65 m each alone left a CT crest 7-9 deg off on one of
  two seeds, BENCHMARKS.md §6d), and at 1x, 2x and 4x (``SEED_WIDTHS``) a chain of refinements until
  one no longer moves the pose (``SEED_CHAIN``), whose most consistent link competes when the image's
  noise explains its share behind the model (:meth:`RefinedTrack._seed_fits`: from 16 mm / 12 deg on
  crest_right_03 one anneal reached 8 mm / 9 deg, four chained at 4x the truth); and, when the start
  came with its prior (``init.sigma_p`` / ``sigma_r``), a multi-start: ``seed_starts`` (16) poses drawn
  about the start at ``seed_spread`` (0.5) times that prior, each refined once, every fit a candidate
  (:meth:`RefinedTrack._start_fits`: Gauss-Newton from the start alone ended in a minimum 8-9 deg off
  under tissue patches on crest_right_02, BENCHMARKS.md §6e); a pose the recovery's wide search
  verified (``seed(..., verified=True)``) is already the refinement's fit on the image, and its first
  frame refines it at width 0 as the track does every frame (the wide steps undid the verification
  where the image leaves the crest's roll loose: BENCHMARKS.md §6o);
- the static-bone prior (``static_prior``, app/filter/static_prior.py): the kept fit is fused with
  the track's held base-frame pose; a frame whose image constrains the template clearly worse than
  the clearest view since the last release (a hand over the bone; both errors on the configured grid,
  :meth:`RefinedTrack._on_grid`) holds the pose, and a fit from
  the filter's estimate replaces a held pose only when it would release the prior (a clear frame
  that contradicts it). Under an 80 % hand the refinement alone slid along the crest (crest_left_03,
  seed 0: lost from 2.6 s, with or without the filter's reseed and the feedback: "track alone" in
  BENCHMARKS.md §6c, identical errors), so the slide was the refinement's, not the coupling's;
- the output pose is the refined one when its fitness >= ``keep_fitness``, else the filter's;
- feedback (``feedback``): when the filter's cloud has converged (its status not lost, its spread
  under ``feedback_spread`` / ``feedback_spread_angle``, 3 mm / 2 deg), the kept fit reaches
  ``status.min_fitness`` and no competitor exists,
  the particle cloud is shifted rigidly so that its mean lands on the refined pose
  (:meth:`app.filter.particle_filter.ParticleFilter.shift_to`): the filter stays inside the
  refinement's capture range (issue 12: seeded 0-3 mm off, 98 % of ICP frames ended under 2 mm,
  5-7.5 mm off only 16 %). Measured in BENCHMARKS.md §6;
- a competitor near the track (``RefineOutcome.nearby``, :class:`app.filter.nearby_search.NearbySearch`): every
  ``nearby_every`` (10) frames the track also refines from ``nearby_starts`` (4) draws 2 mm / 2 deg
  about its pose; a fit moving the template by more than ``status.max_template_std`` (1 mm) whose consistent share
  exceeds the track's by ``nearby_margin`` (0.015) keeps the status below ok: under residual tissue
  the refinement's minimum is a plateau 1-2 mm wide on which the track's fit is not the best
  (BENCHMARKS.md §6j; the follow-up searches about a better fit within 1 mm, §6k, were removed in
  issue 32: their scene no longer needs them). It changes the status only, never the track. Its work is spread
  over frames, ``nearby_per_frame`` (2) refinements or scorings per frame, each frame's step on its own
  image: the answers are the inline ones, some frames later (issue 35: a search never stalls the loop);
- the behind rule's evidence (``RefineOutcome.behind``): the kept fit's own excess, or the excess of
  the track's last ``behind_frames`` fits tested together when larger (app/filter/behind_pool.py;
  reset with the track): a pose 1-2 mm off along residual tissue leaves about one frame's bound
  behind it on every frame (BENCHMARKS.md §6i).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from app import metrics
from app.filter.behind_pool import BehindPool
from app.filter.motion import draws_about_centroid
from app.filter.nearby_search import NearbySearch, share_margin
from app.filter.refine import RENDER_LEVER as REFINE_LEVER
from app.filter.refine import Refiner, RefineResult, template_std
from app.filter.static_prior import StaticPrior, StaticPriorConfig
from app.filter.status import StatusThresholds
from app.geometry import se3

SEED_WIDTHS = (1.0, 2.0, 4.0)  # the seeded first frame's Tukey widths (x RefineParams.start_width; BENCHMARKS.md §6d)
SEED_CHAIN = 6                 # at most this many refinements chained at each seeded width (BENCHMARKS.md §6d)
SEED_SINGLE = (1.0, 2.0)       # widths whose first link is a candidate whatever its consistency (the single refinements of §6d)
SEED_STARTS_RNG = 20261124     # the multi-start's own generator seed (:meth:`RefinedTrack._start_fits`)


@dataclass
class RefineConfig:
    """``refine.*`` of the configuration (module docstring). enabled; stride (1 full / 2 half sensor
    resolution); iterations; samples (model points); keep_fitness; reseed_fitness;
    competitor_distance (m, the template's largest displacement), also the recovery's "far"; feedback (from
    fits confirming status.min_fitness, which was refine.feedback_fitness before issue 32);
    static_prior, prior_release_chi2, prior_clear_ratio, prior_information_frames, prior_motion_frames,
    prior_forget_ratio (app/filter/static_prior.py); seed_starts, seed_spread (the seeded first frame's multi-start,
    :meth:`RefinedTrack._start_fits`); outline_ring (the model's z-buffer grown by a pixel:
    app/filter/refine.py :func:`~app.filter.refine.fill_holes`); tissue_border (a measurement beside a
    buried one is left out of the fit: app/filter/refine.py step 5); behind_frames (the behind rule
    tested over this many of the track's last fits: app/filter/behind_pool.py); nearby_every, nearby_starts,
    nearby_sigma_p (m), nearby_sigma_r (rad), nearby_margin, nearby_hold, nearby_per_frame
    (the search for a competitor near the track: :class:`app.filter.nearby_search.NearbySearch`; its gap is
    the status's tolerance, status.max_template_std, which was refine.nearby_gap before issue 32;
    nearby_per_frame bounds its refinements and scorings per frame, 0 none)."""

    enabled: bool = True
    stride: int = 2
    iterations: int = 5
    samples: int = 30_000
    keep_fitness: float = 0.3
    reseed_fitness: float = 0.6
    competitor_distance: float = 0.005
    feedback: bool = True
    feedback_spread: float = 0.003
    feedback_spread_angle: float = math.radians(2.0)
    static_prior: bool = True
    prior_release_chi2: float = 25.0
    prior_clear_ratio: float = 1.5
    prior_information_frames: float = 300.0
    prior_motion_frames: int = 9
    prior_forget_ratio: float = 2.0
    seed_starts: int = 16
    seed_spread: float = 0.5
    outline_ring: bool = False
    tissue_border: bool = True
    behind_frames: int = 30
    noise_window_px: int = 15
    nearby_every: int = 10
    nearby_starts: int = 4
    nearby_sigma_p: float = 0.002
    nearby_sigma_r: float = math.radians(2.0)
    nearby_margin: float = 0.015
    nearby_hold: int = 2
    nearby_validate: bool = True
    nearby_per_frame: int = 2


@dataclass
class RefineOutcome:
    """One frame: T_base_bone (the refined pose, or None when no fit was kept); fitness (NaN when not
    refined); template_std (m, inf when not refined); competitor : a competing pose fits about as
    well; competitor_fitness; source : 'track' | 'filter' | ''; seconds : time spent; behind : the kept
    fit's share of measurements inside the model in excess of the noise's bound (:func:`behind_excess`;
    <= 0 when the noise explains it), or that of the track's last ``behind_frames`` fits pooled
    (app/filter/behind_pool.py) when larger; held_chi2 : the static prior's Δχ² from the pose it kept to the
    kept fit, divided by the fit's residual correlation factor f (app/tracking/fit_test.py: H counts n
    pixels whose noise carries the evidence of n / f, so a fit's Δχ² under H is f times its own), when
    it did not release onto it (0 when it did, NaN without the prior; status.py); nearby :
    the template gap (m) to a fit near the track that explains the image better, found by the
    last nearby search (:class:`app.filter.nearby_search.NearbySearch`; NaN when none was found; with
    ``nearby_per_frame`` the answer of a frame up to a few frames back, the search's work spread over them);
    nearby_unanswered : the track's first nearby search has not finished yet (its work spread over the
    next frames): the tracker keeps the status below ok until it has (inline, no frame of a track was
    ok before its first search had answered);
    sharp : the frame's best fit's consistent sharp share (:func:`consistent_sharp`), kept or not (NaN
    when no fit converged): the recovery tests a found pose against the wide search's bar with it
    (app/filter/recovery.py, the sixth trigger; a fit too poor to keep is below the bar too)."""

    T_base_bone: np.ndarray | None
    fitness: float
    template_std: float
    competitor: bool
    competitor_fitness: float
    source: str
    seconds: float
    behind: float = float("nan")
    held_chi2: float = float("nan")
    nearby: float = float("nan")
    sharp: float = float("nan")
    nearby_unanswered: bool = False


def behind_excess(result: RefineResult) -> float:
    """The kept fit's share of measurements behind the model beyond what the image's noise explains
    (``RefineResult.behind − behind_allowed``); NaN when the noise could not be measured (too few
    residuals behind the model, app/tracking/fit_test.py ``MIN_BEHIND``): the consistency test cannot run,
    so the status is not ok and a search does not confirm the fit (issue 32: it was tested against a
    fixed 2 %, ``FALLBACK_BEHIND_SHARE``, a share of one simulator's noise)."""
    return float(result.behind - result.behind_allowed)


def consistent_sharp(result: RefineResult) -> float:
    """The fit's share within 1 σ less its share behind the model beyond the noise's bound
    (:func:`behind_excess`, when positive): light does not pass through bone, so a measurement
    inside the model contradicts the pose; two fits are compared on this. An excess that could not be
    measured (NaN) takes nothing off: no evidence either way."""
    excess = behind_excess(result)
    return float(result.sharp - (excess if excess > 0.0 else 0.0))


def pose_gap(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (rad) between two poses."""
    return float(se3.translation_distance(T_a, T_b)), float(se3.rotation_angle(T_a, T_b))


class RefinedTrack:
    """The refinement's own track (module docstring).

    Parameters
    ----------
    refiner : Refiner at the depth images' full resolution
    config : RefineConfig
    plan_points : (K, 3) bone-frame points whose predicted error the status bounds (the template's;
        the mesh's vertices, subsampled, when the plan is not known: a conservative bound)
    inflation : Σ = inflation H⁻¹ (correlated pixels; status.covariance_inflation)
    tolerance : m, the nearby search's gap: a fit moving the template more than this is a different answer
        (status.max_template_std, the clinical tolerance)
    """

    def __init__(self, refiner: Refiner, config: RefineConfig, plan_points: np.ndarray, inflation: float,
                 tolerance: float = StatusThresholds.max_template_std):
        self.refiner = refiner
        self.config = config
        self.plan_points = np.asarray(plan_points, float).reshape(-1, 3) - refiner.center
        self.inflation = inflation
        prior_config = StaticPriorConfig(config.static_prior, config.prior_release_chi2, config.prior_clear_ratio,
                                         config.prior_information_frames, config.prior_motion_frames,
                                         config.prior_forget_ratio)
        self.prior = StaticPrior(prior_config, refiner.center, inflation) if config.static_prior else None
        self.behind_pool = BehindPool(config.behind_frames, refiner.params.behind_z)
        self.nearby = NearbySearch(config, self.plan_points + refiner.center, self._draws, tolerance)
        self.reset()

    def template_gap(self, T_base_bone_a: np.ndarray, T_base_bone_b: np.ndarray) -> float:
        """m, the largest displacement of the template's points between two poses (metrics.mdd): more than
        status.max_template_std is a different answer."""
        return metrics.mdd(T_base_bone_a, T_base_bone_b, self.plan_points + self.refiner.center)

    def reset(self) -> None:
        self.T_base_bone, self.fitness = None, float("nan")
        self._seeded, self._spread = False, None
        self.last_info: dict = {}
        self.behind_pool.reset()
        self.nearby.reset()
        if getattr(self, "prior", None) is not None:
            self.prior.reset()

    def seed(self, T_base_bone: np.ndarray, spread: tuple[float, float] | None = None, verified: bool = False) -> None:
        """Start the track at a given pose (the coarse initial alignment): the first frame refines from
        it with the wide first step as well as from the filter's estimate, and keeps the better fit.
        ``spread`` = (σ_p m, σ_r rad), the start's own prior (``init.sigma_p`` / ``sigma_r``): the
        first frame also refines from ``seed_starts`` poses drawn about the start
        (:meth:`_start_fits`); None (a recovery's pose) draws none. ``verified``: the pose is already
        the refinement's fit on this image (the recovery's wide search verified it,
        app/filter/wide_search.py, 5 and 6): the first frame refines it as the track refines every
        frame (width 0), not with the wide first steps, which undo the verification where the image
        leaves the crest's roll loose. or_fast_reposition crest_right_02 seed 3 at the filter's seed 1:
        a search found the bone 0.4 mm / 0.3 deg off at 4.09 s with a third of the crest in view; the
        wide seed steps slid it to 1.1-5.6 mm / 16-26 deg at a sharp share of 0.41-0.51 with 3-14 % of
        the measurements behind the model, and the track stayed there until the next search (BENCHMARKS.md §6o)."""
        self.T_base_bone, self.fitness, self._seeded = np.array(T_base_bone, float), 1.0, not verified
        self._spread = spread
        self.behind_pool.reset()
        self.nearby.reset()
        if self.prior is not None:
            self.prior.reset()

    def _scored_fit(self, depth, T_camera_base, T_start: np.ndarray):
        """(T_base_bone, consistent sharp share) of the refinement from ``T_start`` (default first width);
        None when it did not converge: the nearby search's fit (app/filter/nearby_search.py)."""
        T_fit, result = self._refine(depth, T_camera_base, T_start)
        if not (result.converged and np.isfinite(result.fitness)):
            return None
        return T_fit, consistent_sharp(result)

    def _scored_pose(self, depth, T_camera_base, T_base_bone: np.ndarray) -> float:
        """The consistent sharp share of ``T_base_bone`` on this frame as it is, not refined (the nearby
        search's out-of-sample validation); NaN when nothing is seen."""
        result = self.refiner.score(depth, T_camera_base @ T_base_bone)
        return consistent_sharp(result) if np.isfinite(result.fitness) else float("nan")

    def _refine(self, depth, T_camera_base, T_base_bone, start_width=None) -> tuple[np.ndarray, RefineResult]:
        result = self.refiner.refine(depth, T_camera_base @ T_base_bone, start_width)
        T_base_camera = se3.inverse(T_camera_base)
        return T_base_camera @ result.T_camera_bone, result

    def _on_grid(self, result: RefineResult, std: float) -> tuple[np.ndarray, float]:
        """The fit's information and template error on the configured grid (``refine.stride``), for the
        static prior: with g = stride / stride_grid, H_grid = H g² and σ_grid = σ / g (σ ∝ N^-1/2,
        H ∝ N, N ∝ stride^-2). A small silhouette is refined at stride 1 (refine.py's ``fine_below``).

        σ, for the prior's relative clear test: a stride-1 fit's H predicts about half the error of the
        same view at stride 2. Compared raw, one stride-1 fit set the clearest view at 0.36 mm and every
        later stride-2 view of the bone at rest (0.7 mm) was held as weak (crest_left_02 bone_moves
        seed 0: 6.4 mm after rest; BENCHMARKS.md §6c).

        H, for the prior's weights and tests: a stride-1 fit has four times the pixels of the same view
        at stride 2, but its errors are not four times smaller: the inflation that makes the predicted
        template error cover the measured one is 8.1 / 12.7 / 15.4 (68 / 90 / 95 %) on static_far's
        stride-1 frames against 2.1 / 2.9 / 3.2 at stride 2 on the clear near view (BENCHMARKS.md §6,
        "Calibrating the predicted template error"): four times, as this scaling says. The residuals
        of neighbouring full-resolution pixels are correlated (the simulator's noise is independent per
        pixel, so there it is the objective's own error: the invalid band along the silhouette, the
        depth unit's steps; a real stereo sensor adds its matching window). Unscaled, the stride-1
        frames of a small silhouette after a fast reposition weighed four times their worth in the
        prior, which then held their biased pose against the clearer stride-2 views that followed
        (BENCHMARKS.md §6h)."""
        H = np.asarray(result.H, float)
        if result.stride <= 0:
            return H, std
        g = result.stride / self.refiner.params.stride
        return H * g * g, std / g

    def _seed_fits(self, depth, T_camera_base) -> list:
        """The seeded first frame (:meth:`seed`): from the start pose, at each width of ``SEED_WIDTHS``, a
        chain of refinements each restarting the annealing at that width (up to ``SEED_CHAIN``, until one
        moves the pose less than ``rerender_step``). Candidates: the first link at 1x and 2x (the single
        refinements of §6d) and the chain's most consistent link (:func:`consistent_sharp`) when the
        image's noise explains its share behind the model (:func:`behind_excess` <= 0: light does not
        pass through bone). One anneal of 5 halving steps did not reach the truth from 16 mm / 12 deg on
        crest_right_03 (or_coarse_start) at any width, four chained at 4x did (0.2 % behind against a
        0.9 % bound); ungated, a chain on crest_left_03 (seed 1) ended 8 mm off with fitness 0.88 but
        25 % behind, was kept and fed back, and the track was lost (BENCHMARKS.md §6d)."""
        prm = self.refiner.params
        fits = []
        for factor in SEED_WIDTHS:
            T, chain = self.T_base_bone, []
            for _ in range(SEED_CHAIN):
                T_new, result = self._refine(depth, T_camera_base, T, start_width=prm.start_width * factor)
                if not (result.converged and np.isfinite(result.fitness)):
                    break
                chain.append(("track", T_new, result))
                dist, angle = pose_gap(T, T_new)
                T = T_new
                if dist < prm.rerender_step and angle * REFINE_LEVER < prm.rerender_step:
                    break
            if chain and factor in SEED_SINGLE:
                fits.append(chain[0])
            consistent = [f for f in chain if behind_excess(f[2]) <= 0.0]
            if consistent:
                fits.append(max(consistent, key=lambda f: consistent_sharp(f[2])))
        return fits

    def _start_fits(self, depth, T_camera_base) -> list:
        """The seeded first frame's multi-start: ``seed_starts`` poses drawn about the start pose from
        its prior scaled by ``seed_spread`` (turned about the bone's centroid, app/filter/motion.py's
        :func:`draws_about_centroid`; a fixed generator, so a replay repeats), each refined once at
        the default first width; every converged fit is a candidate. Gauss-Newton from the start
        pose alone ends in the nearest minimum: under 3 mm tissue patches on crest_right_02
        (or_model_mismatch, seed 1) every refinement from the start (5 mm / 3 deg off) ended 8-9 deg
        off with 2.5 % of the measurements behind the model, while from one of 16 draws at half the
        start prior the fit ended 0.9 mm / 1.8 deg off and was clearly more consistent (0.68 against
        0.39); the same on static_far crest_right_02 seed 1 (9.9 -> 0.75 deg; BENCHMARKS.md §6e)."""
        c = self.config
        if self._spread is None or c.seed_starts <= 0 or c.seed_spread <= 0.0:
            return []
        sigma_p, sigma_r = self._spread
        starts = self._draws(self.T_base_bone, c.seed_starts, c.seed_spread * sigma_p, c.seed_spread * sigma_r,
                             np.random.default_rng(SEED_STARTS_RNG))
        return [("track", *self._refine(depth, T_camera_base, T_start)) for T_start in starts]

    def _draws(self, T_base_bone: np.ndarray, n: int, sigma_p: float, sigma_r: float, rng) -> np.ndarray:
        """(n, 4, 4) base-frame poses drawn about ``T_base_bone``, turned about the bone's centroid
        (app/filter/motion.py :func:`draws_about_centroid`): the multi-starts of the first frame and of
        the nearby search."""
        q0, p0 = se3.to_quat_trans(T_base_bone)
        centre_base = se3.transform_points(T_base_bone, self.refiner.center[None])[0]
        p, q = draws_about_centroid(centre_base, p0, q0, n, sigma_p, sigma_r, rng)
        return se3.from_quat_trans(q, p)

    def _needs_filter(self, T_filter: np.ndarray) -> bool:
        c = self.config
        if self.T_base_bone is None or not self.fitness >= c.reseed_fitness:
            return True
        return self.template_gap(self.T_base_bone, T_filter) > c.competitor_distance

    def _held(self, fits, source, T_best, best, std):
        """The static prior (app/filter/static_prior.py) on the kept fit: a fit from the filter's
        estimate replaces a held pose only when the image alone pins it (it releases the prior); else
        the track's own fit is fused with the prior. Returns (source, T_base_bone, result, std)."""
        prior = self.prior
        grid_H, grid_std = self._on_grid(best, std)
        if prior.active and source == "filter" and not prior.would_release(T_best, grid_H, grid_std):
            track = [f for f in fits if f[0] == "track" and f[2].fitness >= self.config.keep_fitness]
            if not track:
                return source, T_best, best, std
            source, T_best, best = track[0]
            std = template_std(best.H, self.plan_points, self.inflation)
            grid_H, grid_std = self._on_grid(best, std)
        T_held = prior.update(T_best, grid_H, grid_std)
        self.last_info.update(chi2=prior.chi2, motion_chi2=prior.motion_chi2, released=prior.released, held=prior.held, discounted=prior.discounted,
                              held_chi2=0.0 if prior.released else prior.chi2,
                              img_std_mm=1e3 * std, grid_std_mm=1e3 * grid_std)
        return source, T_held, best, std

    def track_fit(self, depth: np.ndarray, T_base_camera: np.ndarray):
        """The refinement from the track's own pose that :meth:`update` makes on a frame after the
        first (width 0), or None where it makes none (no track, its fitness below ``keep_fitness``, the
        seeded first frame). It needs nothing of the filter's frame: the tracker may run it beside the
        filter's step and hand it to :meth:`update` (app/pipeline/stages.py)."""
        if self.T_base_bone is None or not self.fitness >= self.config.keep_fitness or self._seeded:
            return None
        return ("track", *self._refine(depth, se3.inverse(T_base_camera), self.T_base_bone, start_width=0.0))

    def update(self, depth: np.ndarray, T_base_camera: np.ndarray, T_base_bone_filter: np.ndarray,
               track_fit=None) -> RefineOutcome:
        """Refine on one weighed frame (full-resolution depth, metres) and update the track.
        ``track_fit``: :meth:`track_fit` of this frame, computed since the track last changed (beside the
        filter's step), or None to compute it here."""
        t0 = time.perf_counter()
        c = self.config
        T_camera_base = se3.inverse(T_base_camera)
        fits = []
        if self.T_base_bone is not None and self.fitness >= c.keep_fitness:
            if self._seeded:
                fits += self._seed_fits(depth, T_camera_base) + self._start_fits(depth, T_camera_base)
            else:
                fits.append(track_fit or ("track", *self._refine(depth, T_camera_base, self.T_base_bone, start_width=0.0)))
        self._seeded = False
        if self._needs_filter(T_base_bone_filter):
            fits.append(("filter", *self._refine(depth, T_camera_base, T_base_bone_filter)))
        fits = [f for f in fits if f[2].converged and np.isfinite(f[2].fitness)]
        if not fits:
            self.reset()
            return RefineOutcome(None, float("nan"), float("inf"), False, float("nan"), "", time.perf_counter() - t0)
        self.last_info = {f"{name}_sharp": r.sharp for name, _, r in fits}
        fits.sort(key=lambda f: -consistent_sharp(f[2]))
        source, T_best, best = fits[0]
        self.last_info["src"] = source
        competitor, competitor_fitness = False, float("nan")
        if len(fits) > 1:
            competitor_fitness = fits[1][2].fitness
            apart = self.template_gap(T_best, fits[1][1]) > c.competitor_distance
            competitor = apart and fits[1][2].sharp >= best.sharp - share_margin(c, best.correlation)
        std = template_std(best.H, self.plan_points, self.inflation)
        if self.prior is not None and best.fitness >= c.keep_fitness:
            source, T_best, best, std = self._held(fits, source, T_best, best, std)
        if best.fitness >= c.keep_fitness:
            self.T_base_bone, self.fitness = T_best, best.fitness
        else:
            self.reset()
        kept = T_best if best.fitness >= c.keep_fitness else None
        held_chi2 = self.last_info.get("held_chi2", float("nan")) / max(best.correlation, 1.0)
        self.last_info.update(correlation=best.correlation, noise_mm=1e3 * best.noise)
        behind, nearby, sharp = behind_excess(best), float("nan"), consistent_sharp(best)
        unanswered = False
        if kept is not None:
            pooled = self.behind_pool.add(best.behind, best.behind_mean, best.behind_var, best.expected)
            behind = max(behind, pooled) if np.isfinite(pooled) else behind
            nearby = self.nearby.step(lambda T_start: self._scored_fit(depth, T_camera_base, T_start), kept, sharp,
                                      best.correlation, lambda T: self._scored_pose(depth, T_camera_base, T))
            unanswered = self.nearby.answered == 0
        return RefineOutcome(kept, best.fitness, std, competitor, competitor_fitness, source, time.perf_counter() - t0,
                             behind, held_chi2, nearby, sharp, unanswered)
