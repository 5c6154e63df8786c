"""The tracker's lifecycle: one explicit state per frame, moved by one named event through a table.

Import as ``from app.tracking.lifecycle import Lifecycle, State``. DESIGN.md "The status as a test,
and the tracker's lifecycle". A frame is ok only in ``tracking``; the state is part of every frame's
output (status.csv's ``state`` column, rerun, the summaries' shares).

States:
- ``initialising``: no pose yet (waiting for a frame to start from a point);
- ``tracking``: the track follows the bone and the status's tests decide (ok when they all pass);
- ``occluded``: the frame was not weighed (no camera pose, no depth, or the bone hidden): the pose is
  held, never ok;
- ``suspect``: weighed, but a test failed: the track may be wrong; the recovery's triggers count
  these frames (app/filter/recovery.py);
- ``searching``: a re-initialisation is due or under way (the wide search, a re-spread or the
  one-point SMC);
- ``confirming``: a pose a re-initialisation found (away from the last ok one) awaits its evidence
  (``recovery.hold_frames`` and ``recovery.confirm_frames``): never ok.

Events, one per frame, the first that applies (:func:`event`): ``waiting`` (not started),
``reinitialised`` (a re-initialisation ran this frame), ``search_due`` (one is pending),
``unseen`` (not weighed), ``capped`` (the recovery caps ok: hold or confirmation), ``ok``,
``not_ok``.

Today the recovery's triggers still live in app/filter/recovery.py's counters; this module states
the states and their transitions explicitly and reports them, and the table is the contract the
recovery's counters must respect (a transition the table does not hold raises: tests run every
scenario through it).
"""
from __future__ import annotations

import enum


class State(enum.StrEnum):
    INITIALISING = "initialising"
    TRACKING = "tracking"
    OCCLUDED = "occluded"
    SUSPECT = "suspect"
    SEARCHING = "searching"
    CONFIRMING = "confirming"


EVENTS = ("waiting", "reinitialised", "search_due", "unseen", "capped", "ok", "not_ok")

S = State
# TRANSITIONS[state][event] -> next state. An absent pair is a transition the lifecycle does not have.
TRANSITIONS: dict[State, dict[str, State]] = {
    S.INITIALISING: {"waiting": S.INITIALISING, "reinitialised": S.CONFIRMING, "search_due": S.SEARCHING,
                     "unseen": S.INITIALISING, "capped": S.CONFIRMING, "ok": S.TRACKING, "not_ok": S.SUSPECT},
    S.TRACKING: {"reinitialised": S.CONFIRMING, "search_due": S.SEARCHING, "unseen": S.OCCLUDED,
                 "capped": S.CONFIRMING, "ok": S.TRACKING, "not_ok": S.SUSPECT},
    S.OCCLUDED: {"reinitialised": S.CONFIRMING, "search_due": S.SEARCHING, "unseen": S.OCCLUDED,
                 "capped": S.CONFIRMING, "ok": S.TRACKING, "not_ok": S.SUSPECT},
    S.SUSPECT: {"reinitialised": S.CONFIRMING, "search_due": S.SEARCHING, "unseen": S.OCCLUDED,
                "capped": S.CONFIRMING, "ok": S.TRACKING, "not_ok": S.SUSPECT},
    S.SEARCHING: {"reinitialised": S.CONFIRMING, "search_due": S.SEARCHING, "unseen": S.SEARCHING,
                  "capped": S.CONFIRMING, "ok": S.TRACKING, "not_ok": S.SUSPECT},
    S.CONFIRMING: {"reinitialised": S.CONFIRMING, "search_due": S.SEARCHING, "unseen": S.CONFIRMING,
                   "capped": S.CONFIRMING, "ok": S.TRACKING, "not_ok": S.CONFIRMING},
}
"""Notes on the table: ``unseen`` keeps ``searching`` and ``confirming`` (a hand over the bone does not
end a search or confirm a found pose); ``not_ok`` keeps ``confirming`` while the recovery still
awaits the found pose's evidence; ``ok`` is reached from every state but ``initialising`` waiting."""


def event(status: str, weighed: bool, reinitialised: bool, pending: bool, capped: bool, waiting: bool) -> str:
    """The frame's one event (module docstring), the first that applies."""
    if waiting:
        return "waiting"
    if reinitialised:
        return "reinitialised"
    if pending:
        return "search_due"
    if capped:
        return "capped"
    if status == "ok":
        return "ok"
    if not weighed:
        return "unseen"
    return "not_ok"


class Lifecycle:
    """The current state and its history's counts (for the summaries)."""

    def __init__(self, state: State = State.INITIALISING):
        self.state = State(state)
        self.counts: dict[str, int] = {s.value: 0 for s in State}

    def step(self, name: str) -> State:
        """Apply one event (one of EVENTS); a pair the table does not hold raises ValueError."""
        if name not in EVENTS:
            raise ValueError(f"unknown lifecycle event {name!r}; expected one of {', '.join(EVENTS)}")
        nxt = TRANSITIONS[self.state].get(name)
        if nxt is None:
            raise ValueError(f"the lifecycle has no transition from {self.state.value} on {name!r}")
        self.state = nxt
        self.counts[nxt.value] += 1
        return nxt

    def update(self, result, recovery, reinitialised: bool) -> State:
        """The state of a tracked frame from the tracker's result (status, weighed) and the recovery policy
        (its pending re-initialisation, its cap on ok); a frame before the start steps ``waiting``."""
        pending = recovery is not None and recovery.pending is not None
        capped = recovery is not None and bool(recovery.capped)
        return self.step(event(str(result.status), bool(result.weighed), bool(reinitialised), pending, capped,
                               waiting=False))


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
