"""The recovery's triggers: the lifecycle's transitions into ``searching``, as one ordered table.

Import as ``from app.tracking.triggers import TRIGGERS, first_trigger``. Each trigger is a named test
on the evidence the recovery counts (app/filter/recovery.py, :class:`Evidence`); the first that
fires on a frame that is not ok is the lifecycle's ``search_due`` event (app/tracking/lifecycle.py),
its code and text the due search's reason (the summaries' re-initialisations, status.csv's
``searching`` frames). A trigger that fires while the cooldown after the last attempt runs does
nothing (the recovery's backoff). Durations are seconds of processed frames (recovery.py's
FramePeriod), the numbers ``recovery.*`` in configs/default.yaml. Why each exists, measured, is in
recovery.py's docstring ("Trigger") and BENCHMARKS.md §6b-§6o.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Evidence:
    """One frame's counts and facts, as the triggers read them (frames are weighed frames in a row unless
    said). ``bad``: frames lost, unrefined or refined below ``status.min_fitness`` while far (``bad_reason``
    says which); ``outside``: never ok and beyond the start's prior; ``back``: the unseen frames this
    weighed one ended (0 unless at least ``after_lost``); ``not_ok``: not ok while still; ``not_ok_moving``:
    not ok, moving or not; ``below_bar``: a hypothesis' fit below the search's bar; ``far``: more than
    ``refine.competitor_distance`` (the template's largest displacement) from the last ok pose; ``beyond``: never ok and outside the start's
    prior; ``ever_ok``, ``retrying`` (the lifecycle's), ``untried`` (no attempt, declined or kept search
    yet); the thresholds in frames (``after_lost``, ``uncertain``: after_uncertain_s or 0 when off, also
    the never-ok track's one search, ``sliding``); ``gap_m`` / ``gap_rad``: the pose's distance and angle to the last ok pose
    (NaN without one), formatted only when a trigger fires (:func:`gap_text`); ``unseen``: frames in a row not
    weighed (the filter's occlusion hold, or no camera pose or depth) while not ok."""

    bad_reason: str | None
    bad: int
    outside: int
    back: int
    not_ok: int
    not_ok_moving: int
    below_bar: int
    far: bool
    beyond: bool
    ever_ok: bool
    retrying: bool
    untried: bool
    weighed: bool
    rules_ok: bool
    after_lost: int
    uncertain: int
    sliding: int
    gap_m: float
    gap_rad: float
    sharp: float
    search_bar: float
    declined: int
    kept: int
    unseen: int


@dataclass(frozen=True)
class Trigger:
    """A transition into ``searching``: its code, the test, the reason's text, its config keys, and
    when it fires in words (the README's table)."""

    code: str
    fires: Callable[[Evidence], bool]
    text: Callable[[Evidence], str]
    keys: str
    when: str


def _slow(e: Evidence) -> bool:
    """The slow triggers' common condition: on (after_uncertain_s > 0), far, and ok before or outside the start's prior."""
    return bool(e.uncertain) and (e.ever_ok or e.beyond) and e.far


TRIGGERS: tuple[Trigger, ...] = (
    Trigger("lost_for",
            lambda e: e.bad_reason is not None and e.bad >= e.after_lost,
            lambda e: f"{e.bad_reason} for {e.bad} frames",
            "recovery.after_lost_s, status.min_fitness",
            "lost, or the refined fit broken or below status.min_fitness far from the last ok pose, for after_lost_s"),
    Trigger("outside_start",
            lambda e: e.outside >= e.after_lost,
            lambda e: f"never ok, {e.outside} weighed frames outside the start's prior ({gap_text(e)} from the start)",
            "recovery.after_lost_s, status.alpha",
            "never ok and beyond the start's prior (chi, 3 dof, at alpha) for after_lost_s (until the first re-initialisation)"),
    Trigger("back_in_view",
            lambda e: bool(e.back) and e.far,
            lambda e: f"weighed again after {e.back} frames unseen, {gap_text(e)} from the last ok pose",
            "recovery.after_lost_s, refine.competitor_distance",
            "weighed again after after_lost_s unseen, far from the last ok pose"),
    Trigger("not_ok_still",
            lambda e: _slow(e) and e.not_ok >= e.uncertain,
            lambda e: f"not ok for {e.not_ok} weighed frames, {gap_text(e)} from the last ok pose",
            "recovery.after_uncertain_s, recovery.still_window_s",
            "not ok for after_uncertain_s while still, far (ok before, or outside the start's prior)"),
    Trigger("sliding",
            lambda e: _slow(e) and e.not_ok_moving >= e.sliding,
            lambda e: f"not ok for {e.not_ok_moving} weighed frames, moving or not, {gap_text(e)} from the last ok pose",
            "recovery.after_uncertain_s, recovery.sliding_factor",
            "not ok for sliding_factor x after_uncertain_s, moving or not, far (x1 for a hypothesis)"),
    Trigger("below_bar",
            lambda e: e.below_bar >= e.after_lost and e.far,
            lambda e: (f"the found pose's fit below the search's bar for {e.below_bar} weighed frames "
                       f"(sharp share {e.sharp:.2f} < {e.search_bar:.2f}), {gap_text(e)} from the last ok pose"),
            "recovery.after_lost_s",
            "a hypothesis' fit below the search's bar for after_lost_s, far"),
    Trigger("never_ok_once",
            lambda e: bool(e.uncertain) and not e.ever_ok and e.untried and e.not_ok >= e.uncertain,
            lambda e: f"never ok for {e.not_ok} weighed frames since the start: one wide search",
            "recovery.after_uncertain_s",
            "never ok for after_uncertain_s (still), before any attempt: one search"),
    Trigger("still_searching",
            lambda e: e.retrying and e.weighed and not e.rules_ok and e.far,
            lambda e: (f"still searching ({e.declined} searches found nothing, {e.kept} kept the track), "
                       f"{gap_text(e)} from the last ok pose"),
            "status.settle_s, recovery.after_lost_s",
            "a search found nothing or kept the track, and the track is still far and not ok (after the retry wait)"),
    Trigger("still_unseen",
            lambda e: e.retrying and 0 < e.uncertain <= e.unseen,      # unseen: reset by a weighed frame, never ok
            lambda e: (f"still searching ({e.declined} searches found nothing, {e.kept} kept the track), the track "
                       f"unseen for {e.unseen} frames"),
            "recovery.after_uncertain_s, status.settle_s",
            "a search found nothing or kept the track, and the track has not been weighed for after_uncertain_s since "
            "(held as hidden; after the retry wait)"),
)
CODES = tuple(t.code for t in TRIGGERS)


def gap_text(e: Evidence) -> str:
    """The pose's gap to the last ok pose for a reason's text ('nan mm / nan deg' without one)."""
    return f"{1e3 * e.gap_m:.0f} mm / {math.degrees(e.gap_rad):.0f} deg"


def first_trigger(evidence: Evidence) -> Trigger | None:
    """The first trigger of :data:`TRIGGERS` that fires on this evidence, or None."""
    return next((t for t in TRIGGERS if t.fires(evidence)), None)


def markdown_table() -> str:
    """The README's table of the triggers, in their order."""
    rows = ["| trigger | searching when | config |", "|---|---|---|"]
    rows += [f"| `{t.code}` | {t.when} | `{t.keys}` |" for t in TRIGGERS]
    return "\n".join(rows)


