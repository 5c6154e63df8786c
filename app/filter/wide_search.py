"""A wide search for a moved bone: hypothesise, score with the likelihood, verify by the refinement.

Import as ``from app.filter.wide_search import WideSearch``. Used by the recovery
(app/filter/recovery.py, issue 12: "a lost track finds a MOVED bone again"): re-spreading around
the last ok pose and the one-point SMC from the trial's point prior both search where the bone
*was*; a pelvis moved 12 cm / 45 deg (or_fast_reposition) lies outside both. The search is the
classic hypothesise-and-verify scheme of model-based object detection (Hinterstoisser et al., ACCV
2012, "Model based training, detection and pose estimation of texture-less 3D objects": candidate
poses scored against the image, the best ones refined by ICP and verified), with the candidates
drawn from the image and the track instead of a template bank:

1. **Candidate positions from the image.** The crest stands out of the tissue: its top is a local
   height maximum of the measured point cloud (the filter's depth image back-projected into the
   base frame, height along the base's z axis, up for a robot on the floor or a table; the
   simulator's table lies in the base's xy plane). The ``anchors`` highest points at least
   ``ANCHOR_SPACING_M`` apart (greedy non-maximum suppression) each carry the bone's top (the mesh
   vertices along its ridge at the last ok pose, :func:`ridge_points`) in ``yaw_steps`` turns about the up axis (a pelvis
   is repositioned on the table: mostly a translation and a turn about the vertical; Δ yaw = 360° /
   ``yaw_steps``), plus draws around each with ``ANCHOR_SIGMA_M`` / ``ANCHOR_SIGMA_RAD``.
2. **Candidates from the track.** The track's recent estimates (it followed part of the way during
   the move) and the last ok pose, each with draws of ``TRACK_SIGMA_M`` / ``TRACK_SIGMA_RAD``.
3. **Scoring** with the configured likelihood backend (DESIGN.md's depth likelihood at the
   filter's resolution; app/filter/smc_init/levels.py's ``backend_level``) in one batch.
4. **Local search** around the ``clusters`` best distinct candidates (more than
   ``DISTINCT_M`` / ``DISTINCT_RAD`` apart; ``TRACK_CLUSTERS`` of them from the track, the rest from
   the image: a wrong track's neighbourhood scored higher than the moved bone's anchors and took
   every cluster on crest_left_02): ``CEM_ROUNDS`` rounds of the cross-entropy method
   (Rubinstein and Kroese 2004: draw around the best, keep the best; σ halved per round; turns
   about the bone's centroid, so the crest does not swing about the bone frame's origin).
5. **Verification** by the refinement (app/filter/refine.py, robust point-to-plane Gauss-Newton at
   the sensor's resolution) from the ``refine_top`` (5) best (the best from the track and the others
   from the image: every image cluster; with two image slots, the crest turned 180 deg about up,
   which the filter's likelihood at 160x120 can score above the bone, took both while a cluster
   1.5 mm from the bone went unverified: or_fast_reposition crest_left_02 seed 1 at the filter's
   seed 1, 4.41 s; BENCHMARKS.md §6m) in two chains (``VERIFY_CHAINS``): one starting at twice the
   default first Tukey width (a wider capture, as refine_track.py's seeded start) followed by one
   refinement at the default width; one at width 0, followed by one more at width 0 (as the track
   refines each frame) and one at the default width, as the incumbent's (6). The best of a
   candidate's fits stands for it (a fit the search would find before one it would not, then the more
   consistent). With most of the crest out of the image the landscape along the ridge is flat and
   a wide step lets the fit slide: or_fast_reposition crest_right_02 seed 2 at 3.92 s (31 % of
   the crest's samples in the image), a candidate 16 mm / 24 deg off refined to 3.5 mm / 18 deg
   (sharp 0.49, not confirmed) from the wide start and to 0.4 mm / 2.7 deg (0.68, against the wrong
   track's 0.56) from width 0; the fit started *at the truth* slid 8 mm at the wide width (BENCHMARKS.md
   §6l), and on crest_right_02 seed 3 from 2.6 to 4.0 s a default-width step from the truth ended
   4.9-8.2 mm / 19-25 deg off on every probed frame, where width 0 stayed within 0.2-1.9 mm (§6o): a chain
   whose every fit ends at the default width could not verify the bone there. A candidate
   is found only when its refined fit confirms at least ``min_fitness`` (status.min_fitness, 0.6)
   of the expected visible surface within 3 σ, its consistent sharp share (within 1 σ, less the
   share behind the model beyond the noise) is at least ``min_sharp`` = 0.411, the same share at 1 σ for
   Gaussian residuals (:func:`app.tracking.levels.sharp_bar`; it was ``recovery.search_min_sharp`` = 0.5
   until issue 32's merge 12): a right pose leaves Gaussian noise, ~68 % within 1 σ (0.83 at the truth of
   crest_left_02, or_fast_reposition at 5 s), while wrong fits that confirmed 0.63-0.65 within 3 σ had
   0.17-0.23; and its share behind the
   model exceeds the noise's bound by no more than ``max_behind_excess`` (status.max_behind_excess,
   0.2 %): the status never finds such a fit ok, so the search must not find it either. On
   crest_right_02 seed 3 (a third of the crest in view, 2.7-3.9 s) the crest rolled 20-30 deg lay its
   flank along the tissue and scored 0.50-0.57, above the bone's own fit (0.52-0.55), but left 4-7 %
   more of the measurements behind the model than the noise's bound (the bone's fit: none beyond
   it); found, such fits held the track off the bone until 4.4-4.6 s (§6o). Among the found, the one with the highest
   :func:`app.filter.refine_track.consistent_sharp` wins (refine_track.py's rule for two fits).
   Nothing confirmed (the bone out of view, hidden): the search declines, and the tracker keeps its state.
6. **The incumbent.** The tracker's current estimate is verified too (no wide first step, no local
   search first: a refinement from where it is at width 0, then from its result one more at width 0,
   as the track refines each frame, and one more at the default width; the more consistent of the two chains
   stands for it, as for a candidate; ``INCUMBENT_CHAINS``). With the default-width chain alone,
   crest_right_05 seed 3's track, 0.1 mm off at 3.67 s with a quarter of the crest in view, was
   turned 28 deg to a sharp share of 0.56 and lost to a candidate 31 deg off at 0.59; with the
   width-0 chain alone, crest_right_04 seed 3's track 0.2 mm off at 3.50 s scored 0.72 and lost to a
   candidate 3.5 mm / 6.7 deg off at 0.76, which the default-width chain had kept (BENCHMARKS.md
   §6l). It takes part in the ranking; where it is
   confirmed and no candidate's consistent sharp share beats it by more than ``margin``
   (refine.nearby_margin, 0.015: the track's own rule for a fit that explains the image better,
   app/filter/nearby_search.py) *while explaining at least as many of the image's pixels*
   (:func:`explained_pixels`: the share times the silhouette's usable measurements at full
   resolution), the search *keeps* the track (``SearchResult.kept``, with the incumbent's refined pose
   in ``T_base_bone_kept``: the runner moves a track whose own fit fails the bar onto it): replacing a
   track by a pose that explains the image less well, or only as well, is never what the evidence
   says. A share alone does not tell a fit over few measurements from one over many (a pose that
   puts more of the model out of the image needs to explain less): with every image cluster verified, or_fast_reposition crest_right_05 seed 3's track 0.2 mm off
   (0.608 of 2,023 pixels) lost at 3.67 s to a fit 11.9 mm / 18.9 deg off (0.630 of 1,544), and three
   right tracks were so replaced over 48 runs at the filter's seed 1 (BENCHMARKS.md §6m). Without
   the margin a search replaced a track 0.1 mm off by a fit 0.5 mm off that scored 0.006 more
   (crest_right_02 seed 3 at 6.07 s), which restarts the recovery's confirmation, and under residual
   tissue the 45 never-ok searches of 48 runs replaced the track 38 times, with it 7 (BENCHMARKS.md
   §6l). Measured on or_fast_reposition crest_right_04 seed 0 at 3.68 s (the slow trigger on a track
   0.84 mm off that could not be ok with a quarter of the crest in view): every verified candidate
   lay 8.8-9.8 mm / 24-26 deg off at a sharp share of 0.46-0.50, the track refined in place scored
   0.76, and the search replaced it: 8 mm off for the next second (BENCHMARKS.md §6g).

The budget is counted in likelihood evaluations (``evaluations``: poses scored by the backend, 60 %
to the image's candidates, 10 % to the track's, the rest to the local search) plus ``5 * refine_top``
refinements (two chains, of two and of three, per candidate; 3 more for the incumbent: one
refinement, then two from it; 28 in all): work, never seconds (0.60 s of CPU per search on average
over the 48 fast repositions at the filter's seed 1 with 23, BENCHMARKS.md §6m; with 28 §6o).
A found pose is no evidence of being right: the recovery's confirmation rule
(app/filter/recovery.py, "Honesty") keeps it from being ok until the rules have agreed for
``confirm_frames`` weighed frames in a row.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from app.filter.motion import draws_about_centroid
from app.filter.refine_track import behind_excess, consistent_sharp
from app.filter.smc_init.levels import backend_level
from app.filter.status import MAX_BEHIND_EXCESS, MIN_FITNESS
from app.geometry import quaternion as quat
from app.geometry import se3
from app.tracking import levels

UP_BASE = np.array([0.0, 0.0, 1.0])
ANCHOR_SPACING_M = 0.03
PROMINENCE_RADIUS_M = 0.04
MIN_PROMINENCE_M = 0.01
RIDGE_POINTS, RIDGE_DEPTH_M = 5, 0.005
ANCHOR_SIGMA_M, ANCHOR_SIGMA_RAD = 0.005, math.radians(5.0)
TRACK_SIGMA_M, TRACK_SIGMA_RAD = 0.01, math.radians(10.0)
DISTINCT_M, DISTINCT_RAD = 0.01, math.radians(10.0)
CEM_ROUNDS = 2
CEM_SIGMA_M, CEM_SIGMA_RAD = 0.004, math.radians(4.0)
ANCHOR_SHARE = 0.6
TRACK_CLUSTERS = 2
MIN_SHARP = levels.sharp_bar(MIN_FITNESS)   # 0.411: status.min_fitness's default at 1 sigma (levels.sharp_bar)
# a candidate's verification chains: (first width, second widths from its result), x start_width (module docstring, 5)
VERIFY_CHAINS = ((2.0, (1.0,)), (0.0, (0.0, 1.0)))
INCUMBENT_CHAINS = ((0.0, (0.0, 1.0)),)   # the incumbent's: width 0, then width 0 and the default width from it (6)
INCUMBENT = "incumbent"   # the source of the tracker's current estimate among the verified (module docstring, 6)


@dataclass
class SearchConfig:
    """evaluations : likelihood evaluations (poses scored) per search; anchors : image anchors;
    yaw_steps : turns about the up axis per anchor; clusters : distinct candidates searched locally;
    refine_top : of those, refined and verified; min_fitness : a refined fit confirming less is not
    found (status.min_fitness); margin : a candidate replaces a confirmed incumbent only when its
    consistent sharp share exceeds the incumbent's by more than this (refine.nearby_margin: the
    track's own rule for a fit that explains the image better; module docstring, 6);
    max_behind_excess : a fit with more of the image behind the model than the noise explains, by more
    than this share, is not found (status.max_behind_excess: the status would never find it ok;
    module docstring, 5)."""

    evaluations: int = 4000
    anchors: int = 8
    yaw_steps: int = 24
    clusters: int = 6
    refine_top: int = 5
    min_fitness: float = MIN_FITNESS
    margin: float = 0.015
    max_behind_excess: float = MAX_BEHIND_EXCESS

    @property
    def min_sharp(self) -> float:
        """The bar on a found fit's consistent sharp share: ``min_fitness`` carried to 1 sigma
        (:func:`app.tracking.levels.sharp_bar`), never a number of its own (issue 32, merge 12)."""
        return levels.sharp_bar(self.min_fitness)


@dataclass
class SearchResult:
    """T_base_bone : the found pose (None: declined); fitness, sharp : of its refined fit (NaN when
    none converged); evaluations : poses scored; refinements : refiner calls; source : 'image' |
    'track' of the winner; candidates : (fitness, consistent sharp, T_base_bone) of each verified one;
    kept : the incumbent (the tracker's current estimate) was confirmed and no candidate explained the
    image better (module docstring, 6): T_base_bone is None; incumbent : (fitness, consistent sharp)
    of the incumbent's refined fit, NaN without one; T_base_bone_kept : a kept incumbent's refined
    pose (the track refined in place, which may have left a local minimum), else None."""

    T_base_bone: np.ndarray | None
    fitness: float
    sharp: float
    evaluations: int
    refinements: int
    source: str = ""
    candidates: list = field(default_factory=list)
    kept: bool = False
    incumbent: tuple = (math.nan, math.nan)
    T_base_bone_kept: np.ndarray | None = None


class _Verified(NamedTuple):
    """One verified pose: its refined fit's fitness and consistent sharp share, the refined pose (base
    frame), its source ('image' | 'track' | INCUMBENT), :func:`explained_pixels` and its share behind
    the model beyond the noise (:func:`app.filter.refine_track.behind_excess`)."""

    fitness: float
    sharp: float
    T_base_bone: np.ndarray | None
    source: str
    pixels: float
    behind: float


class WideSearch:
    """The search of the module docstring for one mesh.

    Parameters
    ----------
    backend : the likelihood backend (``log_likelihood(T_camera_bone, depth)``) at ``camera``
    camera : the filter's camera (the backend's resolution)
    refiner : app.filter.refine.Refiner at the full-resolution depth images
    vertices : (V, 3) the mesh's vertices (bone frame, m)
    config : SearchConfig
    """

    verify_chains = VERIFY_CHAINS     # a candidate's verification chains (module docstring, 5)

    def __init__(self, backend, camera, refiner, vertices: np.ndarray, config: SearchConfig):
        self.backend, self.camera, self.refiner, self.config = backend, camera, refiner, config
        self.vertices = np.asarray(vertices, float)
        self.centroid_bone = self.vertices.mean(axis=0)

    def run(self, depth_small: np.ndarray, depth_full: np.ndarray, T_base_camera: np.ndarray,
            T_base_bone_ok: np.ndarray, track: list[np.ndarray], rng: np.random.Generator,
            incumbent: np.ndarray | None = None) -> SearchResult:
        """One search on this frame: ``depth_small`` at the backend's resolution, ``depth_full`` at the
        refiner's; ``T_base_bone_ok`` the last ok pose (its orientation turned about up for the image's
        anchors), ``track`` recent estimates (base frame); ``incumbent`` the tracker's current estimate
        (base frame), kept unless a candidate explains the image better (module docstring, 6)."""
        c = self.config
        level = backend_level(self.backend, self.camera, depth_small, se3.inverse(T_base_camera))
        p, q, source = self._candidates(depth_small, T_base_camera, T_base_bone_ok, track, rng)
        ll = _finite(level.score(p, q))
        evaluations = len(p)
        found, evaluations = self._search_locally(level, p, q, ll, source, evaluations, rng)
        n_verify_track = min(1, len(found["track"]), c.refine_top - 1)
        best = sorted(found["image"], key=lambda f: -f[0])[:c.refine_top - n_verify_track] + \
            sorted(found["track"], key=lambda f: -f[0])[:n_verify_track]
        if incumbent is not None:
            best.append((math.nan, *_pose_pq(incumbent), INCUMBENT))
        return self._verify(best, depth_full, T_base_camera, evaluations)

    def _search_locally(self, level, p, q, ll, source, evaluations: int, rng) -> tuple[dict, int]:
        """The local search (module docstring, 4): ``clusters`` distinct best candidates (``TRACK_CLUSTERS``
        of them from the track), each searched by :meth:`_cem` with the budget left; ({'image': [...],
        'track': [...]} of (ll, p, q, source), the evaluations spent in all)."""
        c = self.config
        from_track = source == "track"
        n_track = min(TRACK_CLUSTERS, c.clusters - 1)
        seeds = _distinct_best(p, q, np.where(from_track, -np.inf, ll), c.clusters - n_track) + \
            _distinct_best(p, q, np.where(from_track, ll, -np.inf), n_track)
        per_cluster = max((c.evaluations - evaluations) // max(len(seeds) * CEM_ROUNDS, 1), 1)
        found = {"image": [], "track": []}
        for k in seeds:
            pk, qk, llk, spent = self._cem(level, p[k], q[k], ll[k], per_cluster, rng)
            evaluations += spent
            found[source[k]].append((llk, pk, qk, source[k]))
        return found, evaluations

    # -- candidates ---------------------------------------------------------------------------
    def _candidates(self, depth_small, T_base_camera, T_base_bone_ok, track, rng):
        c = self.config
        anchors = image_anchors(depth_small, self.camera, T_base_camera, c.anchors)
        n_image = int(ANCHOR_SHARE * c.evaluations)
        per_hypothesis = max(n_image // max(len(anchors) * c.yaw_steps * RIDGE_POINTS, 1), 1)
        p_img, q_img = self._anchored(anchors, T_base_bone_ok, per_hypothesis, rng)
        poses = [np.asarray(T, float) for T in track] + [np.asarray(T_base_bone_ok, float)]
        per_pose = max((c.evaluations - n_image) // (4 * len(poses)), 1)
        p_trk, q_trk = [], []
        for T in poses:
            p0, q0 = _pose_pq(T)
            pt, qt = self._around(p0, q0, per_pose, TRACK_SIGMA_M, TRACK_SIGMA_RAD, rng, keep_first=True)
            p_trk.append(pt)
            q_trk.append(qt)
        p = np.concatenate([p_img] + p_trk)
        q = np.concatenate([q_img] + q_trk)
        source = np.array(["image"] * len(p_img) + ["track"] * (len(p) - len(p_img)))
        return p, q, source

    def _anchored(self, anchors: np.ndarray, T_base_bone_ok: np.ndarray, per_hypothesis: int, rng):
        """Poses putting the bone's top (each of its ridge points) on each anchor, turned about up by each
        yaw step (module docstring, 1), with ``per_hypothesis`` - 1 draws about each (turned about the
        bone's centroid, :func:`app.filter.motion.draws_about_centroid`'s model), all in one batch: a
        start tries every tilt's hypotheses (thousands; app/tracking/detector.py), which one call per
        hypothesis spent a third of the start's CPU on, and the Python loop held the GIL while the
        frames waited (a search on the worker, app/tracking/search_worker.py)."""
        if len(anchors) == 0:
            return np.zeros((0, 3)), np.zeros((0, 4))
        R_ok = T_base_bone_ok[:3, :3]
        ridge = ridge_points(self.vertices, R_ok)
        yaws = 2.0 * np.pi * np.arange(self.config.yaw_steps) / self.config.yaw_steps
        q_yaw = quat.multiply(quat.exp_map(yaws[:, None] * UP_BASE[None]),
                              np.broadcast_to(quat.from_matrix(R_ok), (len(yaws), 4)))
        A, Y, K, n = len(anchors), len(yaws), len(ridge), per_hypothesis
        q0 = np.broadcast_to(q_yaw[None, :, None], (A, Y, K, 4)).reshape(-1, 4)
        ridge_base = quat.rotate(np.broadcast_to(q_yaw[:, None], (Y, K, 4)), np.broadcast_to(ridge[None], (Y, K, 3)))
        p0 = (anchors[:, None, None] - ridge_base[None]).reshape(-1, 3)
        centre = p0 + quat.rotate(q0, np.broadcast_to(self.centroid_bone, p0.shape))
        return draws_about_centroid(np.repeat(centre, n, axis=0), np.repeat(p0, n, axis=0), np.repeat(q0, n, axis=0),
                                    len(p0) * n, ANCHOR_SIGMA_M, ANCHOR_SIGMA_RAD, rng, keep_first=True, every=n)

    def _around(self, p0, q0, n, sigma_p, sigma_r, rng, keep_first=False):
        """n poses about (p0, q0) turned about the bone's centroid (the recovery's re-spread,
        :func:`app.filter.motion.draws_about_centroid`)."""
        centre = p0 + quat.rotate(q0[None], self.centroid_bone[None])[0]
        return draws_about_centroid(centre, p0, q0, n, sigma_p, sigma_r, rng, keep_first)

    # -- local search and verification ------------------------------------------------------------
    def _cem(self, level, p0, q0, ll0, per_round: int, rng, rounds: int = CEM_ROUNDS, keep_first: bool = False):
        """``rounds`` rounds of draws around the best so far (σ halved each round; with ``keep_first`` each
        round's first draw is that pose itself); the best kept: (p, q, ll, draws spent)."""
        best_p, best_q, best_ll, spent = p0, q0, ll0, 0
        sigma_p, sigma_r = CEM_SIGMA_M, CEM_SIGMA_RAD
        for _ in range(rounds):
            p, q = self._around(best_p, best_q, per_round, sigma_p, sigma_r, rng, keep_first)
            ll = _finite(level.score(p, q))
            spent += len(p)
            k = int(np.argmax(ll))
            if ll[k] > best_ll:
                best_p, best_q, best_ll = p[k], q[k], ll[k]
            sigma_p, sigma_r = sigma_p / 2.0, sigma_r / 2.0
        return best_p, best_q, best_ll, spent

    def _verify(self, found, depth_full, T_base_camera, evaluations: int) -> SearchResult:
        """Refine each candidate (module docstring, 5: one chain per first width of ``VERIFY_WIDTHS``,
        the more consistent fit kept; the incumbent as the track refines) and keep the best confirmed fit."""
        T_camera_base = se3.inverse(T_base_camera)
        verified, refinements = [], 0
        for _, p, q, source in found:
            T_camera_bone = T_camera_base @ se3.from_quat_trans(q, p)
            result, spent = self._verified_fit(depth_full, T_camera_bone, source == INCUMBENT)
            refinements += spent
            if result is not None:
                T_base_bone = T_base_camera @ result.T_camera_bone
                verified.append(_Verified(result.fitness, consistent_sharp(result), T_base_bone, source,
                                          explained_pixels(result), behind_excess(result)))
        incumbent = next(((v.fitness, v.sharp) for v in verified if v.source == INCUMBENT), (math.nan, math.nan))
        candidates = [(v.fitness, v.sharp, v.T_base_bone) for v in verified if v.source != INCUMBENT]
        confirmed = [v for v in verified if self._confirms(v.fitness, v.sharp, v.behind)]
        if not confirmed:
            best = max(verified, key=lambda v: v.sharp, default=_Verified(math.nan, math.nan, None, "", 0.0, math.nan))
            return SearchResult(None, best.fitness, best.sharp, evaluations, refinements, "", candidates,
                                incumbent=incumbent)
        winner = self._winner(confirmed)
        if winner.source == INCUMBENT:
            return SearchResult(None, winner.fitness, winner.sharp, evaluations, refinements, INCUMBENT, candidates,
                                kept=True, incumbent=incumbent, T_base_bone_kept=winner.T_base_bone)
        return SearchResult(winner.T_base_bone, winner.fitness, winner.sharp, evaluations, refinements, winner.source,
                            candidates, incumbent=incumbent)

    def _confirms(self, fitness: float, sharp: float, behind: float) -> bool:
        """A verified fit is found: it confirms ``min_fitness`` of the expected visible surface within 3 σ,
        its consistent share ``sharp`` (within 1 σ, less its excess behind) reaches ``min_sharp``, and its
        excess ``behind`` the model is no more than the status allows (``max_behind_excess``; module
        docstring, 5)."""
        c = self.config
        return fitness >= c.min_fitness and sharp >= c.min_sharp and behind <= c.max_behind_excess

    def _winner(self, confirmed: list[_Verified]) -> _Verified:
        """The confirmed fit that stands (module docstring, 6): without a confirmed incumbent the highest
        consistent sharp share; with one, the best of the candidates that beat its share by more than
        ``margin`` while explaining at least as many pixels (:func:`explained_pixels`), else the incumbent."""
        incumbent = next((v for v in confirmed if v.source == INCUMBENT), None)
        if incumbent is None:
            return max(confirmed, key=lambda v: v.sharp)
        rivals = [v for v in confirmed if v.source != INCUMBENT
                  and v.sharp > incumbent.sharp + self.config.margin and v.pixels >= incumbent.pixels]
        return max(rivals, key=lambda v: v.sharp) if rivals else incumbent

    def _verified_fit(self, depth_full, T_camera_bone, incumbent: bool):
        """(the best converged fit or None, refinements spent) from one candidate: per chain of
        ``VERIFY_CHAINS`` (``INCUMBENT_CHAINS`` for the incumbent; widths x ``start_width``) a refinement
        at its first width, then one more from its result at each second width (module docstring, 5 and
        6). The best: a fit the search would confirm (:meth:`_confirms`) before one it would not, then
        the higher consistent sharp share."""
        default = self.refiner.params.start_width
        best, best_key, spent = None, None, 0
        for first, seconds in (INCUMBENT_CHAINS if incumbent else self.verify_chains):
            start = self.refiner.refine(depth_full, T_camera_bone, first * default)
            spent += 1
            for second in seconds:
                result = self.refiner.refine(depth_full, start.T_camera_bone, second * default)
                spent += 1
                if not (result.converged and np.isfinite(result.fitness)):
                    continue
                sharp = consistent_sharp(result)
                key = (self._confirms(result.fitness, sharp, behind_excess(result)), sharp)
                if best is None or key > best_key:
                    best, best_key = result, key
        return best, spent


def explained_pixels(result) -> float:
    """The full-resolution pixels a fit explains: its consistent sharp share of the silhouette's usable
    measurements, ``consistent_sharp * expected * stride**2`` (a fit at stride 2 samples every
    fourth pixel)."""
    return consistent_sharp(result) * result.expected * max(result.stride, 1) ** 2


def image_anchors(depth: np.ndarray, camera, T_base_camera: np.ndarray, count: int,
                  spacing: float = ANCHOR_SPACING_M) -> np.ndarray:
    """(K <= count, 3) base-frame points where something stands out: local height maxima (along
    UP_BASE) of the measured cloud within ``spacing`` / 2 that stand at least ``MIN_PROMINENCE_M``
    over the lowest point within ``PROMINENCE_RADIUS_M`` (a top-hat transform of the height map,
    Serra 1982: the crest stands 1-3 cm out of the tissue, the flat table not at all), highest first,
    at least ``spacing`` apart (greedy non-maximum suppression). An instrument above the bone takes
    a few anchors (or_fast_reposition, crest_left_02 at 5 s: the five highest 12-21 cm from the
    crest's top, the sixth on it)."""
    from scipy import ndimage

    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        return np.zeros((0, 3))
    z = np.where(valid, depth, 0.0)
    rays = camera.pixel_rays().reshape(-1, 3)
    points = ((rays * z.ravel()[:, None]) @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]).reshape(*depth.shape, 3)
    height = np.where(valid, points @ UP_BASE, np.nan)
    pixel = float(np.median(z[valid])) / float(camera.K[0, 0])          # m per pixel at the scene's depth
    local = ndimage.maximum_filter(np.where(valid, height, -np.inf), size=_window(spacing / 2.0, pixel))
    floor = ndimage.minimum_filter(np.where(valid, height, np.inf), size=_window(PROMINENCE_RADIUS_M, pixel))
    peaks = valid & (height >= local) & (height - floor >= MIN_PROMINENCE_M)
    rank = np.where(peaks, height, -np.inf).ravel()
    flat_points = points.reshape(-1, 3)
    chosen: list[np.ndarray] = []
    for i in np.argsort(-rank):
        if not np.isfinite(rank[i]) or len(chosen) >= count:
            break
        if all(np.linalg.norm(flat_points[i] - a) >= spacing for a in chosen):
            chosen.append(flat_points[i])
    return np.array(chosen).reshape(-1, 3)


def ridge_points(vertices: np.ndarray, R_base_bone: np.ndarray, count: int = RIDGE_POINTS,
                 depth: float = RIDGE_DEPTH_M) -> np.ndarray:
    """(<= count, 3) bone-frame vertices along the top of the bone at orientation ``R_base_bone``:
    within ``depth`` of the highest along UP_BASE, spread by farthest-point sampling (the measured
    local maximum lies anywhere along the crest's ridge: 14 mm from its highest vertex on
    crest_left_02)."""
    height = (vertices @ R_base_bone.T) @ UP_BASE
    near_top = height >= height.max() - depth
    top = vertices[near_top]
    chosen = [int(np.argmax(height[near_top]))]
    dist = np.linalg.norm(top - top[chosen[0]], axis=1)
    while len(chosen) < min(count, len(top)):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(top - top[chosen[-1]], axis=1))
    return top[chosen]


def _window(radius_m: float, pixel_m: float) -> int:
    """An odd filter size (pixels) covering ``radius_m`` either side."""
    return 2 * max(int(round(radius_m / max(pixel_m, 1e-6))), 1) + 1


def _distinct_best(p: np.ndarray, q: np.ndarray, ll: np.ndarray, count: int) -> list[int]:
    """Indices of the ``count`` best-scoring poses at least DISTINCT_M / DISTINCT_RAD apart."""
    chosen: list[int] = []
    for i in np.argsort(-ll):
        if not np.isfinite(ll[i]):
            break
        if all(np.linalg.norm(p[i] - p[j]) >= DISTINCT_M or
               float(quat.angle_between(q[i], q[j])) >= DISTINCT_RAD for j in chosen):
            chosen.append(int(i))
            if len(chosen) >= count:
                break
    return chosen


def _pose_pq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q, p = se3.to_quat_trans(T)
    return np.asarray(p, float), np.asarray(q, float)


def _finite(ll) -> np.ndarray:
    ll = np.asarray(ll, float)
    return np.where(np.isfinite(ll), ll, -np.inf)
