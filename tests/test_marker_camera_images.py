"""The marker + IMU tracker reading the session camera's infrared images (``images: ir``) from
``camera: marker_simulated`` (the marker simulator's camera as a session camera): tracked as well
as when it renders its own images."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from app.cli import main
from app.geometry import se3
from app.trial.tum import read_tum

SECONDS = 4.0
Q = [0.0, -1.6, 1.6, -1.57, -1.57, 0.0]


def _session(tmp_path, images: str) -> dict:
    session = {
        "camera": {"plugin": "marker_simulated", "params": {"seconds": SECONDS, "seed": 3}},
        "robot": {"plugin": "static", "params": {"q": Q}, "model": "ur5e"},
        "calibration": {"hand_eye": np.eye(4).tolist()},
        "bone": {"mesh": "../../meshes/iliac_crest.ply", "initial_pose": np.eye(4).tolist()},
        "tracker": {"plugin": "marker_imu", "params": {"images": images, "imu": "simulated", "seed": 3, "rerun": "off"}},
    }
    return session


def _errors_mm(out, sim) -> np.ndarray:
    from app.geometry.ur import UR_MODELS, forward_kinematics

    stamps, T_base_bone = read_tum(out / "estimate.txt")
    statuses = [line.split(",")[1] for line in (out / "status.csv").read_text().splitlines()[1:]]
    T_camera_base = se3.inverse(forward_kinematics(UR_MODELS["ur5e"], np.asarray(Q)))
    k = np.rint((stamps - stamps[0]) * sim.sc.camera_fps)
    _, p_true = sim.pose(k / sim.sc.camera_fps)
    p_est = (T_camera_base @ T_base_bone)[:, :3, 3]
    ok = np.array(statuses) == "ok"
    return 1e3 * np.linalg.norm(p_est - p_true, axis=1), ok


@pytest.mark.parametrize("images", ["ir", "simulated"])
def test_marker_session_tracks_from_the_cameras_images(tmp_path, images):
    from app.marker.simulator import MarkerScenario, MarkerSimulator

    repo = __import__("pathlib").Path(__file__).resolve().parents[1]
    cfg = tmp_path / "configs" / "sessions"
    cfg.mkdir(parents=True)
    session = _session(tmp_path, images)
    session["bone"]["mesh"] = str(repo / "meshes" / "iliac_crest.ply")
    (cfg / "s.yaml").write_text(yaml.safe_dump(session))
    out = tmp_path / "out"
    assert main(["track", "--config", str(cfg / "s.yaml"), "--out", str(out)]) == 0
    sim = MarkerSimulator(MarkerScenario(seconds=600.0, seed=3))
    errors, ok = _errors_mm(out, sim)
    print(f"images {images}: {ok.mean():.0%} ok, position error median {np.median(errors[ok]):.2f} mm, "
          f"max {errors[ok].max():.2f} mm")
    assert ok.mean() > 0.8, f"{images}: only {ok.mean():.0%} ok"
    assert np.median(errors[ok]) < 5.0, f"{images}: median {np.median(errors[ok]):.1f} mm"
