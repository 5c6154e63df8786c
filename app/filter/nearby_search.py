"""The search for a competitor near the refined track (issue 12, BENCHMARKS.md §6j, §6k).

Import as ``from app.filter.nearby_search import NearbySearch``. Owned by
app/filter/refine_track.py's :class:`~app.filter.refine_track.RefinedTrack` (one per track, reset with
it); its answer is ``RefineOutcome.nearby``, and status.py keeps the status below ok while it is a gap.

Is the kept pose the best explanation of the image around it? Every ``nearby_every`` frames of
the track, refine (default first width) from ``nearby_starts`` poses drawn about the kept pose at
``nearby_sigma_p`` / ``nearby_sigma_r`` (turned about the bone's centroid,
:func:`app.filter.motion.draws_about_centroid`);
a fit whose template lies more than ``gap`` (status.max_template_std) from the kept pose's (the largest displacement
of the template's points, max_k |T_base_fit p_k − T_base_kept p_k|: :func:`app.metrics.mdd`)
and whose consistency (:func:`app.filter.refine_track.consistent_sharp`) exceeds the kept fit's by at least
``nearby_margin`` is a competitor near the track: it explains the image better. The search
stops at the first; its gap (m) is the answer until the next search (NaN: none). The status is
not ok while there is one (status.py). The next
search refines from the competitor's pose first (the track's pose moved with it in the base
frame), and a competitor found is the answer for ``nearby_hold`` searches unless a newer one
replaces it: on a plateau one search's draws can miss a competitor that is still there
(crest_left_02 or_model_mismatch: 3 of 32 searches found none, each leaving 10 frames ok
while 1.0-1.3 mm off; BENCHMARKS.md §6j).

Out of sample (``nearby_validate``, issue 32): a competitor is a fit refined on one frame and can chase
that frame's noise (a stereo camera's is correlated over its matching window). On the next frame the
competitor and the kept pose, both as they are, are scored on the new image: the competitor is withdrawn
unless it explains it better. A validated one is checked so again on each search's frame instead of
being searched for again, and stays the answer while it still explains the image better.

Follow-ups removed (issue 32, 2026-11-28): a search that found no competitor but a fit within ``gap``
scoring above the track's searched again about that fit on the next frames (``refine.nearby_followups``,
3; crest_left_02 or_model_mismatch seed 0 had 14 frames ok 1.0-1.2 mm off without them, §6k). Since the
status's correlation correction and the validation that scene no longer needs them (0 frames ok while
> 1 mm off either way), and the status matrix and the recovery matrix measured without them kept every
run's safety (BENCHMARKS.md "Decision numbers").

Why the search: under residual tissue on the ridge (or_deep_tissue, or_model_mismatch) the track sat in a
minimum 1-1.8 mm off that the 5 mm / 5 deg competitor rule cannot see, and its status was ok on
13 % of those frames (BENCHMARKS.md §6i). Measured (§6j, 2,076 frames of 40 trials of the eight
CT crests, every 5th frame searched with 8 draws at 2 mm / 2 deg): among the frames every other
rule left ok, a fit > 1 mm away scoring at least as well existed on 13 of the 15 frames > 1 mm off
and on all 145 residual-tissue frames nearer, but on 0 of 416 static_clear frames, 2 of 416
static_far and 0 of 222 static_occluded. The refinement's minimum is a point on a clean crest
and a plateau on a tissue-covered one. On the whole matrix (§6j) that rule (margin 0) also
held clean runs below ok for 20-60 frames (static_other_side crest_right_02: 60): their
competitors scored +0.000 to +0.006 above the track's, ties of a flat but right minimum, while
the residual-tissue competitors were better by more (with 0.015 asked the probe's detections
drop from 149 to 147 of 160 frames, clean frames flagged 1 -> 0 of 1,054). Four draws, not
eight: on the 158 residual-tissue frames with a competitor the first draw found it on 103 and
the first four on 149, and eight every 10 frames doubled the refinement's cost (bench-rate, §6j).
"""
from __future__ import annotations

import math
from collections import deque
from typing import Callable

import numpy as np

from app import metrics
from app.filter.status import MAX_TEMPLATE_STD_M
from app.geometry import se3

NEARBY_RNG = 20261125          # the search's own generator seed: a replay repeats

# fit(T_start) -> (T_base_bone of the refined fit, its consistent sharp share), None when it did not converge
Fit = Callable[[np.ndarray], "tuple[np.ndarray, float] | None"]
# score(T_base_bone) -> the consistent sharp share of that pose on this frame, not refined (NaN: no fit)
Score = Callable[[np.ndarray], float]
# draws(T_base_bone, n, sigma_p, sigma_r, rng) -> (n, 4, 4) poses about T_base_bone, turned about the bone's centroid
Draws = Callable[..., np.ndarray]



def share_margin(config, correlation: float) -> float:
    """The margin within which two fits' shares on one image are not told apart: ``nearby_margin`` sqrt(f),
    f the fit's residual correlation factor (n correlated pixels carry the evidence of n / f, so two shares
    differ by chance sqrt(f) times more; app/tracking/fit_test.py). One margin since issue 32 for the
    competitor rule (a far fit within it explains the image about as well), the nearby search (a fit
    beyond it explains the image better) and the wide search's replacement of a confirmed track.
    ``config``: the refine settings (app/filter/refine_track.py ``RefineConfig``)."""
    return config.nearby_margin * math.sqrt(max(float(correlation), 1.0))

class NearbySearch:
    """The search of the module docstring for one track.

    Parameters
    ----------
    config : the ``nearby_*`` fields of app/filter/refine_track.py's ``RefineConfig``
    points_bone : (N, 3) the template's points (bone frame, m): the gap is their largest displacement
    draws : the track's multi-start draws (``RefinedTrack._draws``)
    gap : m, a fit moving the template's points by more than this is a different answer (the clinical
        tolerance, ``status.max_template_std``; ``refine.nearby_gap`` before issue 32)
    """

    def __init__(self, config, points_bone: np.ndarray, draws: Draws, gap: float = MAX_TEMPLATE_STD_M):
        self.config, self.points_bone, self.draws = config, np.asarray(points_bone, float), draws
        self.gap = float(gap)
        self.map, self.width = map, 1   # fit over the starts, ``width`` at a time (app/pipeline/stages.py: pairs, 2)
        self.reset()

    def reset(self) -> None:
        """A new track: its first frame searches, from a fresh generator; frames not yet answered are dropped."""
        self._rng = np.random.default_rng(NEARBY_RNG)
        self._since = self.config.nearby_every
        self._gap, self._T_kept_competitor, self._age = math.nan, None, 0
        self.validations: list[tuple[float, float]] = []   # (competitor, kept) shares of each validation
        self._margin = self.config.nearby_margin           # nearby_margin sqrt(f) of the last step's fit
        self._unchecked: tuple[np.ndarray, np.ndarray] | None = None   # (T_base competitor, T_base kept) to validate
        self._validated: np.ndarray | None = None                     # T_base of a competitor validated out of sample
        self._queue: deque = deque()        # [steps, request] of each frame not yet answered, oldest first
        self._frames = 0                    # frames of the track stepped
        self.answered = 0                   # frames of the track answered: the answer is frame ``answered``'s
        self.answer = math.nan              # that frame's answer (m; NaN: none)
        self.work = 0                       # refinements and scorings run by the last :meth:`step`

    @property
    def pending(self) -> int:
        """Frames stepped but not answered yet (their work spread over the next frames: ``nearby_per_frame``)."""
        return self._frames - self.answered

    def step(self, fit: Fit, T_base_bone_kept: np.ndarray, own: float, correlation: float = 1.0,
             score: Score | None = None) -> float:
        """One frame of the track (kept pose ``T_base_bone_kept``, its consistent sharp share ``own``):
        search when due and answer the gap (m) to a fit that explains the image better (NaN: none).
        ``correlation``: the kept fit's residual correlation factor f (app/tracking/fit_test.py): two
        fits' shares on one image differ by chance sqrt(f) times more when n pixels carry the evidence
        of n / f, so the margin is ``nearby_margin`` sqrt(f) (0.015 was chosen on independent noise).
        ``score``: the consistent sharp share of a pose on this frame without refining it; with it, a
        competitor found on the last frame is validated here (:meth:`_validate`).

        The work per call is bounded (``nearby_per_frame`` > 0, issue 35: a search never stalls the
        frame loop): the frames' steps run in order, each exactly as on its own frame (its image, its
        kept pose), at most ``nearby_per_frame`` refinements and scorings per call; a search
        that needs more finishes on later calls. The answer is then that of the last frame whose step
        has finished (:attr:`answered`; :attr:`pending` frames behind): the inline answers, the same
        decisions, some frames later. ``fit`` and ``score`` must keep their frame's image until then
        (the caller hands a new depth array per frame). 0: all of a frame's work on its own call.

        The answer falls at most ``nearby_every`` frames behind: a budget below the search's average
        demand (at the defaults a search of up to five refinements and a validation's two scorings every
        10 frames: 0.7 a frame; 1.3 with the follow-ups removed in issue 32) would let it fall further
        behind each period, so a frame that many behind runs its
        work regardless."""
        self._queue.append([self._frame_steps(fit, T_base_bone_kept, own, correlation, score), None])
        self._frames += 1
        budget = self.config.nearby_per_frame
        self.work = 0
        while self._queue:
            entry = self._queue[0]
            steps, request = entry
            results = None
            if request is not None:
                fn, items = request
                if budget > 0 and self.work + len(items) > budget and self.pending < self.config.nearby_every:
                    break
                results = list(self.map(fn, items))
                self.work += len(items)
            try:
                entry[1] = steps.send(results)
            except StopIteration as done:
                self._queue.popleft()
                self.answered += 1
                self.answer = done.value
        return self.answer

    def _chunks(self, items: list) -> list[list]:
        """``items`` in the chunks run at once: ``width`` (two with the stage worker's pairs), at most
        ``nearby_per_frame``."""
        budget = self.config.nearby_per_frame
        n = max(1, min(self.width, budget) if budget > 0 else self.width)
        return [items[i:i + n] for i in range(0, len(items), n)]

    def _frame_steps(self, fit: Fit, T_base_bone_kept: np.ndarray, own: float, correlation: float,
                     score: Score | None):
        """:meth:`step`'s frame as steps: yields (fn, poses) for the work it needs next, receives the
        results, and returns the frame's answer."""
        c = self.config
        self._margin = share_margin(c, correlation)
        if self._unchecked is not None and score is not None:
            yield from self._validate(score)
        self._since += 1
        if c.nearby_starts <= 0 or c.nearby_every <= 0 or self._since < c.nearby_every:
            return self._gap
        self._since = 0
        if self._validated is not None and score is not None:
            if (yield from self._still_better(score, T_base_bone_kept)):
                self._age = 0
                return self._gap
        self._age += 1
        if self._age >= c.nearby_hold:
            self._gap = math.nan
        found = yield from self._search(fit, T_base_bone_kept, own)
        if found is not None:
            self._gap, self._T_kept_competitor = found
            self._age = 0
            if c.nearby_validate:
                self._unchecked = (T_base_bone_kept @ self._T_kept_competitor, np.array(T_base_bone_kept, float))
        return self._gap

    def _scores(self, score: Score, poses: list):
        """The shares of ``poses`` on the frame's image, unrefined (steps: yields the work, returns the shares)."""
        shares = []
        for chunk in self._chunks(poses):
            shares += yield score, chunk
        return shares

    def _validate(self, score: Score):
        """Out of sample: the competitor and the kept pose of the frame it was found on, both as they
        were (not refined again), scored on this frame's image. A competitor refined on one frame can
        chase that frame's noise: a stereo camera's, correlated over its matching window, leaves
        blobs a fit 1-4 mm away explains better by chance (static_far at 0.65 m: the kept pose's share
        varied 0.54-0.72 between frames). A competitor that does not explain the new frame better
        than the kept pose is withdrawn (the status's answer is NaN again); one that does stays."""
        (T_base_competitor, T_base_kept), self._unchecked = self._unchecked, None
        competitor, kept = yield from self._scores(score, [T_base_competitor, T_base_kept])
        if not (competitor > kept):
            self._gap, self._T_kept_competitor = math.nan, None
        else:
            self._validated = T_base_competitor
        self.validations.append((float(competitor), float(kept)))

    def _still_better(self, score: Score, T_base_kept: np.ndarray):
        """A validated competitor, on a search's frame: both poses as they are, scored on this frame's
        image. While the competitor still explains it better it stays the answer (no new search: the
        evidence is already out of sample); else it is dropped and the search runs as usual."""
        competitor, kept = yield from self._scores(score, [self._validated, T_base_kept])
        self.validations.append((float(competitor), float(kept)))
        if competitor > kept:
            return True
        self._validated = None
        return False

    def _search(self, fit: Fit, T_base_kept: np.ndarray, own: float):
        """Refine from the retried competitor's pose, then from ``nearby_starts`` draws about the kept pose.
        Returns the first fit more than ``gap`` (status.max_template_std) away scoring at least ``nearby_margin``
        above ``own``, as (gap m, pose relative to the kept one), or None. Steps: yields
        the refinements a chunk at a time (:meth:`_chunks`), in order; a fit computed in the chunk of
        the one that stops the search is dropped, as the pairs' lazy map dropped it."""
        c = self.config
        starts = list(self.draws(T_base_kept, c.nearby_starts, c.nearby_sigma_p, c.nearby_sigma_r, self._rng))
        if self._T_kept_competitor is not None:
            starts.insert(0, T_base_kept @ self._T_kept_competitor)
        self._T_kept_competitor = None
        T_kept_base, threshold = se3.inverse(T_base_kept), own + self._margin
        for chunk in self._chunks(starts):
            for scored in (yield fit, chunk):
                if scored is None:
                    continue
                T_base_fit, score = scored
                if score < threshold:
                    continue
                gap = metrics.mdd(T_base_fit, T_base_kept, self.points_bone)
                if gap > self.gap:
                    return gap, T_kept_base @ T_base_fit
        return None
