"""The tracker's lifecycle: one explicit state, moved only by named events through one table.

Import as ``from app.tracking.lifecycle import Lifecycle, State``. DESIGN.md "The status as a test,
and the tracker's lifecycle"; issue 32. The lifecycle is the one owner of the tracker's mode: whether
a search is due (and which trigger asked for it), whether the pose is a hypothesis awaiting its
evidence, whether the track was ever ok. The recovery (app/filter/recovery.py) counts the evidence
and names the event; this module decides what the event does (:data:`TRANSITIONS`). A frame is ok
only in ``tracking``; the state is part of every frame's output (status.csv's ``state`` column,
rerun, the summaries' shares).

States:
- ``initialising``: no pose yet (waiting for a frame to start from, or the first frames of a start);
- ``tracking``: the status's tests decide, and they found the last frame ok;
- ``occluded``: the frame was not weighed (no camera pose, no depth, or the bone hidden): the pose is
  held, never ok;
- ``suspect``: weighed, but a test failed: the recovery's triggers count these frames;
- ``searching``: a trigger fired (:mod:`app.tracking.triggers`) and a re-initialisation is due
  (:attr:`Lifecycle.due`: it waits for a usable frame with the bone not hidden), or a search found
  nothing / kept the track and is retried while the track stays far and not ok;
- ``confirming``: a pose a detection found (a re-initialisation, a kept track, a detected start)
  awaits its evidence (:class:`Hypothesis`: ``recovery.confirm_frames``; right after a re-initialisation the motion
  test's settle, ``status.settle_s``, keeps it below ok too: the estimate jumped).

Events: per frame, one of ``waiting`` (before the start), ``search_due`` (a search is due), ``capped``
(the rules found the frame ok but the hypothesis is not confirmed yet), ``ok``, ``unseen`` (not
weighed), ``not_ok`` (:func:`frame_event`); within a frame, the recovery's: ``search_due`` (a trigger
fired), ``reinitialised`` (a search found a pose, or a re-spread / SMC ran), ``kept`` (a search kept
the track, which was ok before: retried), ``kept_once`` (a never-ok track's one search kept it),
``declined`` (a search found nothing: retried), ``detected`` (a start without a pose found the bone),
``moved`` (the rules find the track ok again far from the last ok pose without a re-initialisation:
a hypothesis too).
A pair the table does not hold raises: the tests run every scenario through it.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass


class State(enum.StrEnum):
    INITIALISING = "initialising"
    TRACKING = "tracking"
    OCCLUDED = "occluded"
    SUSPECT = "suspect"
    SEARCHING = "searching"
    CONFIRMING = "confirming"


FRAME_EVENTS = ("waiting", "search_due", "capped", "ok", "unseen", "not_ok")
RECOVERY_EVENTS = ("reinitialised", "kept", "kept_once", "declined", "detected", "moved")
EVENTS = FRAME_EVENTS + RECOVERY_EVENTS

S = State
_SEEN = {"search_due": S.SEARCHING, "ok": S.TRACKING, "unseen": S.OCCLUDED, "not_ok": S.SUSPECT,
         "moved": S.CONFIRMING}
# TRANSITIONS[state][event] -> next state. An absent pair is a transition the lifecycle does not have.
TRANSITIONS: dict[State, dict[str, State]] = {
    S.INITIALISING: {"waiting": S.INITIALISING, "detected": S.CONFIRMING, "search_due": S.SEARCHING,
                     "ok": S.TRACKING, "unseen": S.INITIALISING, "not_ok": S.SUSPECT},
    S.TRACKING: dict(_SEEN),
    S.OCCLUDED: dict(_SEEN),
    S.SUSPECT: dict(_SEEN),
    S.SEARCHING: {"search_due": S.SEARCHING, "reinitialised": S.CONFIRMING, "kept": S.SEARCHING, "moved": S.SEARCHING,
                  "kept_once": S.CONFIRMING, "declined": S.SEARCHING, "capped": S.SEARCHING, "ok": S.TRACKING,
                  "unseen": S.SEARCHING, "not_ok": S.SEARCHING},
    S.CONFIRMING: {"search_due": S.SEARCHING, "capped": S.CONFIRMING, "ok": S.TRACKING,
                   "unseen": S.CONFIRMING, "not_ok": S.CONFIRMING},
}
"""Notes on the table: only ``searching`` runs a re-initialisation (``reinitialised``, ``kept``,
``kept_once``, ``declined``); ``unseen`` and ``not_ok`` keep ``searching`` (the search is retried
until an ok frame or a found pose) and ``confirming`` (a hand over the bone does not confirm nor
refute a found pose); ``capped`` exists only where a hypothesis does; ``ok`` (confirmed) is reached
from every state."""


@dataclass
class Hypothesis:
    """A pose that awaits its evidence (app/filter/recovery.py, "Honesty"); ``evidence_only``: a detected
    start, for which agreeing with the start pose is no evidence (the start is the hypothesis itself)."""

    evidence_only: bool = False


class Lifecycle:
    """The current state, the due search's reason, the hypothesis under confirmation, whether the track
    was ever ok, and the frames' counts per state (for the summaries)."""

    def __init__(self, state: State = State.INITIALISING):
        self.state = State(state)
        self.due: str | None = None                 # searching: the trigger's reason while the attempt waits to run
        self.hypothesis: Hypothesis | None = None   # confirming (or searching again): the pose awaiting evidence
        self.ever_ok = False
        self.counts: dict[str, int] = {s.value: 0 for s in State}

    # -- the table -----------------------------------------------------------------------------
    def step(self, name: str) -> State:
        """Apply one event (one of EVENTS); a pair the table does not hold raises ValueError."""
        if name not in EVENTS:
            raise ValueError(f"unknown lifecycle event {name!r}; expected one of {', '.join(EVENTS)}")
        nxt = TRANSITIONS[self.state].get(name)
        if nxt is None:
            raise ValueError(f"the lifecycle has no transition from {self.state.value} on {name!r}")
        self.state = nxt
        return nxt

    def frame(self, name: str) -> State:
        """The frame's own event (one of FRAME_EVENTS, :func:`frame_event`), stepped and counted: the
        state a frame reports is the state after it."""
        state = self.step(name)
        self.counts[state.value] += 1
        return state

    def passed(self) -> None:
        """The frame's final status is ok (confirmed, if there was a hypothesis): the track has been ok
        (the slow triggers need that, app/tracking/triggers.py)."""
        self.ever_ok, self.hypothesis = True, None

    # -- the recovery's events -------------------------------------------------------------------
    @property
    def retrying(self) -> bool:
        """Searching with no attempt due: a search found nothing or kept the track, and is retried."""
        return self.state == State.SEARCHING and self.due is None

    def search_due(self, reason: str) -> None:
        """A trigger fired (app/tracking/triggers.py): a re-initialisation is due, for ``reason``."""
        self.step("search_due")
        self.due = reason

    def reinitialised(self) -> None:
        """The due attempt re-initialised the track (a found pose, a re-spread, the SMC): a new hypothesis
        (a detected start's evidence-only rule carries over)."""
        self.step("reinitialised")
        evidence_only = self.hypothesis is not None and self.hypothesis.evidence_only
        self.due, self.hypothesis = None, Hypothesis(evidence_only=evidence_only)

    def kept(self, hypothesis: bool = True) -> None:
        """The due search kept the track: the kept pose is a hypothesis too (a confirmation under way goes
        on), unless ``hypothesis`` is False (the recovery's: the track followed the bone with its fit held
        since it was last ok, and the search found nothing better: evidence, not a new pose); retried if the
        track was ever ok, else its one search is spent (``kept_once``)."""
        self.step("kept" if self.ever_ok else "kept_once")
        self.due = None
        if hypothesis and self.hypothesis is None:
            self.hypothesis = Hypothesis()

    def declined(self) -> None:
        """The due search found nothing: nothing changed, retried."""
        self.step("declined")
        self.due = None

    def moved(self) -> None:
        """The rules found the track ok again far from the last ok pose, with no re-initialisation (it
        followed or slid with a moved bone while not ok): that pose is a hypothesis too."""
        self.step("moved")
        self.hypothesis = Hypothesis()

    def detected(self) -> None:
        """A start without a pose found the bone: the found pose is a hypothesis, by evidence only."""
        self.step("detected")
        self.hypothesis = Hypothesis(evidence_only=True)



def frame_event(status: str, weighed: bool, due: bool, capped: bool, waiting: bool = False) -> str:
    """The frame's own event, the first that applies: ``waiting``, ``search_due`` (a search is due: the
    frame stays searching, even if the rules find it ok), ``capped``, ``ok``, ``unseen``, ``not_ok``."""
    if waiting:
        return "waiting"
    if due:
        return "search_due"
    if capped:
        return "capped"
    if status == "ok":
        return "ok"
    if not weighed:
        return "unseen"
    return "not_ok"


def mermaid() -> str:
    """The transition table as a mermaid state diagram (the README's; self-loops left out, the events
    of one edge joined)."""
    edges: dict[tuple[State, State], list[str]] = {}
    for state, row in TRANSITIONS.items():
        for name, nxt in row.items():
            if nxt != state:
                edges.setdefault((state, nxt), []).append(name)
    lines = ["stateDiagram-v2", "    [*] --> initialising"]
    lines += [f"    {a.value} --> {b.value}: {', '.join(names)}" for (a, b), names in edges.items()]
    return "\n".join(lines)
