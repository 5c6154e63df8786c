"""A simulated trial's true camera poses (app/sim/truth.py) and the projected template's error under a
hand-eye error (app/bench/template.py): the outline follows the camera, not the base frame."""
from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest

from app import metrics
from app.bench.template import template_scores
from app.geometry import se3
from app.sim import truth
from app.trial.reader import open_trial


@pytest.fixture(scope="module")
def calibration_trial(tmp_path_factory, gl_ctx):
    """0.3 s of or_calibration on the default crest: hand-eye 2 mm / 0.3 deg off, clock 4 ms, encoder noise."""
    from app.sim.simulator import DEFAULT_MESH, simulate

    path = tmp_path_factory.mktemp("truth") / "or_calibration"
    simulate(path, DEFAULT_MESH, "or_calibration", seconds=0.3, seed=3)
    return path


def _copy_without(src, dst, *names):
    shutil.copytree(src, dst)
    for name in names:
        (dst / name).unlink()
    return open_trial(dst)


def test_camera_truth_differs_from_the_trials_camera_by_the_hand_eye_error(calibration_trial):
    reader = open_trial(calibration_trial)
    T_true, source = truth.true_camera_poses(reader)
    T_measured, valid = reader.camera_poses()
    assert source == truth.FROM_FILE and valid.all() and T_true.shape == T_measured.shape
    gap_mm = 1e3 * np.linalg.norm(T_true[:, :3, 3] - T_measured[:, :3, 3], axis=1)
    gap_deg = np.degrees(se3.rotation_angle(T_true, T_measured))
    # the scenario's 2 mm / 0.3 deg hand-eye error, plus a 4 ms clock offset and 5e-5 rad of encoder noise
    assert np.all((gap_mm > 1.5) & (gap_mm < 2.6)), gap_mm
    assert np.all(np.abs(gap_deg - 0.3) < 0.05), gap_deg


def test_without_the_file_the_true_hand_eye_gives_the_camera_up_to_clock_and_encoder_noise(calibration_trial, tmp_path):
    exact, _ = truth.true_camera_poses(open_trial(calibration_trial))
    reader = _copy_without(calibration_trial, tmp_path / "t", truth.CAMERA_TRUTH_FILE)
    T, source = truth.true_camera_poses(reader)
    assert source == truth.FROM_HAND_EYE
    assert np.max(np.linalg.norm(T[:, :3, 3] - exact[:, :3, 3], axis=1)) < 3e-4   # well under the 2 mm error
    bare = _copy_without(calibration_trial, tmp_path / "bare", truth.CAMERA_TRUTH_FILE, truth.SIMULATION_FILE)
    T, source = truth.true_camera_poses(bare)
    assert source == truth.FROM_TRIAL and np.array_equal(T, bare.camera_poses()[0])


def test_a_camera_truth_file_that_does_not_match_the_frames_is_ignored_with_a_warning(calibration_trial, tmp_path, caplog):
    from app.trial.tum import read_tum, write_tum

    dst = tmp_path / "t"
    shutil.copytree(calibration_trial, dst)
    stamps, T = read_tum(dst / truth.CAMERA_TRUTH_FILE)
    write_tum(dst / truth.CAMERA_TRUTH_FILE, stamps[:-1], T[:-1])
    with caplog.at_level(logging.WARNING, logger="app.sim.truth"):
        _, source = truth.true_camera_poses(open_trial(dst))
    assert source == truth.FROM_HAND_EYE and "do not match" in caplog.text


def test_bone_seen_is_the_truth_when_the_calibration_is_exact(rng):
    T_camera = se3.from_rotvec_trans(rng.normal(size=(5, 3)), rng.normal(size=(5, 3)))
    T_bone = se3.from_rotvec_trans(rng.normal(size=(5, 3)), rng.normal(size=(5, 3)))
    assert np.allclose(truth.bone_seen(T_camera, T_camera, T_bone), T_bone, atol=1e-12)


def test_the_outline_lands_on_the_bone_at_the_seen_pose_and_off_it_at_the_base_truth(calibration_trial):
    """An estimate equal to the seen pose (eq. S1) puts every outline point on its plan although its
    base-frame ADD is the calibration's error (> 1 mm); the base-frame truth itself is drawn off by it."""
    reader = open_trial(calibration_trial)
    n = len(reader)
    T_measured, _ = reader.camera_poses()
    T_true, _ = truth.true_camera_poses(reader)
    gt = np.asarray(reader.groundtruth)
    seen = truth.bone_seen(T_measured, T_true, gt)
    points = np.asarray(reader.load_mesh().vertices)
    assert min(1e3 * metrics.add(s, g, points) for s, g in zip(seen, gt)) > 1.0
    every = 4
    on = template_scores(reader, seen, ["ok"] * n, n, every=every)
    assert on["ok_frames_scored"] == len(range(0, n, every)) and on["camera_truth"] == truth.FROM_FILE
    assert on["outline_max_mm"] < 1e-3 and on["add_camera_mm"]["max"] < 1e-6
    off = template_scores(reader, gt, ["ok"] * n, n, every=every)
    assert off["outline_mean_mm"]["median"] > 0.5 and off["add_camera_mm"]["median"] > 1.0
    # only ok frames are drawn and scored
    statuses = ["uncertain"] * n
    statuses[0] = "ok"
    assert template_scores(reader, gt, statuses, n)["ok_frames_scored"] == 1
