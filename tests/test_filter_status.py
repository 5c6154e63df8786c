"""Tracking status rules."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest

from app.filter.status import StatusInputs, StatusThresholds, TrackingStatus, classify, lost_reasons, uncertain_reasons

GOOD = StatusInputs(position_spread=0.001, rotation_spread=math.radians(0.5), ess_ratio=0.3,
                    inlier_fraction=0.9, covered_pixels=400, n_nan=0, n_particles=200, weighed=True,
                    seconds_without_pose=0.0, template_spread=0.002)


def test_a_tight_well_supported_track_is_ok():
    assert classify(GOOD) == TrackingStatus.OK
    assert classify(GOOD) == "ok"  # compares equal to its string


@pytest.mark.parametrize("change", [
    {"covered_pixels": 10, "inlier_fraction": 0.0}, {"n_nan": 3}, {"weighed": False},
    {"weighed": False, "seconds_without_pose": 0.3},
])
def test_weak_evidence_is_uncertain(change):
    assert classify(replace(GOOD, **change)) == TrackingStatus.UNCERTAIN


@pytest.mark.parametrize("change", [
    {"template_spread": 0.006}, {"inlier_fraction": 0.1},
    {"weighed": False, "seconds_without_pose": 1.1}, {"n_nan": 200}, {"template_spread": float("nan")},
])
def test_no_evidence_or_a_wide_cloud_is_lost(change):
    assert classify(replace(GOOD, **change)) == TrackingStatus.LOST


def test_without_a_camera_pose_the_track_is_lost_after_the_lifecycles_patience(tmp_path):
    """Issue 32: one patience with a track that is not ok: a frame without a camera pose is uncertain, and lost
    once recovery.after_uncertain_s has passed without one (status.lost_no_pose_s, 0.5 s, is gone: a key names
    its replacement); the configuration ties the two, also when only the recovery's value is set."""
    from app.config import TrackerConfig, config_from_dict
    from app.errors import ConfigError
    from app.filter.recovery import RecoveryConfig

    assert TrackerConfig().status.lost_no_pose_s == RecoveryConfig().after_uncertain_s == 1.0
    config = config_from_dict({"recovery": {"after_uncertain_s": 0.4}})
    assert config.status.lost_no_pose_s == 0.4
    blind = replace(GOOD, weighed=False)
    assert classify(replace(blind, seconds_without_pose=0.39), config.status) == TrackingStatus.UNCERTAIN
    assert classify(replace(blind, seconds_without_pose=0.41), config.status) == TrackingStatus.LOST
    assert classify(replace(blind, seconds_without_pose=0.9), TrackerConfig().status) == TrackingStatus.UNCERTAIN
    assert replace(config, recovery=RecoveryConfig(after_uncertain_s=0.0)).status.lost_no_pose_s == 0.0
    with pytest.raises(ConfigError, match="recovery.after_uncertain_s"):
        config_from_dict({"status": {"lost_no_pose_s": 0.5}})


def test_low_inliers_without_enough_covered_pixels_is_not_lost():
    s = replace(GOOD, covered_pixels=5, inlier_fraction=0.0)
    assert lost_reasons(s, StatusThresholds()) == []


def test_a_spread_below_the_lost_one_does_not_lower_the_status():
    """Issue 32: the template's predicted error (the refinement's) says how precise the output is; the cloud's
    spread of a few mm / deg only gates the feedback (refine.feedback_spread); the template's points spread
    5 mm over the particles, two answers apart (refine.competitor_distance), is lost."""
    assert classify(replace(GOOD, position_spread=0.004, rotation_spread=math.radians(3),
                            template_spread=0.0045)) == TrackingStatus.OK
    assert classify(replace(GOOD, template_spread=0.0055)) == TrackingStatus.LOST


def test_the_lost_spread_is_the_distance_between_two_answers():
    """Issue 32, merge 10: status.lost_spread is gone; the configuration ties the lost spread to
    refine.competitor_distance, also when only that key is set."""
    from app.config import config_from_dict

    config = config_from_dict({"refine": {"competitor_distance": 0.008}})
    assert config.status.lost_spread == 0.008
    assert classify(replace(GOOD, template_spread=0.0075), config.status) == TrackingStatus.OK
    assert classify(replace(GOOD, template_spread=0.0085), config.status) == TrackingStatus.LOST


def test_thresholds_are_configurable():
    loose = StatusThresholds(lost_spread=0.02)
    assert classify(replace(GOOD, template_spread=0.011), loose) == TrackingStatus.OK
    strict = StatusThresholds(min_covered_pixels=500)
    assert classify(GOOD, strict) == TrackingStatus.UNCERTAIN


def test_the_filter_alone_has_no_share_fitted_to_one_simulator():
    """Issue 32: a 60 % inlier share, a small ESS and 48 pixels of an 80x60 image no longer lower the filter's
    status (its former uncertain_inlier_fraction, min_ess_ratio, min_ok_fraction); the refinement's tests
    decide ok, and without the refinement no frame is ok (tests/test_tracker_refine.py)."""
    weak = replace(GOOD, inlier_fraction=0.6, ess_ratio=0.001, covered_pixels=48)
    assert uncertain_reasons(weak, StatusThresholds()) == []
    assert classify(replace(weak, inlier_fraction=0.1)) == TrackingStatus.LOST     # the lost rule stays


def test_without_the_refinement_an_ok_frame_is_uncertain_and_says_why():
    """Issue 32: the seen test (the template's predicted error) needs the refinement; refine.enabled: false
    leaves every frame at most uncertain, with the code not_refined (app/pipeline/tracker.py)."""
    import numpy as np

    from app.filter.particle_filter import FilterOutput
    from app.pipeline.tracker import _unrefined

    def output(status):
        return FilterOutput(T_base_bone=np.eye(4), position_spread=0.001, rotation_spread=0.01, ess=50.0,
                            ess_ratio=0.25, log_likelihood_max=0.0, status=status, inlier_fraction=0.9,
                            covered_pixels=400, n_nan=0, resampled=False, dt=0.011, weighed=True, timings={})

    out = _unrefined(output(TrackingStatus.OK))
    assert out.status == TrackingStatus.UNCERTAIN and [r.code for r in out.reasons] == ["not_refined"]
    assert _unrefined(output(TrackingStatus.LOST)).status == TrackingStatus.LOST


def test_the_template_spread_is_exact_where_it_decides_and_its_bound_elsewhere():
    """app/filter/estimate.py template_spread: two equally weighted particles turned by -θ and +θ about z, a point
    at r on x: its images lie 2 r sin θ apart, so its RMS distance to their mean is r sin θ; with the position
    spread added the bound σ_p + σ_r r holds; within the limit the bound itself is returned."""
    import numpy as np

    from app.filter.estimate import estimate, template_spread
    from app.geometry import quaternion as quat

    theta, r = math.radians(10.0), 0.08
    q = quat.exp_map(np.array([[0.0, 0.0, -theta], [0.0, 0.0, theta]]))
    p = np.zeros((2, 3))
    lw = np.zeros(2)
    points = np.array([[r, 0.0, 0.0], [0.0, 0.0, r]])        # the second lies on the axis: it does not move
    pose = estimate(p, q, lw)
    exact = template_spread(p, q, lw, points, pose, limit=0.001)
    assert exact == pytest.approx(r * math.sin(theta), rel=1e-9)
    assert exact <= pose.position_spread + pose.rotation_spread * r
    assert template_spread(p, q, lw, points, pose, limit=1.0) == pytest.approx(pose.rotation_spread * r)   # the bound
    shifted = p + np.array([[0.0, 0.0, -0.003], [0.0, 0.0, 0.003]])   # plus 3 mm along z each way
    pose = estimate(shifted, q, lw)
    assert template_spread(shifted, q, lw, points, pose, limit=0.001) == pytest.approx(
        math.hypot(r * math.sin(theta), 0.003), rel=1e-9)


def test_the_template_spread_is_the_largest_over_every_point():
    """The closed form (app/filter/estimate.py template_spread) against the definition, point by point, on
    random particles and 300 random points: the same largest spread (it took 64 of the points before)."""
    import numpy as np

    from app.filter.estimate import estimate, template_spread
    from app.geometry import quaternion as quat

    rng = np.random.default_rng(7)
    for _ in range(5):
        n = 200
        q = quat.exp_map(rng.normal(0.0, 0.1, (n, 3)))
        p = rng.normal(0.0, 0.004, (n, 3))
        lw = rng.normal(0.0, 1.0, n)
        points = rng.normal(0.0, 0.04, (300, 3))
        pose = estimate(p, q, lw)
        W = np.exp(lw - lw.max())
        W /= W.sum()
        x = np.einsum("nij,mj->nmi", quat.to_matrix(q), points) + p[:, None, :]
        d = x - np.einsum("n,nmi->mi", W, x)[None]
        definition = np.sqrt(np.einsum("n,nmi,nmi->m", W, d, d))
        assert template_spread(p, q, lw, points, pose, limit=0.0) == pytest.approx(definition.max(), rel=1e-9)


def test_a_new_tracks_unfinished_nearby_search_keeps_the_status_below_ok():
    """RefinementEvidence.nearby_unanswered (the first nearby search spread over frames,
    refine.nearby_per_frame): not ok, reason ambiguous, until it has answered; never raised."""
    from app.filter.status import RefinementEvidence, refinement_reasons, with_refinement

    good = RefinementEvidence(0.9, 5e-4, False, -0.01, float("nan"), float("nan"))
    t = StatusThresholds()
    assert with_refinement(TrackingStatus.OK, good, t) == TrackingStatus.OK
    waiting = replace(good, nearby_unanswered=True)
    assert with_refinement(TrackingStatus.OK, waiting, t) == TrackingStatus.UNCERTAIN
    assert [r.code for r in refinement_reasons(waiting, t)] == ["ambiguous"]
    assert with_refinement(TrackingStatus.LOST, waiting, t) == TrackingStatus.LOST
