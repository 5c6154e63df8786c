"""The pointer end to end (issue 33, item 3): the simulator draws a pointer tool held on the crest into
the infrared images (app/sim/pointer.py), the marker tracker reads its tip there (app/tracking/pointer.py)
once held still, and the detector starts the track from it (app/tracking/start.py). Frames are processed
in order, the detection inline (as a replay does): work is counted, never timed."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from app import metrics
from app.interfaces import DepthFrame
from app.sim.pointer import SimulatedPointer
from app.tracking.pointer import HOLD_S


@pytest.fixture(scope="module")
def pointer_trial(tmp_path_factory):
    """A 0.6 s static_clear trial of the default crest with the infrared stream and the pointer drawn."""
    from app.sim.simulator import simulate

    out = tmp_path_factory.mktemp("pointer") / "trial"
    simulate(out, scenario_name="static_clear", seconds=0.6, seed=1, streams="depth,ir", pointer=SimulatedPointer())
    return out


def test_a_simulated_pointer_s_tip_is_read_from_the_infrared_images_where_it_touches(pointer_trial):
    """Every frame's marker is found; the tip read through the camera pose lies where the simulator held
    it (simulation.yaml's tip_base) within 3 mm (IPPE's orientation error times the 10 cm lever)."""
    from app.tracking.pointer import PointerTip
    from app.trial.reader import open_trial

    reader = open_trial(pointer_trial)
    info = yaml.safe_load((pointer_trial / "simulation.yaml").read_text())["pointer"]
    tool = SimulatedPointer()
    assert {k: info[k] for k in tool.session_block()} == tool.session_block()
    pointer = PointerTip(tool.marker_id, tool.marker_length_m, tool.tip_offset_m, reader.meta.camera)
    T_base_camera, _ = reader.camera_poses()
    errors = []
    for k in range(0, len(reader), 9):
        pointer.observe(DepthFrame(k, float(reader.stamps[k]), None, float(reader.stamps[k]),
                                   infrared=reader.read_infrared(k)))
        tip = pointer.tip(T_base_camera[k])
        assert tip is not None, f"frame {k}: the marker not found"
        errors.append(np.linalg.norm(tip - np.asarray(info["tip_base"])))
    assert max(errors) < 0.003
    top = np.asarray(reader.meta.point_prior)           # the simulator's crest top, which the tip is held off
    assert np.linalg.norm(np.asarray(info["tip_base"]) - top) == pytest.approx(tool.off_m, abs=1e-9)


def test_a_track_starts_from_the_held_pointer_tip_and_is_ok_only_when_right(pointer_trial):
    """init.method auto with bone.pointer's source: lost ('initialising') until the tip has been held
    HOLD_S, then the detector from the tip finds the bone within 1 mm, and no frame is ok while more
    than 2 mm off."""
    from dataclasses import replace

    from app.config import load_config
    from app.pipeline.tracker import DepthTracker
    from app.tracking.pointer import PointerTip
    from app.trial.reader import open_trial

    reader = open_trial(pointer_trial)
    config = replace(load_config(None), backend="cpu")
    mesh = reader.load_mesh()
    tracker = DepthTracker(config, mesh, reader.meta.camera)
    tool = SimulatedPointer()
    pointer = PointerTip(tool.marker_id, tool.marker_length_m, tool.tip_offset_m, reader.meta.camera)
    tracker.start_by_detection(None, point_source=pointer)
    T_base_camera, _ = reader.camera_poses()
    points = np.asarray(mesh.vertices)
    found_at, ok_off = None, 0
    for k, frame in enumerate(reader.iter_frames()):
        pointer.observe(DepthFrame(k, frame.stamp, frame.depth_m, frame.stamp, infrared=frame.infrared))
        result = tracker.process(frame.depth_m, frame.stamp, T_base_camera[k])
        add_mm = 1e3 * metrics.add(result.T_base_bone, reader.groundtruth[k], points) if result.T_base_bone is not None \
            else np.inf
        if found_at is None and not tracker._start_detection.pending:
            found_at = k
            assert add_mm < 1.0
        if found_at is None:
            assert result.status == "lost" and result.state == "initialising"
        ok_off += result.status == "ok" and add_mm > 2.0
    tracker.release()
    report = tracker.start_report
    assert found_at is not None and report["found"] and report["source"] == "pointer (marker 7)"
    assert report["located_stamp"] - reader.stamps[0] >= HOLD_S
    assert report["attempts"] >= 1 and ok_off == 0


def test_a_simulated_pointer_without_the_infrared_stream_is_refused_by_name():
    """camera/robot: simulated with ``pointer: true`` needs ``ir`` in its streams (the marker is drawn there)."""
    from app.errors import ConfigError
    from app.sim.simulator import simulate
    from plugins.trial_player import SimulatedCamera, SimulatedRobot

    with pytest.raises(ConfigError, match=r"camera\.params\.pointer.*streams to include ir"):
        SimulatedCamera(pointer=True, streams="depth")
    with pytest.raises(ConfigError, match=r"robot\.params\.pointer.*true or false"):
        SimulatedRobot(pointer="yes", streams="depth,ir")
    with pytest.raises(ConfigError, match=r"camera\.params\.streams.*unknown: thermal"):
        SimulatedCamera(streams="depth,thermal")
    with pytest.raises(ValueError, match="streams must include ir"):
        simulate("/nonexistent/never-written", scenario_name="static_clear", seconds=0.1, pointer=SimulatedPointer())
