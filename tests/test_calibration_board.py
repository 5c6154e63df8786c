"""ChArUco board spec, detection, pose, rendering and intrinsics (calibration.board/.intrinsics)."""
import numpy as np
import pytest

from calibration.board import (DEFAULT_BOARD_SPEC, BoardDetector, BoardSpec, board_image, board_pose,
                               parse_board_spec)
from calibration.intrinsics import (CameraIntrinsics, calibrate_intrinsics, read_camera_yaml,
                                    write_camera_yaml)
from calibration.simulator import BoardRenderer, SimulationConfig, make_scene, plan_captures


def test_default_spec_parses_and_round_trips():
    spec = parse_board_spec(DEFAULT_BOARD_SPEC)
    assert spec == BoardSpec(7, 5, 0.04, 0.03, "DICT_5X5_100")
    assert parse_board_spec(spec.to_string()) == spec
    assert spec.n_corners == 24


def test_yaml_mapping_spec_equals_string_spec(tmp_path):
    text = "{type: charuco, squares: [7, 5], square_length: 0.04, marker_length: 0.03, dictionary: DICT_5X5_100}"
    assert parse_board_spec(text) == parse_board_spec(DEFAULT_BOARD_SPEC)
    path = tmp_path / "board.yaml"
    path.write_text("board:\n  squares: [7, 5]\n  square_length: 0.04\n  marker_length: 0.03\n"
                    "  dictionary: DICT_5X5_100\n")
    assert parse_board_spec(str(path)) == parse_board_spec(DEFAULT_BOARD_SPEC)


@pytest.mark.parametrize("bad, match", [
    ("charuco:7x5:0.04:DICT_5X5_100", "4 ':'-separated fields"),
    ("charuco:7x5:0.04:0.05:DICT_5X5_100", "marker length < square length"),
    ("charuco:7x5:0.04:0.03:DICT_NOPE", "unknown ArUco dictionary"),
    ("chessboard:7x5:0.04:0.03:DICT_5X5_100", "only 'charuco'"),
    ("charuco:7by5:0.04:0.03:DICT_5X5_100", "expected 'charuco:SXxSY"),
])
def test_bad_specs_say_what_is_wrong(bad, match):
    with pytest.raises(ValueError, match=match):
        parse_board_spec(bad)


def test_generated_board_corners_sit_at_documented_pixels():
    image, px_per_m = board_image(DEFAULT_BOARD_SPEC, px_per_square=80)
    det, why = BoardDetector().detect(np.pad(image, 40, constant_values=255))
    assert det is not None, why
    expected = det.points_board[:, :2] * px_per_m - 0.5 + 40
    np.testing.assert_allclose(det.corners_px, expected, atol=0.05)


def test_blank_image_is_reported_not_detected():
    det, why = BoardDetector().detect(np.full((480, 640), 255, np.uint8))
    assert det is None and "0 ChArUco corners" in why


@pytest.fixture(scope="module")
def views():
    cfg = SimulationConfig()
    scene = make_scene(cfg)
    q = plan_captures(scene, 8, np.random.default_rng(7))
    renderer = BoardRenderer(cfg)
    poses = [scene.T_camera_board(qk) for qk in q]
    return cfg, poses, [renderer.render(T) for T in poses]


def test_rendered_board_pose_matches_truth(views):
    cfg, poses, images = views
    detector = BoardDetector(cfg.board)
    for T_true, image in zip(poses, images):
        det, why = detector.detect(image)
        assert det is not None, why
        T, errors = board_pose(det, cfg.K)
        assert np.sqrt(np.mean(errors ** 2)) < 0.2
        assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 1e-3
        cos = (np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2
        assert np.degrees(np.arccos(min(cos, 1.0))) < 0.3


def test_intrinsics_recovered_from_rendered_views(views):
    cfg, _, images = views
    named = {f"{k:06d}.png": im for k, im in enumerate(images)}
    named["blank.png"] = np.full_like(images[0], 255)
    named["unreadable.png"] = None
    result = calibrate_intrinsics(named, cfg.board, fix_k3=True)
    assert {s["image"] for s in result.skipped} == {"blank.png", "unreadable.png"}
    assert len(result.per_image) == 8 and result.rms_px < 0.3
    np.testing.assert_allclose(result.camera.K, cfg.K, atol=3.0)
    assert (result.camera.width, result.camera.height) == (cfg.width, cfg.height)


def test_too_few_board_images_is_an_error():
    with pytest.raises(ValueError, match="only 0 of 1 images"):
        calibrate_intrinsics({"a.png": np.full((480, 640), 255, np.uint8)})


def test_camera_yaml_round_trip(tmp_path):
    cam = CameraIntrinsics(np.array([[600.0, 0, 320], [0, 601.0, 240], [0, 0, 1]]),
                           np.array([0.1, -0.01, 0.0, 0.0, 1e-5]), 640, 480)
    write_camera_yaml(tmp_path / "camera.yaml", cam, {"rms_px": 0.1})
    text = (tmp_path / "camera.yaml").read_text()
    assert "1e-05" not in text     # YAML 1.1 readers take 1e-05 as a string (RECORDING_FORMAT.md)
    back = read_camera_yaml(tmp_path / "camera.yaml")
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_array_equal(back.dist, cam.dist)
