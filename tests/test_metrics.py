"""Pose error metrics (app/metrics.py) against hand-computed cases."""
from __future__ import annotations

import numpy as np
import pytest

from app import metrics
from app.geometry import se3


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    return se3.make_pose(np.asarray(R, dtype=float), np.asarray(t, dtype=float))


@pytest.fixture
def points():
    return np.random.default_rng(0).normal(0.0, 0.03, (500, 3))


@pytest.fixture
def T_gt():
    return _pose(_rot_z(0.7), (0.1, -0.2, 0.4))


def test_identical_poses_give_zero_for_every_metric(points, T_gt):
    assert metrics.add(T_gt, T_gt, points) == pytest.approx(0.0, abs=1e-12)
    assert metrics.add_s(T_gt, T_gt, points) == pytest.approx(0.0, abs=1e-12)
    assert metrics.mdd(T_gt, T_gt, points) == pytest.approx(0.0, abs=1e-12)
    assert metrics.mdd_s(T_gt, T_gt, points) == pytest.approx(0.0, abs=1e-12)
    assert metrics.translation_error(T_gt, T_gt) == pytest.approx(0.0, abs=1e-12)
    assert metrics.rotation_error(T_gt, T_gt) == pytest.approx(0.0, abs=1e-6)


def test_one_millimetre_shift_gives_one_millimetre_add_mdd_and_translation(points, T_gt):
    T_est = T_gt.copy()
    T_est[:3, 3] += np.array([0.0, 0.6e-3, 0.8e-3])   # |shift| = 1 mm
    assert metrics.add(T_est, T_gt, points) == pytest.approx(1e-3, rel=1e-9)
    assert metrics.mdd(T_est, T_gt, points) == pytest.approx(1e-3, rel=1e-9)
    assert metrics.translation_error(T_est, T_gt) == pytest.approx(1e-3, rel=1e-9)
    assert metrics.rotation_error(T_est, T_gt) == pytest.approx(0.0, abs=1e-6)
    # ADD-S / MDD-S never exceed ADD / MDD (the closest point is at most the corresponding one)
    assert metrics.add_s(T_est, T_gt, points) <= 1e-3 + 1e-12
    assert metrics.mdd_s(T_est, T_gt, points) <= 1e-3 + 1e-12


def test_rotation_about_the_origin_gives_hand_computed_add_and_mdd():
    # four points on a circle of radius r about z; a rotation by a about z moves each by 2 r sin(a/2)
    r, a = 0.05, np.deg2rad(10.0)
    points = r * np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]])
    T_est = _pose(_rot_z(a))
    expected = 2 * r * np.sin(a / 2)
    assert metrics.add(T_est, np.eye(4), points) == pytest.approx(expected, rel=1e-12)
    assert metrics.mdd(T_est, np.eye(4), points) == pytest.approx(expected, rel=1e-12)
    assert np.rad2deg(metrics.rotation_error(T_est, np.eye(4))) == pytest.approx(10.0, rel=1e-6)


def test_symmetric_object_flip_gives_zero_add_s_but_large_add():
    # a square in the xy plane is symmetric under a 90 deg turn about z: the vertices swap places
    points = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]]) * 0.04
    T_gt = _pose(np.eye(3), (0.0, 0.0, 0.3))
    T_flip = T_gt @ _pose(_rot_z(np.pi / 2))
    assert metrics.add_s(T_flip, T_gt, points) == pytest.approx(0.0, abs=1e-12)
    assert metrics.mdd_s(T_flip, T_gt, points) == pytest.approx(0.0, abs=1e-12)
    assert metrics.add(T_flip, T_gt, points) == pytest.approx(0.04 * np.sqrt(2), rel=1e-12)


def test_mdd_s_is_the_largest_closest_point_distance():
    # two points; the estimate moves one of them 3 mm off the truth's surface and leaves the other
    points = np.array([[0.0, 0, 0], [0.1, 0, 0]])
    T_est = _pose(np.eye(3), (0.0, 0.0, 0.003))
    assert metrics.mdd_s(T_est, np.eye(4), points) == pytest.approx(0.003)
    assert metrics.add_s(T_est, np.eye(4), points) == pytest.approx(0.003)


def test_symmetric_errors_of_a_sequence_match_the_per_frame_functions(points):
    rng = np.random.default_rng(1)
    T_gt = np.stack([se3.from_rotvec_trans(rng.normal(0, 1, 3), rng.normal(0, 0.1, 3)) for _ in range(4)])
    T_est = T_gt @ np.stack([se3.from_rotvec_trans(rng.normal(0, 0.05, 3), rng.normal(0, 0.003, 3)) for _ in range(4)])
    add_s, mdd_s = metrics.symmetric_errors(T_est, T_gt, points)
    for k in range(4):
        assert add_s[k] == pytest.approx(metrics.add_s(T_est[k], T_gt[k], points), rel=1e-9)
        assert mdd_s[k] == pytest.approx(metrics.mdd_s(T_est[k], T_gt[k], points), rel=1e-9)


def test_vsd_of_identical_renderings_is_zero():
    depth = np.zeros((4, 5))
    depth[1:3, 1:4] = 0.5
    assert metrics.vsd(depth, depth, depth) == 0.0


def test_vsd_on_a_hand_built_depth_pair():
    # truth covers 6 pixels at 0.50 m; the estimate covers 4 of them (2 at 0.51 m: within tau, 2 at
    # 0.55 m: beyond tau) plus 2 pixels the truth does not cover. The measured depth is the truth's.
    # union = 8 px, intersection = 4 px (2 misaligned), symmetric difference = 4 px -> (2 + 4) / 8
    gt = np.zeros((3, 4))
    gt[0:2, 0:3] = 0.50
    est = np.zeros((3, 4))
    est[0, 0:2] = 0.51
    est[1, 0:2] = 0.55
    est[2, 0:2] = 0.50
    measured = gt.copy()
    measured[2, :] = 0.60                         # the table behind, where the estimate is wrongly
    assert metrics.vsd(est, gt, measured, tau=0.02) == pytest.approx(6 / 8)
    # a generous tau forgives the 5 cm misalignment: (0 + 4) / 8
    assert metrics.vsd(est, gt, measured, tau=0.06) == pytest.approx(4 / 8)


def test_vsd_ignores_surface_hidden_by_an_occluder_in_both_renderings():
    # a hand at 0.30 m covers the right half; truth and estimate differ only under the hand
    gt = np.full((2, 4), 0.50)
    est = gt.copy()
    est[:, 2:] = 0.60
    measured = gt.copy()
    measured[:, 2:] = 0.30
    assert metrics.vsd(est, gt, measured) == pytest.approx(0.0)
    # no measurement (0) counts as visible: the difference shows
    measured[:, 2:] = 0.0
    assert metrics.vsd(est, gt, measured) == pytest.approx(4 / 8)


def test_vsd_is_one_when_nothing_is_visible_and_uses_ray_distances_with_k():
    zero = np.zeros((2, 2))
    assert metrics.vsd(zero, zero, zero) == 1.0
    K = np.array([[1.0, 0, 0.0], [0, 1.0, 0.0], [0, 0, 1.0]])
    # pixel (1, 1) has ray length sqrt(3) per metre of z: 15 mm of z become 26 mm along the ray
    gt = np.zeros((2, 2))
    gt[1, 1] = 0.5
    est = gt.copy()
    est[1, 1] = 0.515
    assert metrics.vsd(est, gt, gt, tau=0.02) == 0.0
    assert metrics.vsd(est, gt, gt, K=K, tau=0.02) == 1.0
    assert metrics.depth_to_distance(gt, K)[1, 1] == pytest.approx(0.5 * np.sqrt(3))


def test_recall_counts_values_below_the_threshold_and_nan_as_failures():
    assert metrics.recall([0.1, 0.2, 0.5, np.nan], 0.3) == 0.5
    assert metrics.vsd_recall([0.29, 0.3]) == 0.5
    assert np.isnan(metrics.recall([], 0.3))


def test_summarise_ignores_nan():
    s = metrics.summarise([1.0, 2.0, 3.0, np.nan])
    assert s["median"] == 2.0 and s["max"] == 3.0 and s["mean"] == 2.0
    assert np.isnan(metrics.summarise([])["median"])
