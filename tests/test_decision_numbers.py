"""Issue 32, Deliver 4: every decision number is in configs/default.yaml with its unit and how it was
chosen; the README shows the table and the count as scripts/decision_numbers.py prints them; the keys
merged as exact duplicates name the key that replaced them."""
import subprocess
import sys
from pathlib import Path

import pytest

from app import decision_numbers
from app.config import KEYS, TrackerConfig, config_from_dict
from app.errors import ConfigError
from app.filter.recovery import RecoveryPolicy
from app.filter.refine_track import RefineConfig
from app.filter.status import StatusThresholds

REPO = Path(__file__).resolve().parents[1]


def test_the_readme_shows_the_decision_numbers_as_the_script_prints_them():
    table = decision_numbers.markdown_table()
    assert table in (REPO / "README.md").read_text()
    printed = subprocess.run([sys.executable, str(REPO / "scripts" / "decision_numbers.py")], capture_output=True,
                             text=True, check=True).stdout
    assert printed.strip() == table.strip()
    assert subprocess.run([sys.executable, str(REPO / "scripts" / "decision_numbers.py"), "--check",
                           str(REPO / "README.md")], capture_output=True).returncode == 0


def test_the_count_is_the_tables_rows_and_benchmarks_states_it():
    table = decision_numbers.markdown_table()
    counts = decision_numbers.counts()
    rows = [r for r in table.splitlines() if r.startswith("| `")]
    counted = [r for r in rows if r.split(" | ")[3] in decision_numbers.COUNTED]
    assert len(counted) == counts["status+lifecycle"]
    assert f"**{counts['status+lifecycle']}** decision numbers" in table
    assert f"**{counts['status+lifecycle']}** status and lifecycle decision numbers" in (REPO / "BENCHMARKS.md").read_text()


def test_every_number_of_status_refine_and_recovery_is_a_key_with_a_kind():
    nums = decision_numbers.numbers()
    numeric = {k for k, spec in KEYS.items() if k.split(".")[0] in decision_numbers.SECTIONS
               and spec.kind in ("int", "float")}
    assert {n.key for n in nums} == numeric
    for n in nums:
        if n.kind in decision_numbers.DECISIONS:
            assert n.unit and n.chosen, n


def test_a_number_without_its_kind_is_refused(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("status:\n  min_fitness: 0.6   # ok needs this share\n")
    with pytest.raises(ValueError, match=r"status\.min_fitness has no kind"):
        decision_numbers.numbers(path)
    path.write_text("status:\n  min_fitness: 0.6   # ok needs this share [status]\n")
    with pytest.raises(ValueError, match=r"status\.min_fitness is a decision: write \[status, UNIT"):
        decision_numbers.numbers(path)


@pytest.mark.parametrize("old, new", [
    ("recovery.far_m", "refine.competitor_distance"),
    ("recovery.far_angle", "refine.competitor_distance"),
    ("refine.competitor_angle", "refine.competitor_distance"),
    ("refine.competitor_margin", "refine.nearby_margin"),
    ("recovery.min_visible_share", "status.min_fitness"),
    ("recovery.max_backoff_doublings", "recovery.after_uncertain_s"),
    ("status.lost_position_spread", "status.lost_spread"),
    ("status.lost_rotation_spread", "status.lost_spread"),
    ("recovery.never_ok_search_s", "recovery.after_uncertain_s"),
    ("refine.nearby_gap", "status.max_template_std"),
    ("refine.feedback_fitness", "status.min_fitness"),
    ("status.uncertain_inlier_fraction", "the refinement's consistency test"),
    ("status.min_ok_fraction", "status.max_template_std"),
    ("status.min_ess_ratio", "status.max_template_std"),
    ("recovery.kept_move_m", "status.max_template_std"),
    ("recovery.kept_move_angle", "status.max_template_std"),
    ("status.uncertain_position_spread", "status.max_template_std.*refine.feedback_spread"),
    ("status.uncertain_rotation_spread", "status.max_template_std.*refine.feedback_spread_angle"),
    ("status.uncertain_angular_speed", "status.uncertain_speed"),
    ("recovery.hold_frames", "status.settle_s"),
    ("recovery.cooldown_s", "recovery.after_lost_s"),
    ("status.lost_no_pose_s", "recovery.after_uncertain_s"),
    ("status.lost_spread", "refine.competitor_distance"),
    ("recovery.search_retry_s", "status.settle_s"),
    ("recovery.search_min_sharp", "status.min_fitness"),
])
def test_a_merged_key_names_the_key_that_replaced_it(old, new):
    section, name = old.split(".")
    with pytest.raises(ConfigError, match=rf"{old}.*replaced by {new}"):
        config_from_dict({section: {name: 0.001}})


def test_a_removed_key_says_so():
    with pytest.raises(ConfigError, match=r"refine.nearby_followups.*removed \(issue 32\)"):
        config_from_dict({"refine": {"nearby_followups": 3}})


def test_the_merged_numbers_are_the_ones_they_replaced():
    """The values each removed key had (5 mm / 5 deg, 1 s, 1 mm, 0.6) are its replacement's defaults, and
    the code reads the replacement (so the defaults' behaviour is unchanged: BENCHMARKS.md's replays)."""
    c = TrackerConfig()
    assert c.refine.competitor_distance == 0.005
    assert c.recovery.after_uncertain_s == 1.0
    assert c.status.max_template_std == 0.001 and c.status.min_fitness == 0.6
    policy = RecoveryPolicy(c.recovery, [0, 0, 0], [0, 0, 0], True)
    assert policy.far == RefineConfig.competitor_distance
    assert c.status.lost_spread == c.refine.competitor_distance == 0.005   # tied since merge 10
    assert StatusThresholds().max_template_std == 0.001


def test_the_decision_numbers_still_in_code_exist_there():
    for file, name, *_ in decision_numbers.IN_CODE:
        assert f"\n{name} = " in (REPO / file).read_text(), (file, name)
    for file, name, *_ in decision_numbers.MEASURES_IN_CODE:
        assert name in (REPO / file).read_text(), (file, name)
