"""Issue 32: one level (status.alpha) for every statistical test of the status and the lifecycle
(app/tracking/levels.py): its critical values against printed tables, and the configuration reaching each test."""
import numpy as np
import pytest

from app.config import config_from_dict
from app.errors import ConfigError
from app.pipeline.recovery_runner import _policy
from app.pipeline.tracker import refine_params
from app.filter.status import RefinementEvidence, StatusThresholds, TrackingStatus, with_refinement
from app.tracking import levels


@pytest.mark.parametrize("dof, p, x", [(1, 0.05, 3.841), (3, 0.001, 16.266), (6, 0.001, 22.458), (6, 0.05, 12.592),
                                      (2, 0.01, 9.210), (5, 0.01, 15.086)])
def test_chi2_points_match_the_printed_table(dof, p, x):
    """Abramowitz & Stegun table 26.8 (upper percentage points of χ²)."""
    assert levels.chi2_level(p, dof) == pytest.approx(x, abs=1e-3)
    assert levels.chi2_sf(x, dof) == pytest.approx(p, rel=2e-3)


def test_the_default_level_is_three_sigma_one_sided():
    assert levels.ALPHA == pytest.approx(0.0013499, abs=1e-7)
    assert levels.normal_level(levels.ALPHA) == pytest.approx(3.0, abs=1e-12)
    assert levels.chi_level(levels.ALPHA, 3) == pytest.approx(3.9536, abs=1e-4)
    assert levels.held_level(levels.ALPHA, 6.0) == pytest.approx(3.6232, abs=1e-4)


def test_one_alpha_sets_the_behind_held_and_start_tests():
    """alpha 0.001: the behind test at 3.09 sd, the held bound χ²₆ 22.46 / 6, the start's prior at 4.03 sigmas."""
    c = config_from_dict({"status": {"alpha": 0.001}})
    assert refine_params(c).behind_z == pytest.approx(3.0902, abs=1e-4)
    assert _policy(c, np.eye(3), 0.5).start_level == pytest.approx(4.0331, abs=1e-4)
    t = StatusThresholds(alpha=0.001)
    held = 22.458 / t.covariance_inflation
    assert with_refinement(TrackingStatus.OK, RefinementEvidence(0.9, 0.0003, False, 0.0, held - 0.01), t) == "ok"
    assert with_refinement(TrackingStatus.OK, RefinementEvidence(0.9, 0.0003, False, 0.0, held + 0.01), t) == "uncertain"


@pytest.mark.parametrize("old", ["refine.behind_z", "status.max_held_chi2", "recovery.start_sigmas"])
def test_the_former_levels_name_alpha(old):
    section, name = old.split(".")
    with pytest.raises(ConfigError, match=rf"{old}.*replaced by status\.alpha"):
        config_from_dict({section: {name: 3.0}})


def test_alpha_must_be_a_probability_below_one_half():
    with pytest.raises(ConfigError, match="status.alpha"):
        config_from_dict({"status": {"alpha": 0.0}})
    with pytest.raises(ConfigError, match="status.alpha"):
        config_from_dict({"status": {"alpha": 0.7}})
    assert config_from_dict({"status": {"alpha": 0.01}}).status.alpha == 0.01


def test_the_search_bar_is_the_fitness_bar_at_one_sigma(monkeypatch):
    """Issue 32, merge 12 (recovery.search_min_sharp merged into status.min_fitness): the share within 1 sigma that
    goes with a share within 3 sigma for Gaussian residuals, 0.6 x 0.682689 / 0.997300 (the normal table's
    P(|Z| < 1) and P(|Z| < 3)); the wide search built from a config takes it from status.min_fitness."""
    import app.filter.wide_search as wide_search
    from app.pipeline.recovery_runner import build_wide_search

    assert levels.sharp_bar(0.6) == pytest.approx(0.6 * 0.682689 / 0.997300, abs=1e-6)
    assert wide_search.MIN_SHARP == levels.sharp_bar(0.6) == pytest.approx(0.41072, abs=1e-5)
    assert levels.sharp_bar(0.6, 3.0, 3.0) == pytest.approx(0.6)
    monkeypatch.setattr(wide_search, "WideSearch", lambda *args: args[-1])     # the search's config, not a search
    search = build_wide_search(config_from_dict({"status": {"min_fitness": 0.7}}), None, None, None, None)
    assert search.min_fitness == 0.7 and search.min_sharp == pytest.approx(0.7 * 0.682689 / 0.997300, abs=1e-6)
