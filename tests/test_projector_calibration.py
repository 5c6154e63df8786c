"""Projector calibration: Gray-code encode/decode, and recovery of K_p and T_camera_projector in simulation."""
import argparse

import numpy as np
import pytest
import yaml

from app.cli import main
from app.errors import ConfigError
from app.geometry import se3
from calibration.graycode import bit_count, decode, gray_decode, gray_encode, pattern_count, patterns
from calibration.projector import (ProjectorSimulation, calibrate_projector, run_command, simulate_views,
                                  write_captures)


def test_gray_code_neighbours_differ_in_one_bit_and_decode_back():
    i = np.arange(4096)
    g = gray_encode(i)
    assert np.all(np.bitwise_count((g[1:] ^ g[:-1]).astype(np.uint64)) == 1)
    np.testing.assert_array_equal(gray_decode(g), i)
    assert bit_count(640) == 10 and bit_count(1024) == 10 and bit_count(1025) == 11


def test_patterns_decode_to_their_own_pixel_coordinates():
    P = patterns(100, 37)
    assert P.shape == (pattern_count(100, 37), 37, 100) == (2 + 2 * (7 + 6), 37, 100)
    d = decode(P, 100, 37)
    assert d.valid.all()
    np.testing.assert_array_equal(d.col, np.broadcast_to(np.arange(100), (37, 100)))
    np.testing.assert_array_equal(d.row, np.broadcast_to(np.arange(37)[:, None], (37, 100)))


def test_decode_rejects_unlit_and_low_contrast_pixels():
    P = patterns(64, 32).astype(np.float32)
    P[:, :, :10] = 40.0                              # the projector does not reach these pixels
    P[5, 20:, :] = P[4, 20:, :] = 100.0              # one bit without contrast
    d = decode(P, 64, 32)
    assert not d.valid[:, :10].any() and not d.valid[20:].any() and d.valid[:20, 10:].all()
    with pytest.raises(ValueError, match="expected 24 captures"):
        decode(P[:-1], 64, 32)


@pytest.fixture(scope="module")
def simulated():
    sim = ProjectorSimulation(pixel_noise=1.5)
    return sim, simulate_views(sim, 5, np.random.default_rng(7))


def test_calibration_recovers_the_simulated_projector(simulated):
    sim, views = simulated
    result = calibrate_projector(views, sim.projector_size, sim.K_camera, board=sim.board, distortion="none")
    assert not result.skipped and len(result.per_view) == 5
    np.testing.assert_allclose(np.diag(result.K)[:2], np.diag(sim.K_projector)[:2], rtol=0.01)
    np.testing.assert_allclose(result.K[:2, 2], sim.K_projector[:2, 2], atol=2.0)
    assert np.linalg.norm(result.T_camera_projector[:3, 3] - sim.T_camera_projector[:3, 3]) < 0.002
    assert np.rad2deg(se3.rotation_angle(result.T_camera_projector, sim.T_camera_projector)) < 0.3
    assert result.rms_projector_px < 0.5 and result.rms_stereo_px < 0.5


def test_calibrate_projector_command_writes_a_loadable_projector_yaml(simulated, tmp_path, capsys):
    from app.projector.config import parse_projector_config

    sim, views = simulated
    folder = tmp_path / "cal"
    write_captures(folder, [v[1] for v in views], sim.projector_size, sim.board, sim.K_camera, sim.camera_size,
                   truth=sim.truth())
    (folder / "pose_001" / "pattern_003.png").unlink()
    assert main(["calibrate", "projector", "--captures", str(folder)]) == 0
    printed = capsys.readouterr().out
    assert "skipped pose_001" in printed and "vs truth" in printed and "RMS reprojection" in printed
    assert "with 'k1k2' the projector RMS would be" in printed
    data = yaml.safe_load((folder / "projector.yaml").read_text())
    model = parse_projector_config(data).projector
    assert (model.width, model.height) == sim.projector_size
    assert data["calibration"]["rms_stereo_px"] < 0.5


def test_too_few_usable_poses_is_a_config_error(simulated, tmp_path):
    sim, views = simulated
    folder = tmp_path / "few"
    write_captures(folder, [v[1] for v in views[:2]], sim.projector_size, sim.board, sim.K_camera, sim.camera_size)
    args = argparse.Namespace(simulate=0, captures=folder, camera=None, board=None, out=None, distortion="none")
    with pytest.raises(ConfigError, match="2 usable board poses, need at least 3"):
        run_command(args)


def test_distortion_models_and_the_alternative_rms(simulated):
    """'k1k2' fits radial terms (non-zero k1, k2; no tangential), 'none' fits none; each reports the
    other's projector RMS, which for nested models is never below the richer model's own."""
    sim, views = simulated
    plain = calibrate_projector(views, sim.projector_size, sim.K_camera, board=sim.board, distortion="none")
    radial = calibrate_projector(views, sim.projector_size, sim.K_camera, board=sim.board, distortion="k1k2")
    assert np.all(plain.dist == 0) and np.any(radial.dist[:2] != 0) and np.all(radial.dist[2:] == 0)
    assert plain.alternative_rms_px["k1k2"] == pytest.approx(radial.rms_projector_px, rel=1e-6)
    assert radial.alternative_rms_px["none"] == pytest.approx(plain.rms_projector_px, rel=1e-6)
    assert radial.rms_projector_px <= plain.rms_projector_px + 1e-9
    with pytest.raises(ValueError, match="distortion model"):
        calibrate_projector(views, sim.projector_size, sim.K_camera, board=sim.board, distortion="k1k2k3")
