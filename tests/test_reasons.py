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
    used |= {"holding", "confirming"}                     # the recovery's caps (app/filter/recovery.py)
    assert used and used <= set(reasons.REASONS), used - set(reasons.REASONS)


def test_each_failed_rule_gives_its_code():
    good = status.StatusInputs(0.001, 0.01, 0.5, 0.95, 400, 0, 100, True, 0.0)
    assert status.verdict(good) == (status.TrackingStatus.OK, [])
    moving = status.verdict(status.StatusInputs(0.001, 0.01, 0.5, 0.95, 400, 0, 100, True, 0.0, speed=0.1))
    assert moving[0] == "uncertain" and status.codes(moving[1]) == ("moving",)
    lost = status.verdict(status.StatusInputs(0.02, 0.01, 0.5, 0.95, 400, 0, 100, True, 1.0))
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


def test_the_lifecycle_table_has_every_event_from_every_state_but_waiting():
    for state, row in lifecycle.TRANSITIONS.items():
        expected = set(lifecycle.EVENTS) - ({"waiting"} if state != lifecycle.State.INITIALISING else set())
        assert set(row) == expected, state


def test_the_lifecycle_walks_a_recovery():
    life = lifecycle.Lifecycle()
    walk = ["ok", "unseen", "unseen", "not_ok", "search_due", "unseen", "reinitialised", "capped", "not_ok", "ok"]
    states = [life.step(e).value for e in walk]
    assert states == ["tracking", "occluded", "occluded", "suspect", "searching", "searching", "confirming",
                      "confirming", "confirming", "tracking"]
    assert life.counts["confirming"] == 3
    with pytest.raises(ValueError, match="no transition from tracking on 'waiting'"):
        life.step("waiting")
    with pytest.raises(ValueError, match="unknown lifecycle event"):
        life.step("bogus")


@pytest.mark.parametrize("facts, expected", [
    (dict(status="ok", weighed=True, reinitialised=False, pending=False, capped=False, waiting=False), "ok"),
    (dict(status="ok", weighed=True, reinitialised=False, pending=False, capped=True, waiting=False), "capped"),
    (dict(status="uncertain", weighed=False, reinitialised=False, pending=False, capped=False, waiting=False), "unseen"),
    (dict(status="uncertain", weighed=True, reinitialised=False, pending=True, capped=False, waiting=False), "search_due"),
    (dict(status="uncertain", weighed=True, reinitialised=True, pending=True, capped=False, waiting=False), "reinitialised"),
    (dict(status="lost", weighed=True, reinitialised=False, pending=False, capped=False, waiting=False), "not_ok"),
])
def test_one_event_per_frame_the_first_that_applies(facts, expected):
    assert lifecycle.event(**facts) == expected


def test_the_printed_summary_says_why_the_template_was_not_shown():
    from app.pipeline.report import summary_rows
    summary = {"frames": 10, "processing_rate_hz": 30.0, "particles": 200, "resolution": [160, 120],
               "sampling": "joint", "gl": "cpu", "status_fraction": {"ok": 0.5, "uncertain": 0.5, "lost": 0.0},
               "blocked_by": {"imprecise": 0.42, "moving": 0.03}}
    rows = dict(summary_rows(summary))
    assert rows["not ok because (share of frames)"] == "imprecise 42 %, moving 3 %"
    del summary["blocked_by"]
    assert "not ok because (share of frames)" not in dict(summary_rows(summary))
