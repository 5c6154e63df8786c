"""The simulator writes complete, exact trials: depth equals the mesh re-rendered at the ground truth
through FK, hand-eye and K within the sensor noise model; scenarios do what they say."""
from __future__ import annotations

import numpy as np
import pytest

from app.geometry import se3
from app.render.scene import SceneRenderer
from app.sim.scenarios import SCENARIOS, get_scenario
from app.sim.sensor import SensorModel
from app.sim.simulator import simulate, target_occlusion


@pytest.fixture(scope="module")
def clear_trial(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "static_clear"
    simulate(out, scenario_name="static_clear", seconds=0.25, seed=3)
    return out


def test_simulated_depth_equals_the_mesh_rendered_at_ground_truth_within_noise(clear_trial, gl_ctx):
    """Where the bone is visible the measurement is the bone's depth within sigma(z); where the
    rendered bone is hidden (soft tissue covers all but the crest) the measurement lies in front of
    it, never behind it."""
    import csv

    from app.trial.reader import open_trial

    reader = open_trial(clear_trial)
    mesh = reader.load_mesh()
    T_base_camera, valid = reader.camera_poses()
    assert valid.all()
    visible_bone_px = {int(r["frame"]): int(r["bone_pixels"]) * (1 - float(r["occlusion"]))
                       for r in csv.DictReader(open(clear_trial / "simulation.csv"))}
    scene = SceneRenderer(gl_ctx, reader.meta.camera)
    scene.add_mesh("bone", mesh.vertices, mesh.faces, label=1)
    sensor = SensorModel()
    residuals = []
    for frame in reader.iter_frames():
        T_camera_bone = se3.inverse(T_base_camera[frame.index]) @ reader.groundtruth[frame.index]
        rendered, labels = scene.render({"bone": T_camera_bone})
        use = (labels == 1) & (frame.depth_m > 0)
        assert use.sum() > 2000, "the bone must be well in view"
        r = (frame.depth_m[use] - rendered[use]) / sensor.sigma(rendered[use])
        # edge pixels and 1 % random dropouts are invalid; the rest of the visible bone is an inlier
        assert np.sum(np.abs(r) < 5) > 0.9 * visible_bone_px[frame.frame_id]
        assert np.sum(np.abs(r) < 5) < 1.1 * visible_bone_px[frame.frame_id]  # + tissue grazing the rim
        residuals.append(r)
    scene.release()
    r = np.concatenate(residuals)
    inliers = np.abs(r) < 5
    assert np.mean(r > 5) < 0.005          # nothing is measured behind the bone's surface
    median = np.median(r[inliers])
    robust_std = 1.4826 * np.median(np.abs(r[inliers] - median))   # tissue grazing the rim skews the mean
    assert abs(median) < 0.1
    assert 0.85 < robust_std < 1.15


def test_trial_carries_a_coarse_initial_pose_and_a_point_on_the_bone(clear_trial):
    from app.trial.reader import open_trial

    reader = open_trial(clear_trial)
    T0 = reader.groundtruth[0]
    init = reader.meta.initial_pose
    assert 4.0 < 1e3 * np.linalg.norm(init[:3, 3] - T0[:3, 3]) < 6.0
    assert 2.5 < np.rad2deg(se3.rotation_angle(init, T0)) < 3.5
    mesh = reader.load_mesh()
    p_bone = se3.transform_points(se3.inverse(T0), reader.meta.point_prior[None])
    distance = np.min(np.linalg.norm(mesh.vertices - p_bone, axis=1))
    assert distance < 1e-6


def test_joint_samples_at_500_hz_cover_every_frame_at_90_hz(clear_trial):
    from app.trial.reader import open_trial

    reader = open_trial(clear_trial)
    assert np.median(np.diff(reader.joint_stamps)) == pytest.approx(1 / 500, rel=1e-6)
    assert reader.joint_stamps[0] < reader.stamps[0] and reader.joint_stamps[-1] > reader.stamps[-1]
    frame_dt = np.diff(reader.stamps)
    assert np.min(frame_dt) == pytest.approx(1 / 90, rel=1e-6)
    assert reader.meta.camera.width == 640 and reader.meta.camera.height == 480


def test_occlusion_profile_reaches_80_percent_and_returns():
    s = get_scenario("static_occluded")
    assert target_occlusion(s, 5.0) == pytest.approx(0.8)
    assert target_occlusion(s, 0.5) == 0.0 and target_occlusion(s, 9.5) == 0.0


@pytest.mark.parametrize("fraction", [0.3, 0.8])
def test_hand_covers_the_requested_fraction_of_the_bone(tmp_path, fraction):
    import csv
    from dataclasses import replace

    scenario = replace(get_scenario("static_clear"), name="half", occlusion_profile=((0.0, fraction), (1.0, fraction)))
    simulate(tmp_path / "occ", scenario_name=scenario, seconds=0.05, seed=1)
    rows = list(csv.DictReader(open(tmp_path / "occ" / "simulation.csv")))
    assert all(abs(float(r["occlusion"]) - fraction) < 0.03 for r in rows)


def test_dropouts_leave_300_ms_gaps(tmp_path):
    """The dropouts scenario's gaps are 300 ms; the simulator leaves such a gap in the frames. Its
    first gap moved from 2.0 s to 0.2 s, so 0.7 s of frames (63, not 225) hold it."""
    from dataclasses import replace

    from app.trial.reader import open_trial

    scenario = get_scenario("dropouts")
    assert [d for _, d in scenario.gaps] == [0.3, 0.3, 0.3]
    out = tmp_path / "drop"
    simulate(out, scenario_name=replace(scenario, seconds=0.7, gaps=((0.2, 0.3),)), seed=2)
    stamps = open_trial(out).stamps
    gaps = np.diff(stamps)
    assert gaps.max() == pytest.approx(0.3 + 1 / 90, abs=1 / 90 + 1e-6)
    assert stamps[int(np.argmax(gaps))] - stamps[0] == pytest.approx(0.2, abs=1 / 90 + 1e-6)   # where it was put


def test_unknown_scenario_lists_the_valid_ones():
    with pytest.raises(ValueError, match="static_clear"):
        get_scenario("nope")
    assert {"static_clear", "static_occluded", "bone_moves", "dropouts"} <= set(SCENARIOS)


def test_far_view_shrinks_the_bone_by_the_square_of_the_distance_and_other_side_turns_it(tmp_path):
    """static_far puts the bone 0.65 m from the camera (0.42 m otherwise): its pixels shrink about as
    (0.42 / 0.65)²; static_other_side turns it 180 deg about its crest-up axis (same seed, same place)."""
    import csv

    from app.trial.reader import open_trial

    pixels, T0 = {}, {}
    for name in ("static_clear", "static_far", "static_other_side"):
        simulate(tmp_path / name, scenario_name=name, seconds=0.03, seed=5)
        pixels[name] = np.mean([float(r["bone_pixels"]) for r in csv.DictReader(open(tmp_path / name / "simulation.csv"))])
        T0[name] = open_trial(tmp_path / name).groundtruth[0]
    assert pixels["static_far"] / pixels["static_clear"] == pytest.approx((0.42 / 0.65) ** 2, rel=0.25)
    assert pixels["static_other_side"] > 0.5 * pixels["static_clear"]
    R_turn = T0["static_clear"][:3, :3].T @ T0["static_other_side"][:3, :3]   # tiltᵀ R_z(180°) tilt
    assert np.trace(R_turn) == pytest.approx(-1.0, abs=1e-9)                  # a half turn
    axis = np.linalg.eigh(R_turn + R_turn.T)[1][:, -1]                         # its axis: near the crest-up z
    assert abs(axis[2]) > np.cos(np.deg2rad(40.0))
    np.testing.assert_allclose(T0["static_other_side"][:3, 3], T0["static_clear"][:3, 3], atol=1e-12)
