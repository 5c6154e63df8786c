"""The recorder: every accepted frame and joint sample written as a trial while the loop runs;
a killed session leaves every frame listed so far readable."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from app.session import run_session
from test_session_faults import CollectingOutput, fake_plugins, session  # noqa: F401 (fixture)

FAULTS_FILE = Path(__file__).with_name("test_session_faults.py")


def _box_mesh(tmp_path) -> Path:
    import trimesh

    path = tmp_path / "bone.ply"
    trimesh.creation.box((0.05, 0.02, 0.01)).export(path)
    return path


def test_recording_holds_every_good_frame_despite_faults(tmp_path, fake_plugins):
    from app.trial.reader import open_trial

    config = session(tmp_path, record=str(tmp_path / "trial"))
    config.mesh = _box_mesh(tmp_path)
    result = run_session(config)
    camera = fake_plugins[0][0]
    sink = CollectingOutput.instances[0]
    reader = open_trial(tmp_path / "trial")
    frames = list(reader.iter_frames())
    assert [f.frame_id for f in frames] == camera.pushed_good
    report = result.summary["outputs"]["Recorder"]
    assert report["dropped"]["queue"] == report["dropped"]["disk"] == 0 and report["complete"]
    for f in frames[::10]:
        np.testing.assert_allclose(f.depth_m, 0.4, atol=1e-4)
    np.testing.assert_allclose(reader.joint_stamps, sink.joint_stamps, atol=1e-6)
    np.testing.assert_allclose(reader.meta.T_flange_camera, np.eye(4))


RUNNER = """
import faulthandler, importlib.util, sys
faulthandler.enable()   # SIGABRT from the test on a hang prints every thread's stack
from pathlib import Path
spec = importlib.util.spec_from_file_location("faults", sys.argv[1])
m = importlib.util.module_from_spec(spec); sys.modules["faults"] = m; spec.loader.exec_module(m)
from app import plugins_registry as r
r.register("camera", "scripted", m.ScriptedCamera)
r.register("robot", "scripted", m.ScriptedRobot)
from app.session import parse_session, run_session
tmp = Path(sys.argv[2])
raw = {"camera": {"plugin": "scripted", "params": {"seconds": 60.0, "faults": False}},
       "robot": {"plugin": "scripted", "params": {"faults": False}, "model": "ur5e"},
       "tracker": False, "calibration": {"hand_eye": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
       "bone": {"mesh": str(tmp / "bone.ply")}, "record": str(tmp / "trial"), "out": str(tmp / "out")}
run_session(parse_session(raw, tmp))
"""


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT, signal.SIGTERM], ids=["kill", "ctrl-c", "term"])
def test_stopped_or_killed_session_leaves_a_readable_trial(tmp_path, sig):
    """SIGKILL: every frame listed is readable. Ctrl-C / SIGTERM: a clean stop with the summary written."""
    from app.trial.reader import open_trial

    _box_mesh(tmp_path)
    proc = subprocess.Popen([sys.executable, "-c", RUNNER, str(FAULTS_FILE), str(tmp_path)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    frames_csv = tmp_path / "trial" / "frames.csv"
    deadline = time.monotonic() + 60
    try:
        while time.monotonic() < deadline:
            if frames_csv.is_file() and frames_csv.read_text().count("\n") > 30:
                break
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.05)
        else:
            pytest.fail("the session wrote no frames")
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, sig)
        try:
            rc = proc.wait(30)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGABRT)
            proc.wait(10)
            pytest.fail(f"the session did not stop within 30 s of {sig.name}:\n{proc.stderr.read().decode()}")
    if sig != signal.SIGKILL:
        assert rc == 0, proc.stderr.read().decode()
        summary = (tmp_path / "out" / "summary.json").read_text()
        assert '"Recorder"' in summary
        assert "interrupted" in (tmp_path / "out" / "events.csv").read_text()
    reader = open_trial(tmp_path / "trial")
    n_rows = len(reader.stamps)
    frames = list(reader.iter_frames())
    assert n_rows >= 30 and len(frames) == n_rows
    assert all(np.allclose(f.depth_m, 0.4, atol=1e-4) for f in frames)
    assert len(reader.joint_stamps) > 0 and np.all(np.diff(reader.joint_stamps) > 0)
