"""One detector: the bone's pose on one frame, from a prior or from nothing; start is detection.

Import as ``from app.tracking.detector import Detection, make_detector``. Issue 33: the tracker's
start and its recovery both ask "where is the bone in this image?". A :class:`Detector` answers
``detect(depth_small, depth_m, T_base_camera, prior) -> Detection | None``:

- ``depth_small``: the depth image at the filter's resolution (the likelihood backend's), ``depth_m``
  at the sensor's (the refinement's), ``T_base_camera`` its camera pose;
- ``prior``: a point on the bone (base frame, (3,): the trial's / session's ``point_prior``), a
  coarse pose ((4, 4) T_base_bone), or None (nothing known: the whole image);
- the :class:`Detection`: the found ``T_base_bone``, its verification score (the refined fit's
  consistent sharp share and fitness, :mod:`app.filter.refine_track`) and the work it took
  (likelihood evaluations, refinements); None when nothing was confirmed (the bone out of view).

Two strategies, wrapped, not rewritten:

- :class:`SearchDetector`, the recovery's wide search (app/filter/wide_search.py: hypothesise from the
  image's height maxima, score with the likelihood, search locally, verify by the refinement with its
  ``VERIFY_CHAINS`` and its bar). With a point, only the height maxima within ``POINT_RADIUS_M`` of it
  (found at ``POINT_SPACING_M``, finer than the recovery's 3 cm, so a taller object nearby does not
  suppress the crest's own top) and the point itself carry the bone's top; with a pose, the
  recovery's own form (anchors everywhere, the pose as the track); with nothing, every anchor. The
  bone's orientation before the turns about up: its top direction (the mesh's +z: the CT's head
  direction, the crest's top, pelvis README; the simulator stands the bone so) along the base's up,
  as the wide search assumes for a bone on the table, and that orientation tilted by
  ``StartSearch.tilt_rad`` towards ``tilt_directions`` directions (a patient's crest is not level:
  from up alone every start of the simulator's views tilted 21 deg was missed or confirmed up to
  15 mm off), each then turned ``yaw_steps`` times about up
  (``app.filter.wide_search.WideSearch._anchored``). A start spends more than a recovery's search
  (``StartSearch``: twice the evaluations, more candidates verified): it happens once, and its winner
  is the most consistent confirmed fit, so each right candidate verified is a chance to beat a wrong
  one. The recovery keeps calling the same :class:`~app.filter.wide_search.WideSearch` object
  directly (its incumbent and track rules are the recovery's, its budget and orientations its own).
- :class:`SMCDetector`, the one-point SMC initialiser (app/filter/smc_init/) from a point (a pose's
  prior: the surface point nearest the mesh's centroid), its weighted-mean pose then verified by the
  same refinement chains and bar as a wide-search candidate, so the two strategies are scored alike.

A found pose is no evidence of being right: the tracker's start treats it as the recovery treats a
found pose (confirmation before ok; app/filter/recovery.py, "Honesty").
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from app.filter.smc_init.geometry import rotation_between
from app.filter.wide_search import (ANCHOR_SHARE, CEM_ROUNDS, RIDGE_POINTS, TRACK_CLUSTERS, UP_BASE, VERIFY_CHAINS,
                                    WideSearch, _distinct_best, image_anchors)
from app.geometry import quaternion as quat
from app.geometry import se3

POINT_RADIUS_M = 0.02       # a point prior's anchors: height maxima within this of the point (2-5 mm pointing error)
POINT_SPACING_M = 0.01      # their non-maximum suppression: finer than the recovery's 3 cm (module docstring)
POINT_ANCHORS = 4           # at most this many of them, the point itself included
# a start's verification chains (StartSearch.chains): 'wide' the wide search's first chain alone (from twice
# the first Tukey width, then the default), 'both' also its chain from width 0 (the recovery's, for a bone
# mostly out of the image after a move: app/filter/wide_search.py's module docstring, 5)
START_CHAINS = {"wide": VERIFY_CHAINS[:1], "both": VERIFY_CHAINS}
SEARCH = "search"
SMC = "smc"
STRATEGIES = (SEARCH, SMC)
BONE_TOP = np.array([0.0, 0.0, 1.0])   # the mesh's top direction: the CT's head direction, the crest's top


@dataclass
class Detection:
    """A found pose: T_base_bone (base frame), score (its refined fit's consistent sharp share, the
    wide search's ranking), fitness (the share of the expected visible surface confirmed within 3 σ),
    evaluations (poses scored by the likelihood backend), refinements (refiner calls), strategy."""

    T_base_bone: np.ndarray
    score: float
    fitness: float
    evaluations: int
    refinements: int
    strategy: str


class Detector(Protocol):
    """Find the bone on one frame (module docstring); ``last_work``: (likelihood evaluations, refinements)
    of the last call, found or not."""

    last_work: tuple[int, int]

    def detect(self, depth_small: np.ndarray, depth_m: np.ndarray, T_base_camera: np.ndarray,
               prior: np.ndarray | None) -> Detection | None: ...


def prior_kind(prior) -> str:
    """'point' ((3,)), 'pose' ((4, 4)) or 'none'; anything else is refused with the shapes accepted."""
    if prior is None:
        return "none"
    a = np.asarray(prior, float)
    if a.shape == (3,) and np.all(np.isfinite(a)):
        return "point"
    if a.shape == (4, 4) and np.all(np.isfinite(a)):
        return "pose"
    raise ValueError(f"a detector's prior is a point (3 finite numbers, base frame), a 4x4 T_base_bone or "
                     f"None; got shape {a.shape}")


def up_orientation() -> np.ndarray:
    """T_base_bone's rotation with the bone's top direction (mesh +z, ``BONE_TOP``) along the base's up:
    the orientation a bone on the table is searched from (then turned about up) when nothing else is known."""
    return quat.to_matrix(rotation_between(BONE_TOP[None], UP_BASE)[0])


class PriorSearch(WideSearch):
    """The wide search with its image candidates restricted to a point prior's neighbourhood (or every
    anchor without one) and no track candidates (module docstring). ``point``: set per call;
    ``tilts``: the bone-frame tilts (3x3 rotations) of the start orientation tried besides it
    (:func:`tilt_rotations`)."""

    point: np.ndarray | None = None
    tilts: tuple = ()
    screened: int = 0

    def _search_locally(self, level, p, q, ll, source, evaluations: int, rng) -> tuple[dict, int]:
        """The local search with a screening round (successive halving, Jamieson and Talwalkar 2016):
        the ``screened`` best distinct hypotheses each get one round of the local search's draws
        (:meth:`WideSearch._cem` at its first spread, the hypothesis itself kept); the best distinct of the
        screened are then the clusters of the wide search's local search (:meth:`WideSearch._cem`).
        Every round of either stage draws as many poses. Why: the start's grid is coarse (24 turns,
        7 orientations, 5 ridge points: its pose nearest the truth can be 6 mm off), and at the filter's
        resolution such a pose can score below a family of wrong poses that matches the crest along
        other directions (crest_left_04 view 3: ten clusters 74-83 mm off, the nearest to the truth
        ranked 33rd); one round lifts it above them (BENCHMARKS.md "Start from a point").
        ``screened`` <= the clusters: the wide search's own local search."""
        n = self.config.clusters - TRACK_CLUSTERS
        if self.screened <= n:
            return super()._search_locally(level, p, q, ll, source, evaluations, rng)
        seeds = _distinct_best(p, q, ll, self.screened)
        per_round = max((self.config.evaluations - evaluations) // max(len(seeds) + n * CEM_ROUNDS, 1), 1)
        screened = [self._cem(level, p[k], q[k], ll[k], per_round, rng, rounds=1, keep_first=True) for k in seeds]
        evaluations += sum(spent for *_, spent in screened)
        sp, sq = np.array([s[0] for s in screened]).reshape(-1, 3), np.array([s[1] for s in screened]).reshape(-1, 4)
        sll = np.array([s[2] for s in screened], float)
        found = {"image": [], "track": []}
        for k in _distinct_best(sp, sq, sll, n):
            pk, qk, llk, spent = self._cem(level, sp[k], sq[k], sll[k], per_round, rng)
            evaluations += spent
            found["image"].append((llk, pk, qk, "image"))
        return found, evaluations

    def _candidates(self, depth_small, T_base_camera, T_base_bone_ok, track, rng):
        anchors = self._prior_anchors(depth_small, T_base_camera)
        starts = [T_base_bone_ok] + [_tilted(T_base_bone_ok, R) for R in self.tilts]
        n_image = int(self.config.evaluations * ANCHOR_SHARE)
        per_hypothesis = max(n_image // max(len(anchors) * self.config.yaw_steps * RIDGE_POINTS * len(starts), 1), 1)
        ps, qs = zip(*(self._anchored(anchors, T, per_hypothesis, rng) for T in starts))
        p, q = np.concatenate(ps), np.concatenate(qs)
        return p, q, np.array(["image"] * len(p))

    def _prior_anchors(self, depth_small, T_base_camera) -> np.ndarray:
        """The point (when given) and the image's height maxima near it (POINT_RADIUS_M, at
        POINT_SPACING_M), or the recovery's anchors over the whole image."""
        if self.point is None:
            return image_anchors(depth_small, self.camera, T_base_camera, self.config.anchors)
        peaks = image_anchors(depth_small, self.camera, T_base_camera, 64, spacing=POINT_SPACING_M)
        near = peaks[np.linalg.norm(peaks - self.point, axis=1) <= POINT_RADIUS_M] if len(peaks) else peaks
        return np.vstack([self.point[None], near[:POINT_ANCHORS - 1]])


@dataclass(frozen=True)
class StartSearch:
    """The search of a start from a point or from nothing (``init.detector_*``; module docstring): its
    likelihood ``evaluations``, its ``clusters`` searched locally and ``refine_top`` of them verified
    (the recovery's 4,000 / 6 / 5: a start is once per session, its budget is the 2 s of issue 33), and
    the start orientation (the bone's top up) also tilted by ``tilt_rad`` towards ``tilt_directions``
    directions (:func:`tilt_rotations`): the simulator's bone tilts 8 deg per axis (a Rayleigh tilt
    of the top, median 9 deg, 95 % under 20 deg), and from up alone the search missed or
    mis-confirmed every start of the views tilted 21 deg (BENCHMARKS.md, "Start from a point");
    ``screened`` hypotheses given one round of local search first (:meth:`PriorSearch._search_locally`);
    ``chains``: the verification chains (``START_CHAINS``): 'wide' alone found as many as 'both' on
    the left crests' starts at three quarters of the CPU (a pointed crest is in view; the width-0
    chain is the recovery's, for a bone mostly out of the image)."""

    evaluations: int = 8000
    clusters: int = 10
    refine_top: int = 8
    tilt_rad: float = math.radians(15.0)
    tilt_directions: int = 6
    screened: int = 60
    chains: str = "wide"


class SearchDetector:
    """The wide search behind the :class:`Detector` interface (module docstring).

    Parameters
    ----------
    search : app.filter.wide_search.WideSearch (the recovery's, or one built alike)
    rng : np.random.Generator (the tracker's filter's: one stream, deterministic replays)
    start : StartSearch, the search from a point or from nothing (None: its defaults); a pose prior
        is searched with ``search`` itself, as the recovery does
    """

    strategy = SEARCH

    def __init__(self, search: WideSearch, rng: np.random.Generator, start: StartSearch | None = None):
        self.search, self.rng = search, rng
        self.start = start = start or StartSearch()
        # the point / whole-image form: same backend, refiner, mesh and bar; the track's slots go to the image
        config = replace(search.config, evaluations=start.evaluations, clusters=start.clusters + TRACK_CLUSTERS,
                         refine_top=start.refine_top)
        self.prior_search = PriorSearch(search.backend, search.camera, search.refiner, search.vertices, config)
        self.prior_search.tilts = tilt_rotations(start.tilt_rad, start.tilt_directions)
        self.prior_search.screened = start.screened
        self.prior_search.verify_chains = START_CHAINS[start.chains]
        self.last_work = (0, 0)

    def detect(self, depth_small, depth_m, T_base_camera, prior) -> Detection | None:
        kind = prior_kind(prior)
        if kind == "pose":
            T = np.asarray(prior, float)
            result = self.search.run(depth_small, depth_m, T_base_camera, T, [T], self.rng)
        else:
            self.prior_search.point = None if kind == "none" else np.asarray(prior, float)
            start = np.eye(4)
            start[:3, :3] = up_orientation()
            result = self.prior_search.run(depth_small, depth_m, T_base_camera, start, [], self.rng)
        self.last_work = (result.evaluations, result.refinements)
        if result.T_base_bone is None:
            return None
        return Detection(result.T_base_bone, result.sharp, result.fitness, result.evaluations, result.refinements,
                         SEARCH)


class SMCDetector:
    """The one-point SMC initialiser behind the :class:`Detector` interface, its pose verified as a
    wide-search candidate (module docstring).

    Parameters
    ----------
    backend, camera : the filter's likelihood backend and its camera
    vertices, faces : the tracking mesh
    smc : app.filter.smc_init.SMCInitConfig
    verifier : a WideSearch whose refinement chains and bar verify the result
    rng : np.random.Generator
    """

    strategy = SMC

    def __init__(self, backend, camera, vertices, faces, smc, verifier: WideSearch, rng: np.random.Generator):
        self.backend, self.camera, self.vertices, self.faces = backend, camera, vertices, faces
        self.smc, self.verifier, self.rng = smc, verifier, rng
        self.last_result = None
        self.last_work = (0, 0)

    def detect(self, depth_small, depth_m, T_base_camera, prior) -> Detection | None:
        from app.filter.smc_init import OnePointInitialiser

        kind = prior_kind(prior)
        if kind == "none":
            raise ValueError("the one-point SMC needs a point (or a pose) as its prior")
        point = np.asarray(prior, float) if kind == "point" else _surface_point(np.asarray(prior, float), self.vertices)
        initialiser = OnePointInitialiser(self.backend, self.camera, self.vertices, self.faces, self.smc, self.rng)
        result = initialiser.run(depth_small, T_base_camera, point)
        self.last_result = result
        q, p = se3.to_quat_trans(result.estimate.T_base_bone)
        found = self.verifier._verify([(math.nan, np.asarray(p, float), np.asarray(q, float), "image")], depth_m,
                                      T_base_camera, int(result.evaluations))
        self.last_work = (found.evaluations, found.refinements)
        if found.T_base_bone is None:
            return None
        return Detection(found.T_base_bone, found.sharp, found.fitness, found.evaluations, found.refinements, SMC)


def tilt_rotations(tilt_rad: float, directions: int) -> tuple:
    """Bone-frame rotations tilting the bone's top (``BONE_TOP``) by ``tilt_rad`` towards ``directions``
    evenly spaced directions of the bone's xy plane: R_k = exp(tilt_rad [cos b_k, sin b_k, 0]^),
    b_k = 2 pi k / directions. Applied on the right of the start orientation (T_base_bone R_k), so the
    search's turns about up (on the left) sweep each tilted orientation's heading."""
    if tilt_rad <= 0.0 or directions <= 0:
        return ()
    b = 2.0 * np.pi * np.arange(directions) / directions
    axes = tilt_rad * np.column_stack([np.cos(b), np.sin(b), np.zeros_like(b)])
    return tuple(quat.to_matrix(quat.exp_map(a)) for a in axes)


def _tilted(T_base_bone: np.ndarray, R_bone: np.ndarray) -> np.ndarray:
    """T_base_bone with its rotation tilted in the bone frame: R_base_bone R_bone."""
    T = np.array(T_base_bone, float)
    T[:3, :3] = T[:3, :3] @ R_bone
    return T


def _surface_point(T_base_bone: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """The mesh vertex nearest its centroid, in the base frame at ``T_base_bone`` (the recovery's SMC point)."""
    centroid = vertices.mean(axis=0)
    v = vertices[np.argmin(np.linalg.norm(vertices - centroid, axis=1))]
    return T_base_bone[:3, :3] @ v + T_base_bone[:3, 3]

