"""Tracking status rules."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest

from app.filter.status import StatusInputs, StatusThresholds, TrackingStatus, classify, lost_reasons, uncertain_reasons

GOOD = StatusInputs(position_spread=0.001, rotation_spread=math.radians(0.5), ess_ratio=0.3,
                    inlier_fraction=0.9, covered_pixels=400, n_nan=0, n_particles=200, weighed=True,
                    seconds_without_pose=0.0)


def test_a_tight_well_supported_track_is_ok():
    assert classify(GOOD) == TrackingStatus.OK
    assert classify(GOOD) == "ok"  # compares equal to its string


@pytest.mark.parametrize("change", [
    {"position_spread": 0.004}, {"rotation_spread": math.radians(3)}, {"inlier_fraction": 0.6},
    {"covered_pixels": 10, "inlier_fraction": 0.0}, {"n_nan": 3}, {"weighed": False},
    {"weighed": False, "seconds_without_pose": 0.3},
])
def test_weak_evidence_is_uncertain(change):
    assert classify(replace(GOOD, **change)) == TrackingStatus.UNCERTAIN


@pytest.mark.parametrize("change", [
    {"position_spread": 0.011}, {"rotation_spread": math.radians(11)}, {"inlier_fraction": 0.1},
    {"weighed": False, "seconds_without_pose": 0.6}, {"n_nan": 200}, {"position_spread": float("nan")},
])
def test_no_evidence_or_a_wide_cloud_is_lost(change):
    assert classify(replace(GOOD, **change)) == TrackingStatus.LOST


def test_low_inliers_without_enough_covered_pixels_is_not_lost():
    s = replace(GOOD, covered_pixels=5, inlier_fraction=0.0)
    assert lost_reasons(s, StatusThresholds()) == []


def test_thresholds_are_configurable():
    loose = StatusThresholds(uncertain_position_spread=0.005)
    assert classify(replace(GOOD, position_spread=0.004), loose) == TrackingStatus.OK
    strict = StatusThresholds(min_ess_ratio=0.5)
    assert classify(GOOD, strict) == TrackingStatus.UNCERTAIN


def test_too_few_visible_pixels_for_the_image_is_not_ok_even_when_they_all_fit():
    """48 fitting pixels of an 80x60 image (1 %) are too little evidence; 400 (8 %) are enough."""
    few = replace(GOOD, covered_pixels=48, inlier_fraction=1.0, image_pixels=80 * 60)
    assert classify(few) == TrackingStatus.UNCERTAIN
    assert any("too little evidence" in r for r in uncertain_reasons(few, StatusThresholds()))
    assert classify(replace(few, covered_pixels=400)) == TrackingStatus.OK
    assert classify(replace(few, image_pixels=0)) == TrackingStatus.OK      # rule off without an image size
