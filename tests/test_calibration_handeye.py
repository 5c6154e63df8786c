"""Simulated hand-eye round trips (calibration.simulator + calibration.handeye).

Documented accuracy on the simulator's 640x480 views of the default board, 12 captures:
- noise-free: every method within 1 mm and 0.1 deg of the true T_flange_camera;
- ``NOISY`` preset (1.2 px blur, 6 grey levels, 5e-5 rad encoder noise): the chosen method
  within 1 mm and 0.1 deg, every method within 3 mm and 0.2 deg (Andreff's linear solve is the
  least accurate), the robot-world board pose within 1 mm.
"""
import numpy as np
import pytest

from calibration import handeye
from calibration.captures import CaptureWriter, read_captures
from calibration.simulator import SimulationConfig, noisy, rotation_angle_deg, simulate_captures

K = SimulationConfig().K


def _error(T, T_true):
    return 1000 * np.linalg.norm(T[:3, 3] - T_true[:3, 3]), rotation_angle_deg(T[:3, :3], T_true[:3, :3])


def _run(root, seed, config, corrupt=None, n=12):
    truth = simulate_captures(root, n, np.random.default_rng(seed), config, corrupt=corrupt)
    obs, skipped, robot = handeye.observations_from_folder(root, K, None)
    result = handeye.calibrate_hand_eye(obs, K)
    result.skipped = skipped
    return truth, result


@pytest.mark.parametrize("seed", [0, 1])
def test_noise_free_round_trip_within_1mm_and_0_1deg(tmp_path, seed):
    truth, result = _run(tmp_path, seed, SimulationConfig())
    assert len(result.observations) == 12 and not result.skipped and not result.warnings
    for m, r in result.methods.items():
        mm, deg = _error(r.T_flange_camera, truth.T_flange_camera)
        assert mm < 1.0 and deg < 0.1, (m, mm, deg)
    mm, deg = _error(result.robot_world["T_base_board"], truth.T_base_board)
    assert mm < 1.0 and deg < 0.1
    assert np.nanmax(result.chosen.reprojection_px) < 0.5


def test_noisy_round_trip_within_documented_bounds(tmp_path):
    truth, result = _run(tmp_path, 3, noisy())
    mm, deg = _error(result.chosen.T_flange_camera, truth.T_flange_camera)
    assert mm < 1.0 and deg < 0.1
    for m, r in result.methods.items():
        mm, deg = _error(r.T_flange_camera, truth.T_flange_camera)
        assert mm < 3.0 and deg < 0.2, (m, mm, deg)
    mm, _ = _error(result.robot_world["T_base_board"], truth.T_base_board)
    assert mm < 1.0


def test_corrupt_captures_are_skipped_with_a_reason(tmp_path):
    corrupt = {1: "blank", 4: "noise", 6: "missing", 8: "garbage"}
    truth, result = _run(tmp_path, 2, SimulationConfig(), corrupt=corrupt)
    reasons = {s["capture"]: s["reason"] for s in result.skipped}
    assert set(reasons) == set(corrupt)
    assert "no usable board" in reasons[1] and "no usable board" in reasons[4]
    assert "missing" in reasons[6] and "cannot be read" in reasons[8]
    assert len(result.observations) == 8
    mm, deg = _error(result.chosen.T_flange_camera, truth.T_flange_camera)
    assert mm < 1.5 and deg < 0.1


def _flange_poses(rotvecs):
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (len(rotvecs), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    T[:, :3, 3] = np.random.default_rng(0).normal(size=(len(rotvecs), 3)) * 0.1
    return T


def test_small_rotations_warn():
    rv = np.random.default_rng(1).normal(size=(6, 3)) * np.radians(1.0)
    warnings = handeye.check_conditioning(_flange_poses(rv))
    assert any("too small" in w for w in warnings)


def test_rotations_about_one_axis_warn():
    rv = np.outer(np.radians([0, 20, 40, 60, 80]), [0, 0, 1.0])
    warnings = handeye.check_conditioning(_flange_poses(rv))
    assert any("too similar" in w for w in warnings)


def test_varied_rotations_do_not_warn():
    rv = np.radians(30) * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]])
    assert handeye.check_conditioning(_flange_poses(rv)) == []


def test_board_pose_only_captures_are_used(tmp_path):
    """A capture row may carry the board pose instead of an image."""
    from app.geometry.ur import dh_from_config, forward_kinematics

    from calibration.simulator import make_scene, plan_captures

    scene = make_scene(SimulationConfig())
    q = plan_captures(scene, 6, np.random.default_rng(4))
    with CaptureWriter(tmp_path, robot={"model": "ur5e"}) as w:
        for k, qk in enumerate(q):
            w.add(float(k), qk, T_camera_board=scene.T_camera_board(qk))
    cs = read_captures(tmp_path)
    assert all(c.image_path is None and c.T_camera_board is not None for c in cs.captures)
    obs, skipped, _ = handeye.observations_from_folder(tmp_path, K, None)
    assert len(obs) == 6 and not skipped
    np.testing.assert_allclose(obs[0].T_base_flange, forward_kinematics(dh_from_config({"model": "ur5e"}), q[0]))
    result = handeye.calibrate_hand_eye(obs, K, method="park")
    mm, deg = _error(result.chosen.T_flange_camera, SimulationConfig().T_flange_camera)
    assert mm < 1e-3 and deg < 1e-5      # exact poses: only CSV rounding (1e-9) remains
    assert np.isnan(result.chosen.reprojection_px).all()


def test_fewer_than_three_usable_captures_is_an_error(tmp_path):
    simulate_captures(tmp_path, 3, np.random.default_rng(5), corrupt={0: "blank", 1: "missing"})
    obs, skipped, _ = handeye.observations_from_folder(tmp_path, K, None)
    with pytest.raises(ValueError, match="only 1 usable captures"):
        handeye.calibrate_hand_eye(obs, K)
