"""ArUco search paths, the orientation Kalman filter and the fused tracker on simulated sequences."""
import json
import types

import numpy as np
import pytest

from app.geometry import quaternion as quat
from app.marker import bench
from app.marker.aruco import MarkerDetector, dictionary
from app.marker.fusion import MarkerImuFusion
from app.marker.kalman import OrientationKalman, marker_increment
from app.marker.simulator import MarkerScenario, MarkerSimulator


@pytest.fixture(scope="module")
def sim():
    return MarkerSimulator(MarkerScenario(seconds=12.0, seed=3))


def _detector(sim):
    sc = sim.sc
    return MarkerDetector(sim.K, None, sc.dictionary, sc.marker_id, sc.marker_length_m)


def _pose(sim, t):
    (R,), (p,) = sim.pose([t])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def test_good_prediction_finds_marker_in_region(sim):
    rng = np.random.default_rng(0)
    t = 6.0
    det = _detector(sim).detect(sim.image(t, rng), _pose(sim, t))
    assert det.path == "roi"
    x0, y0, x1, y1 = det.roi
    assert np.all((det.corners >= [x0, y0]) & (det.corners <= [x1, y1]))
    T = _pose(sim, t)
    assert np.linalg.norm(det.T_C_M[:3, 3] - T[:3, 3]) < 0.005
    assert np.rad2deg(quat.angle_between(det.q_C_M, quat.from_matrix(T[:3, :3]))) < 4.0


def test_bad_prediction_falls_back_to_whole_image(sim):
    rng = np.random.default_rng(1)
    t = 6.0
    wrong = _pose(sim, t)
    wrong[:3, 3] += [0.12, -0.08, 0.0]                     # 12 cm off: the region misses the marker
    det = _detector(sim).detect(sim.image(t, rng), wrong)
    assert det.path == "full"
    assert not (det.roi[0] <= det.corners[:, 0].min() and det.corners[:, 0].max() <= det.roi[2]
                and det.roi[1] <= det.corners[:, 1].min() and det.corners[:, 1].max() <= det.roi[3])


def test_no_marker_reports_none(sim):
    det = _detector(sim).detect(sim._background.astype(np.uint8), _pose(sim, 6.0))
    assert det.path == "none" and not det.found and det.T_C_M is None


def test_unknown_dictionary_lists_valid_names():
    with pytest.raises(ValueError, match="DICT_4X4_50"):
        dictionary("DICT_4X4_5")


def test_marker_increment_maps_imu_motion_into_marker_frame():
    rng = np.random.default_rng(2)
    q_S_M, q_W_S0, q_W_S1 = quat.random_uniform(rng, 3)
    q_W_M0, q_W_M1 = quat.multiply(q_W_S0, q_S_M), quat.multiply(q_W_S1, q_S_M)
    expected = quat.multiply(quat.conjugate(q_W_M0), q_W_M1)
    assert quat.allclose_up_to_sign(marker_increment(q_W_S0, q_W_S1, q_S_M), expected, atol=1e-12)


def test_kalman_gates_a_flip_then_reinitialises():
    kf = OrientationKalman(max_rejections=3)
    q0 = quat.exp_map(np.array([0.1, 0.2, 0.3]))
    kf.update(q0)
    flipped = quat.multiply(q0, quat.exp_map(np.array([np.deg2rad(40.0), 0, 0])))
    assert kf.update(flipped) is False and kf.update(flipped) is False
    assert quat.allclose_up_to_sign(kf.q, q0)
    assert kf.update(flipped) is True and kf.resets == 1
    assert quat.allclose_up_to_sign(kf.q, flipped)


def test_kalman_prediction_with_exact_increments_is_exact():
    rng = np.random.default_rng(3)
    kf = OrientationKalman()
    q = quat.random_uniform(rng, 1)[0]
    kf.initialise(q)
    for _ in range(200):
        dq = quat.exp_map(rng.normal(0, 0.02, 3))
        q = quat.multiply(q, dq)
        kf.predict(dq, 0.01)
    assert np.rad2deg(quat.angle_between(kf.q, q)) < 1e-9
    assert np.all(np.linalg.eigvalsh(kf.P) > 0)


def test_fused_error_below_marker_error_at_imu_rate(sim):
    """Orientation error of the fused tracker (at every IMU sample) against the marker alone (at
    every image), with the true calibration, on a 12 s simulated sequence."""
    rng = np.random.default_rng(4)
    imu = sim.imu()
    frames = sim.frame_stamps()
    marker = _detector(sim)
    fusion = MarkerImuFusion(_detector(sim), quat.from_matrix(sim.sc.R_S_M))
    err_marker, err_fused, fused_stamps = [], [], []
    k = 0
    for i, t in enumerate(imu["stamp"]):
        while k < len(frames) and frames[k] < t:
            gray = sim.image(frames[k], rng)
            d = marker.detect(gray)
            if d.found:
                q_true = quat.from_matrix(sim.pose([frames[k]])[0][0])
                err_marker.append(quat.angle_between(d.q_C_M, q_true))
            fusion.on_image(gray, frames[k])
            k += 1
        est = fusion.on_imu(t, imu["q_W_S"][i])
        if est.q_C_M is not None:
            fused_stamps.append(t)
            err_fused.append(quat.angle_between(est.q_C_M, quat.from_matrix(sim.pose([t])[0][0])))
    mean_marker, mean_fused = np.rad2deg(np.mean(err_marker)), np.rad2deg(np.mean(err_fused))
    assert mean_fused < 0.7 * mean_marker, (mean_fused, mean_marker)
    rate = (len(fused_stamps) - 1) / (fused_stamps[-1] - fused_stamps[0])
    assert rate == pytest.approx(sim.sc.imu_rate_hz, rel=1e-6)
    assert fusion.counts["roi"] > 0.8 * len(frames)        # the IMU's prediction finds it first
    assert fusion.counts["full"] >= 1                       # the first image, and the box's transfer


def test_bench_marker_command_writes_json_and_meets_targets(tmp_path, capsys):
    from app.commands import bench_marker

    out = tmp_path / "bench.json"
    args = types.SimpleNamespace(seconds=10.0, seeds=[5], camera_fps=10.0, imu_rate=100.0, yaw_drift=None,
                                 json=str(out), overwrite=False)
    assert bench_marker.run(args) == 0
    printed = capsys.readouterr().out
    assert "| fused (Kalman) |" in printed
    result = json.loads(out.read_text())["mean"]["methods"]
    fused, marker = result["fused"], result["marker"]
    assert fused["inclination_mae_deg"] < marker["inclination_mae_deg"]   # the APP registered with the IMU
    assert fused["anteversion_mae_deg"] < marker["anteversion_mae_deg"]
    assert fused["rate_hz"] == pytest.approx(100.0, rel=0.02)
    assert marker["rate_hz"] <= 10.0 + 1e-9
