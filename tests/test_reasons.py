"""The reason codes and the lifecycle: every code the tracker emits is in the table, the README shows
the table and the lifecycle diagram as the code has them, and the lifecycle's table is complete."""
import re
from pathlib import Path

import pytest

from app.filter import status
from app.tracking import lifecycle, reasons

REPO = Path(__file__).resolve().parents[1]


def test_the_readme_shows_the_reason_table_and_the_lifecycle_as_the_code_has_them():
    readme = (REPO / "README.md").read_text()
    assert reasons.markdown_table() in readme
    assert lifecycle.mermaid() in readme


def test_every_code_in_the_sources_is_in_the_table():
    used = set()
    for path in (REPO / "app").rglob("*.py"):
        used |= set(re.findall(r'Reason\("([a-z_]+)"', path.read_text()))
    used |= {"confirming"}                                # the recovery's cap (app/filter/recovery.py)
    assert used and used <= set(reasons.REASONS), used - set(reasons.REASONS)


def test_each_failed_rule_gives_its_code():
    good = status.StatusInputs(0.001, 0.01, 0.5, 0.95, 400, 0, 100, True, 0.0, template_spread=0.002)
    assert status.verdict(good) == (status.TrackingStatus.OK, [])
    moving = status.verdict(status.StatusInputs(0.001, 0.01, 0.5, 0.95, 400, 0, 100, True, 0.0, speed=0.1, template_spread=0.002))
    assert moving[0] == "uncertain" and status.codes(moving[1]) == ("moving",)
    lost = status.verdict(status.StatusInputs(0.02, 0.01, 0.5, 0.95, 400, 0, 100, True, 1.5, template_spread=0.02))
    assert lost[0] == "lost" and status.codes(lost[1]) == ("no_pose", "spread")
    evidence = status.RefinementEvidence(0.3, 0.002, True, 0.01, 9.0, 0.002)
    got = status.codes(status.refinement_reasons(evidence, status.StatusThresholds()))
    assert got == ("unconfirmed", "imprecise", "ambiguous", "behind", "held")


def test_a_reason_keeps_its_code_through_pickling():
    import pickle
    r = pickle.loads(pickle.dumps(status.Reason("behind", "1 % behind")))
    assert r == "1 % behind" and r.code == "behind"


def test_reason_shares_count_each_frame_once_per_code():
    shares = reasons.reason_shares([("behind", "moving"), ("behind",), (), ()], ["suspect", "suspect", "tracking", ""])
    assert shares["blocked_by"] == {"behind": 0.5, "moving": 0.25}
    assert shares["state_fraction"] == {"suspect": 0.5, "tracking": 0.25}


def test_the_lifecycle_table_is_the_contract():
    T, S = lifecycle.TRANSITIONS, lifecycle.State
    assert set(T) == set(S)
    assert all(set(row) <= set(lifecycle.EVENTS) for row in T.values())
    assert all(row["ok"] == S.TRACKING for row in T.values())                     # ok (confirmed) from every state
    for name in lifecycle.RECOVERY_EVENTS:                                         # only searching runs an attempt
        where = {"detected": [S.INITIALISING], "moved": [S.TRACKING, S.OCCLUDED, S.SUSPECT, S.SEARCHING]}.get(name, [S.SEARCHING])
        assert [s for s, row in T.items() if name in row] == where
    for state in (S.SEARCHING, S.CONFIRMING):                                      # a hand does not end a search
        assert T[state]["unseen"] == T[state]["not_ok"] == state
    assert [s for s, row in T.items() if "capped" in row] == [S.SEARCHING, S.CONFIRMING]   # only with a hypothesis


def test_the_lifecycle_walks_a_recovery():
    life = lifecycle.Lifecycle()
    states = [life.frame(e).value for e in ["ok", "unseen", "unseen", "not_ok"]]
    life.passed()
    life.search_due("lost for 10 frames")
    assert life.due == "lost for 10 frames" and not life.retrying
    states += [life.frame(e).value for e in ["search_due", "unseen"]]
    life.declined()
    assert life.retrying and life.state == "searching"
    life.search_due("still searching")
    life.reinitialised()
    assert life.due is None and life.hypothesis is not None and not life.hypothesis.evidence_only
    states += [life.frame(e).value for e in ["capped", "not_ok", "unseen"]]
    life.passed()
    states.append(life.frame("ok").value)
    assert states == ["tracking", "occluded", "occluded", "suspect", "searching", "searching", "confirming",
                      "confirming", "confirming", "tracking"]
    assert life.counts["confirming"] == 3 and life.hypothesis is None and life.ever_ok
    with pytest.raises(ValueError, match="no transition from tracking on 'waiting'"):
        life.frame("waiting")
    with pytest.raises(ValueError, match="no transition from tracking on 'reinitialised'"):
        life.reinitialised()                                         # an attempt runs only when one is due
    with pytest.raises(ValueError, match="unknown lifecycle event"):
        life.step("bogus")


def test_a_kept_track_is_retried_only_if_it_was_ever_ok_and_a_detected_start_stays_evidence_only():
    never = lifecycle.Lifecycle()
    never.detected()
    assert never.state == "confirming" and never.hypothesis.evidence_only
    never.search_due("never ok: one wide search")
    never.kept()
    assert never.state == "confirming" and never.hypothesis.evidence_only        # its one search is spent
    never.search_due("not ok, far")
    never.reinitialised()
    assert never.hypothesis.evidence_only                                      # still a detected start's hypothesis
    was_ok = lifecycle.Lifecycle()
    was_ok.frame("ok")
    was_ok.passed()
    was_ok.search_due("not ok, far")
    was_ok.kept()
    assert was_ok.retrying and was_ok.hypothesis is not None and not was_ok.hypothesis.evidence_only


@pytest.mark.parametrize("facts, expected", [
    (dict(status="ok", weighed=True, due=False, capped=False), "ok"),
    (dict(status="ok", weighed=True, due=False, capped=True), "capped"),
    (dict(status="uncertain", weighed=False, due=False, capped=False), "unseen"),
    (dict(status="uncertain", weighed=True, due=True, capped=False), "search_due"),
    (dict(status="ok", weighed=True, due=True, capped=False), "search_due"),
    (dict(status="lost", weighed=True, due=False, capped=False), "not_ok"),
    (dict(status="lost", weighed=False, due=False, capped=False, waiting=True), "waiting"),
])
def test_one_event_per_frame_the_first_that_applies(facts, expected):
    assert lifecycle.frame_event(**facts) == expected


def test_the_readme_shows_the_triggers_in_their_order():
    from app.tracking import triggers

    readme = (REPO / "README.md").read_text()
    assert triggers.markdown_table() in readme
    assert len(set(triggers.CODES)) == len(triggers.TRIGGERS) == 9
