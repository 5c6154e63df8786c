"""The ``tracker: marker_imu`` session plugin (plugins/marker_imu.py)."""
import time

import numpy as np
import pytest

from app import plugins_registry as registry
from app.errors import ConfigError
from app.interfaces import DepthFrame
from app.marker import imu as imu_proto


def _tick(stamp):
    """A frame without images (the simulated marker camera renders its own)."""
    return DepthFrame(frame_id=0, stamp=float(stamp), depth_m=np.zeros((2, 2), np.float32), arrival=float(stamp))


def _create(**params):
    return registry.create("tracker", "marker_imu", params, "tracker", mesh=None, camera=None, T_flange_camera=None)


def test_registered_and_tracks_with_simulated_imu():
    assert "marker_imu" in registry.available("tracker")
    tracker = _create(imu="simulated", seed=1)
    tracker.start(np.eye(4))
    T_base_camera = np.eye(4)
    T_base_camera[:3, 3] = [0.1, 0.0, 0.2]
    results = [tracker.process(_tick(50.0 + k / 10), T_base_camera) for k in range(12)]
    tracker.release()
    assert results[-1].status == "ok"
    assert {r.path for r in results} <= {"roi", "full"} and results[-1].path == "roi"
    (R,), (p,) = tracker.sim.pose([1.1])
    np.testing.assert_allclose(results[-1].T_base_bone[:3, 3], p + [0.1, 0.0, 0.2], atol=0.01)


def test_udp_imu_feeds_the_filter_over_loopback():
    tracker = _create(imu="udp", imu_port=0, seed=2)
    sender = imu_proto.UdpSender(tracker.receiver.address)
    sim_imu = tracker.sim.imu()
    try:
        for k in range(30):
            sender.send(k, sim_imu["sensor_stamp"][k], sim_imu["q_W_S"][k])
        end = time.monotonic() + 30.0       # event-driven wait; the timeout is a safety net only
        while tracker.receiver.counts["received"] < 30 and time.monotonic() < end:
            time.sleep(0.01)
        result = tracker.process(_tick(0.0), None)
    finally:
        sender.close()
        tracker.release()
    assert tracker.fusion.counts["imu"] == 30
    assert result.q_C_M is not None


def test_bad_parameters_name_the_key():
    with pytest.raises(ConfigError, match="tracker.params.imu"):
        _create(imu="serial")
    with pytest.raises(ConfigError, match="imu_file"):
        _create(imu="file")


def test_rerun_log_file_and_angles_after_imu_registration(tmp_path):
    """The tracker logs its image, region, orientations and angles to an .rrd file; after the IMU's
    pelvic-plane registration the results carry inclination and anteversion near the truth."""
    rrd = tmp_path / "marker.rrd"
    tracker = _create(imu="simulated", seed=3, rerun=str(rrd))
    tracker.start(np.eye(4))
    results = [tracker.process(_tick(k / 10), None) for k in range(45)]   # registration ends at 2 s
    tracker.release()
    assert rrd.exists() and rrd.stat().st_size > 1000
    assert results[5].inclination is None                               # still registering
    last = results[-1]
    assert last.inclination is not None and last.anteversion is not None
    assert last.diagnostics["anteversion"] == last.anteversion
    (inc_true,), (ant_true,) = tracker.sim.angles([4.4])
    assert abs(np.rad2deg(last.inclination - inc_true)) < 3.0
    assert abs(np.rad2deg(last.anteversion - ant_true)) < 3.0
    data = rrd.read_bytes()
    for entity in (b"plots/marker/inclination_deg", b"plots/marker/anteversion_deg", b"marker/image/roi",
                   b"marker/image/corners", b"marker/orientation/fused"):
        assert entity in data, entity


def test_rerun_auto_without_a_recording_does_not_log():
    import rerun as rr

    # an earlier test in this worker may have left a recording active: none for this one, then put back
    held = rr.set_thread_local_data_recording(None), rr.set_global_data_recording(None)
    try:
        assert rr.get_data_recording() is None
        tracker = _create(imu="simulated", seed=4)
        assert tracker.rerun is None
        tracker.start(np.eye(4))
        assert tracker.process(_tick(0.0), None).path in ("roi", "full", "none")
        tracker.release()
    finally:
        rr.set_thread_local_data_recording(held[0])
        rr.set_global_data_recording(held[1])


def test_in_a_session_the_tracker_logs_into_the_rerun_outputs_recording(tmp_path):
    """The session opens its outputs before starting the tracker: with rerun 'auto' the marker
    tracker's entities land in the rerun output's .rrd file."""
    import rerun as rr

    from plugins.rerun_output import RerunOutput

    rrd = tmp_path / "session.rrd"
    output = RerunOutput(path=str(rrd))
    tracker = _create(imu="simulated", seed=5)            # created before the outputs, as in app/session.py
    output.open({"mesh": None, "camera": None, "T_flange_camera": None})
    try:
        tracker.start(np.eye(4))
        assert tracker.rerun is not None
        for k in range(25):
            tracker.process(_tick(k / 10), None)
        tracker.release()
    finally:
        output.close()
        rr.set_global_data_recording(None)
    assert b"marker/orientation/fused" in rrd.read_bytes()
