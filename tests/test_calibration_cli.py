"""`osteonav calibrate ...` end to end on simulated captures."""
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from app.cli import main


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("cal") / "captures"
    assert main(["calibrate", "simulate", "--out", str(root), "--count", "10", "--seed", "1",
                 "--corrupt", "2:blank"]) == 0
    return root


def test_simulate_writes_a_capture_folder(captures):
    assert (captures / "captures.csv").read_text().splitlines()[0].startswith("capture,stamp,q0,q1")
    assert len(list((captures / "images").glob("*.png"))) == 10
    for name in ("camera.yaml", "capture.yaml", "truth.yaml"):
        assert (captures / name).is_file()


def test_intrinsics_command_writes_camera_yaml(captures, tmp_path, capsys):
    out = tmp_path / "camera.yaml"
    assert main(["calibrate", "intrinsics", "--images", str(captures / "images"), "--out", str(out),
                 "--fix-k3"]) == 0
    printed = capsys.readouterr().out
    assert "skipped 000002.png" in printed and "px RMS" in printed
    cam = yaml.safe_load(out.read_text())["camera"]
    assert (cam["width"], cam["height"]) == (640, 480)
    np.testing.assert_allclose(cam["K"], [[600, 0, 320], [0, 600, 240], [0, 0, 1]], atol=3.0)
    assert len(cam["dist"]) == 5


def test_hand_eye_command_writes_trial_compatible_yaml_and_rrd(captures, tmp_path, capsys):
    out, rrd = tmp_path / "hand_eye.yaml", tmp_path / "hand_eye.rrd"
    assert main(["calibrate", "hand-eye", "--captures", str(captures), "--out", str(out),
                 "--rrd", str(rrd)]) == 0
    printed = capsys.readouterr().out
    for m in ("tsai", "park", "horaud", "andreff", "daniilidis", "robot-world", "skipped capture 2"):
        assert m in printed
    data = yaml.safe_load(out.read_text())
    truth = yaml.safe_load((captures / "truth.yaml").read_text())
    X = np.asarray(data["hand_eye"], dtype=float)
    assert X.shape == (4, 4) and np.allclose(X[3], [0, 0, 0, 1])
    X_true = np.asarray(truth["hand_eye"], dtype=float)
    # 9 simulated captures (corner noise, no robot error): translation within 1 mm and rotation
    # within 0.1 deg of the truth (measured: 0.32 mm, 0.025 deg; a wrong axis convention or a
    # transposed rotation is degrees off)
    assert np.linalg.norm(X[:3, 3] - X_true[:3, 3]) < 1e-3
    angle = np.degrees(np.arccos(np.clip((np.trace(X[:3, :3].T @ X_true[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 0.1, angle
    assert np.asarray(data["T_base_board"]).shape == (4, 4)
    assert data["robot"] == {"model": "ur5e"} and data["camera"]["width"] == 640
    assert [c["capture"] for c in data["captures"]] == [0, 1, 3, 4, 5, 6, 7, 8, 9]
    assert data["skipped"][0]["capture"] == 2
    assert set(data["methods"]) == {"tsai", "park", "horaud", "andreff", "daniilidis"}
    assert rrd.read_bytes()[:4] == b"RRF2"


def test_hand_eye_yaml_is_read_by_the_session_and_names_no_backend(captures, tmp_path):
    from app.session import parse_session

    out = tmp_path / "hand_eye.yaml"
    assert main(["calibrate", "hand-eye", "--captures", str(captures), "--out", str(out)]) == 0
    data = yaml.safe_load(out.read_text())
    assert "backend" not in data  # the solvers are OpenCV's, there is no backend to name
    raw = {"camera": {"plugin": "simulated"}, "robot": {"plugin": "simulated"},
           "calibration": {"hand_eye": out.name}}
    config = parse_session(raw, tmp_path)
    np.testing.assert_allclose(config.hand_eye, np.asarray(data["hand_eye"]))


def test_hand_eye_has_no_backend_option(captures, tmp_path):
    assert main(["calibrate", "hand-eye", "--captures", str(captures), "--backend", "numpy"]) == 2


def test_hand_eye_rrd_holds_a_frustum_per_capture(captures, tmp_path):
    rerun = Path(shutil.which("rerun") or Path(__import__("sys").executable).parent / "rerun")
    if not rerun.exists():
        pytest.skip("rerun CLI not installed")
    rrd = tmp_path / "he.rrd"
    assert main(["calibrate", "hand-eye", "--captures", str(captures), "--out",
                 str(tmp_path / "he.yaml"), "--rrd", str(rrd)]) == 0
    text = subprocess.run([str(rerun), "rrd", "print", str(rrd)], capture_output=True, text=True,
                          timeout=120).stdout
    for k in (0, 9):
        assert f"world/captures/{k:06d}/flange/camera/image" in text
    assert "world/board" in text


def test_hand_eye_without_intrinsics_names_the_option(captures, tmp_path, capsys):
    folder = tmp_path / "nocam"
    shutil.copytree(captures, folder)
    (folder / "camera.yaml").unlink()
    assert main(["calibrate", "hand-eye", "--captures", str(folder)]) == 2
    assert "--camera" in capsys.readouterr().err


def test_capture_from_simulated_session(tmp_path):
    session = tmp_path / "session.yaml"
    session.write_text("camera: simulated\nrobot: simulated\n")
    out = tmp_path / "live"
    assert main(["calibrate", "capture", "--config", str(session), "--out", str(out), "--count", "5"]) == 0
    assert len((out / "captures.csv").read_text().splitlines()) == 6
    assert main(["calibrate", "hand-eye", "--captures", str(out), "--method", "park"]) == 0


def test_live_capture_session_errors_name_the_key(tmp_path, capsys):
    """A live session (any camera but 'simulated') goes through the session's plugins: a missing robot and a
    camera without the infrared stream are named (calibration/live_session.py)."""
    session = tmp_path / "session.yaml"
    session.write_text("camera: {plugin: realsense}\n")
    assert main(["calibrate", "capture", "--config", str(session), "--out", str(tmp_path / "x"), "--no-viewer"]) == 2
    assert "config key 'robot'" in capsys.readouterr().err
    from app.sim.simulator import simulate

    simulate(tmp_path / "trial", scenario_name="static_clear", seconds=0.05, seed=0)
    session.write_text(f"camera: {{plugin: recorded, params: {{trial: {tmp_path / 'trial'}}}}}\n"
                       f"robot: {{plugin: recorded, params: {{trial: {tmp_path / 'trial'}}}}}\n")
    assert main(["calibrate", "capture", "--config", str(session), "--out", str(tmp_path / "y"), "--no-viewer"]) == 2
    err = capsys.readouterr().err
    assert "config key 'camera.params.streams'" in err and "no ir images" in err


def test_bad_board_spec_is_a_config_error(captures, capsys):
    assert main(["calibrate", "intrinsics", "--images", str(captures / "images"),
                 "--board", "charuco:7x5:0.04"]) == 2
    assert "--board" in capsys.readouterr().err
