"""A simulated trial's true camera poses, and the true bone as the calibrated camera sees it.

The trial format's ground truth is the bone in the robot base frame (shared/RECORDING_FORMAT.md).
When the rig's calibration is off (the ``or_calibration`` scenario: hand-eye 2 mm / 0.3 deg off,
robot clock 4 ms off, encoder noise), the camera poses the trial gives (FK of ``joints.csv`` and
the trial's ``hand_eye``) are not the camera's true poses. The simulator writes the true ones to
``camera_truth.txt`` (TUM rows, the pose of the camera optical frame in the base, one per frame,
the frames' stamps); a trial directory may hold such files (the format's "other files").

The projector rides on the flange, calibrated to the camera (T_camera_projector). It draws with
the pose the tracker believes, ``T_base_camera_measured``, so a template lands on the real bone
as if the bone stood at (eq. S1)::

    T_base_bone_seen = T_base_camera_measured @ inv(T_base_camera_true) @ T_base_bone_true

in the measured base frame: the true bone in the camera frame, carried out through the measured
camera pose. An estimate equal to it puts the template exactly on the bone, whatever the hand-eye
error; its base-frame ADD against the ground truth is then the calibration's own error.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import yaml

from app.geometry import se3

log = logging.getLogger(__name__)

CAMERA_TRUTH_FILE = "camera_truth.txt"
SIMULATION_FILE = "simulation.yaml"

FROM_FILE = "camera_truth.txt"
FROM_HAND_EYE = "joints.csv with the simulation's true hand-eye"
FROM_TRIAL = "the trial's own camera poses (its calibration taken as exact)"


def true_camera_poses(reader) -> tuple[np.ndarray, str]:
    """``(T_base_camera_true (N, 4, 4), source)`` for the frames of ``reader`` (an open trial).

    In order: ``camera_truth.txt`` (exact; stamps must match the frames'); else ``simulation.yaml``'s
    ``true_hand_eye`` on the FK of ``joints.csv`` (exact but for the trial's encoder noise and clock
    offset, which it then charges to the tracker); else the trial's own camera poses. NaN rows where
    the trial has no camera pose.
    """
    path = Path(reader.path)
    T_measured, valid = reader.camera_poses()
    truth_path = path / CAMERA_TRUTH_FILE
    if truth_path.is_file():
        from app.trial.tum import read_tum

        stamps, T = read_tum(truth_path)
        if len(stamps) == len(reader.stamps) and np.allclose(stamps, reader.stamps, atol=1e-6):
            return T, FROM_FILE
        log.warning("%s: %d stamps that do not match the %d frames'; ignored", truth_path, len(stamps),
                    len(reader.stamps))
    hand_eye = _true_hand_eye(path / SIMULATION_FILE)
    if hand_eye is None:
        return np.array(T_measured), FROM_TRIAL
    # the reader's FK of joints.csv, with the trial's hand-eye swapped for the true one (NaN rows stay NaN)
    return T_measured @ se3.inverse(np.asarray(reader.meta.T_flange_camera, float)) @ hand_eye, FROM_HAND_EYE


def _true_hand_eye(path: Path) -> np.ndarray | None:
    if not path.is_file():
        return None
    try:
        info = yaml.safe_load(path.read_text()) or {}
        T = np.asarray(info.get("true_hand_eye"), dtype=float)
    except (yaml.YAMLError, TypeError, ValueError):
        return None
    return T if T.shape == (4, 4) and np.all(np.isfinite(T)) else None


def bone_seen(T_base_camera_measured: np.ndarray, T_base_camera_true: np.ndarray,
              T_base_bone_true: np.ndarray) -> np.ndarray:
    """(..., 4, 4) the true bone carried through the measured camera pose (module docstring, eq. S1)."""
    return np.asarray(T_base_camera_measured) @ se3.inverse(np.asarray(T_base_camera_true)) @ np.asarray(T_base_bone_true)
