"""A pointer tool's tip as the start's point (app/tracking/pointer.py; issue 33, item 3): an ArUco
marker rendered into a synthetic infrared image at a known pose gives the tip in the base frame once
held still; the session's ``bone.pointer`` is checked by name."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.errors import ConfigError
from app.geometry.camera import PinholeCamera
from app.interfaces import DepthFrame
from app.marker.aruco import dictionary
from app.session import parse_session
from app.tracking.pointer import HOLD_M, HOLD_S, PointerTip

CAMERA = PinholeCamera(width=640, height=480, K=np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]))
MARKER_ID, LENGTH_M = 7, 0.04
TIP_M = np.array([0.0, -0.10, -0.005])     # 10 cm below the marker's centre, 5 mm behind its face


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _infrared(T_camera_marker: np.ndarray, marker_id: int = MARKER_ID) -> np.ndarray:
    """(H, W) uint8: the marker (a white quiet zone of one module around it) warped onto a grey
    background at ``T_camera_marker`` through CAMERA (pixel centres at integers)."""
    side, quiet = 120, 20
    marker = cv2.aruco.generateImageMarker(dictionary("DICT_4X4_50"), marker_id, side, borderBits=1)
    canvas = np.full((side + 2 * quiet, side + 2 * quiet), 235, np.uint8)
    canvas[quiet:quiet + side, quiet:quiet + side] = np.where(marker > 127, 235, 25)
    n = side + 2 * quiet
    h = 0.5 * LENGTH_M * n / side
    corners_M = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    p = corners_M @ T_camera_marker[:3, :3].T + T_camera_marker[:3, 3]
    uv, _ = CAMERA.project(p)
    px = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32) - 0.5
    H = cv2.getPerspectiveTransform(px, uv.astype(np.float32))
    size = (CAMERA.width, CAMERA.height)
    warped = cv2.warpPerspective(canvas.astype(np.float32), H, size, flags=cv2.INTER_AREA)
    mask = cv2.warpPerspective(np.ones((n, n), np.float32), H, size, flags=cv2.INTER_LINEAR)
    return np.clip(110.0 * (1 - mask) + warped * mask, 0, 255).astype(np.uint8)


def _frame(image, stamp) -> DepthFrame:
    return DepthFrame(0, stamp, np.full((CAMERA.height, CAMERA.width), 0.4, np.float32), stamp, infrared=image)


def _pointer() -> PointerTip:
    return PointerTip(MARKER_ID, LENGTH_M, TIP_M, CAMERA)


# the marker's face towards the camera (M's z out of the face: about pi about x from the camera's axes), tilted
T_CAMERA_MARKER = _pose((Rotation.from_rotvec([0.35, 0.25, 0.1]) * Rotation.from_rotvec([np.pi, 0.0, 0.0])).as_rotvec(),
                        [0.02, -0.03, 0.35])
T_BASE_CAMERA = _pose([2.8, 0.4, -0.2], [0.55, -0.10, 0.62])


def test_the_tip_is_the_marker_pose_times_its_offset_in_the_base_frame():
    pointer = _pointer()
    pointer.observe(_frame(_infrared(T_CAMERA_MARKER), 0.0))
    tip = pointer.tip(T_BASE_CAMERA)
    truth = (T_BASE_CAMERA @ T_CAMERA_MARKER @ np.append(TIP_M, 1.0))[:3]
    assert np.linalg.norm(tip - truth) < 0.002        # IPPE on a sharp synthetic image: well under 2 mm


def test_the_tip_counts_once_held_still_for_hold_s_of_frame_stamps():
    """Seen but not yet held: no point, the reason says to hold it; from HOLD_S on (frame stamps): the
    mean of the held tips. A tip that moves more than HOLD_M starts the hold again; a frame without the
    marker resets it."""
    pointer = _pointer()
    image = _infrared(T_CAMERA_MARKER)
    period = 1.0 / 30
    located = []
    for k in range(12):
        pointer.observe(_frame(image, k * period))
        point, why = pointer.locate(None, T_BASE_CAMERA)
        located.append(point is not None)
        if point is None:
            assert "hold its tip still" in why
    first = located.index(True)
    assert first == int(np.ceil(HOLD_S / period - 1e-9))
    truth = (T_BASE_CAMERA @ T_CAMERA_MARKER @ np.append(TIP_M, 1.0))[:3]
    assert np.linalg.norm(point - truth) < 0.002
    moved = T_CAMERA_MARKER.copy()
    moved[:3, 3] += [3 * HOLD_M, 0.0, 0.0]
    pointer.observe(_frame(_infrared(moved), 1.0))
    assert pointer.locate(None, T_BASE_CAMERA)[0] is None            # moved: the hold starts again
    pointer.observe(_frame(np.full((480, 640), 110, np.uint8), 2.0))
    point, why = pointer.locate(None, T_BASE_CAMERA)
    assert point is None and why == "the pointer (marker 7) is not seen"
    pointer.observe(_frame(_infrared(T_CAMERA_MARKER, marker_id=3), 3.0))   # another marker: not the pointer
    assert pointer.locate(None, T_BASE_CAMERA)[1] == "the pointer (marker 7) is not seen"
    pointer.observe(DepthFrame(0, 4.0, np.zeros((480, 640), np.float32), 4.0))
    assert pointer.locate(None, T_BASE_CAMERA) == (None, "no ir image on this frame for the pointer (marker 7)")


def test_the_start_takes_the_held_tip_as_the_detectors_point():
    from app.tracking.start import StartByDetection
    from tests.test_pointed_pixel import _Recording

    detector = _Recording()
    pointer = _pointer()
    start = StartByDetection(detector, None, pointer)
    image = _infrared(T_CAMERA_MARKER)
    k = 0
    while start.pending and k < 30:
        pointer.observe(_frame(image, k / 30))
        start.attempt(None, None, T_BASE_CAMERA, k / 30)
        k += 1
    assert not start.pending and len(detector.priors) == 1
    truth = (T_BASE_CAMERA @ T_CAMERA_MARKER @ np.append(TIP_M, 1.0))[:3]
    assert np.linalg.norm(detector.priors[0] - truth) < 0.002
    assert start.report()["source"] == "pointer (marker 7)" and start.report()["method"] == "detect_pointed"


# ----------------------------------------------------------------------------- the session file
def _raw(**bone) -> dict:
    return {"camera": {"plugin": "simulated"}, "robot": {"plugin": "simulated"}, "bone": bone}


POINTER = {"marker_id": 7, "marker_length_m": 0.04, "tip_offset_m": [0.0, -0.1, 0.0]}


def test_a_pointer_from_the_session_file():
    config = parse_session(_raw(pointer=POINTER), Path("."))
    assert config.pointer == {**POINTER, "dictionary": "DICT_4X4_50", "stream": "ir"}


@pytest.mark.parametrize("change, key, match", [
    ({"marker_id": -1}, "marker_id", "integer >= 0"),
    ({"marker_id": 1.5}, "marker_id", "integer >= 0"),
    ({"marker_length_m": 40}, "marker_length_m", "side in metres"),
    ({"tip_offset_m": [0, 0.1]}, "tip_offset_m", r"\[x, y, z\]"),
    ({"tip_offset_m": [0, 100, 0]}, "tip_offset_m", "less than 0.5 m"),
    ({"dictionary": "DICT_5X5_9"}, "dictionary", "unknown ArUco dictionary"),
    ({"stream": "depth"}, "stream", "allowed: ir, color"),
    ({"tip": [0, 0, 0]}, "tip", "allowed: marker_id"),
])
def test_a_bad_pointer_is_named_with_the_fix(change, key, match):
    with pytest.raises(ConfigError, match=rf"bone\.pointer\.{key}'.*{match}"):
        parse_session(_raw(pointer={**POINTER, **change}), Path("."))


def test_a_pointer_without_its_marker_or_beside_another_start_is_refused():
    with pytest.raises(ConfigError, match=r"bone\.pointer\.tip_offset_m'.*missing"):
        parse_session(_raw(pointer={"marker_id": 7, "marker_length_m": 0.04}), Path("."))
    with pytest.raises(ConfigError, match=r"bone\.pointer.*not both"):
        parse_session(_raw(pointer=POINTER, point_prior=[0.1, 0.2, 0.3]), Path("."))
    with pytest.raises(ConfigError, match=r"bone\.pointed_pixel.*bone\.pointer, not both"):
        parse_session(_raw(pointer=POINTER, pointed_pixel=[1, 2]), Path("."))


def test_a_pointer_in_a_stream_the_camera_does_not_deliver_is_refused_by_name(tmp_path, capsys):
    """A depth-only simulated camera and a pointer seen in 'ir': the session stops before tracking,
    naming bone.pointer.stream and the camera's streams key."""
    import yaml

    from app.cli import main

    params = {"scenario": "static_clear", "seconds": 0.2, "seed": 1, "trial_dir": str(tmp_path / "trial")}
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump({"camera": {"plugin": "simulated", "params": params},
                                    "robot": {"plugin": "simulated", "params": params},
                                    "bone": {"pointer": POINTER}}))
    assert main(["track", "--config", str(path), "--out", str(tmp_path / "out")]) != 0
    err = capsys.readouterr().err
    assert "config key 'bone.pointer.stream'" in err and "does not deliver (depth only)" in err
    assert 'camera.params.streams: "depth,ir"' in err


def test_a_session_gives_the_pointer_each_frames_infrared_image_and_waits_while_it_is_not_seen(tmp_path, monkeypatch):
    """A simulated session with the infrared stream and no pointer in view (the simulator draws none):
    the pointer gets every frame's infrared image (its reason is 'not seen', never 'no ir image'), so
    every frame is lost, 'initialising' (status.csv), the summary gives that reason, nothing is searched."""
    import json

    import yaml

    from app.cli import main
    from tests.clocks import lockstep_sessions

    lockstep_sessions(monkeypatch, lead_s=0.005)
    params = {"scenario": "static_clear", "seconds": 0.15, "seed": 1, "trial_dir": str(tmp_path / "trial"),
              "streams": "depth,ir"}
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump({"camera": {"plugin": "simulated", "params": params},
                                    "robot": {"plugin": "simulated", "params": params},
                                    "bone": {"pointer": POINTER}, "loop": {"robot_wait_s": 30.0}}))
    out = tmp_path / "out"
    assert main(["track", "--config", str(path), "--out", str(out)]) == 0
    rows = (out / "status.csv").read_text().splitlines()[1:]
    assert len(rows) == json.loads((out / "summary.json").read_text())["processed"] > 5
    assert all(r.split(",")[1:] == ["lost", "initialising", "initialising"] for r in rows), rows[:3]
    start = json.loads((out / "summary.json").read_text())["start"]
    assert start["source"] == "pointer (marker 7)" and start["point"] is None and start["attempts"] == 0
    assert start["waiting"] == "the pointer (marker 7) is not seen"
