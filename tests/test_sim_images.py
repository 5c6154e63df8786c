"""The simulator's infrared and colour images (app/sim/appearance.py, ir.py, images.py): closed forms of the
shading and the dot pattern's parallax, the appearance a reviewer expects (bone whitish-yellow,
tissue red, glove and gauze brighter than bone, dots only with the emitter on), and
``osteonav simulate --streams depth,ir,color`` writing a 1.1 trial the reader, ``view`` and ``replay`` accept."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.geometry.camera import PinholeCamera
from app.sim.appearance import MATERIALS, FourierNoise, Lamp, OperatingField, shade
from app.sim.images import Imager, parse_streams
from app.sim.ir import DotProjector

CAM = PinholeCamera(np.array([[300.0, 0.0, 79.5], [0.0, 300.0, 59.5], [0.0, 0.0, 1.0]]), 160, 120)


def test_lambert_on_a_plane_facing_a_lamp_on_the_axis():
    """L = albedo (ambient + I cos(theta) / d^2) (+ specular): closed form on a fronto-parallel plane."""
    z = 0.5
    depth = np.full((CAM.height, CAM.width), z)
    rows = np.zeros(depth.shape + (6,))
    rows[..., :3] = (0.8, 0.6, 0.4)
    rows[..., 3] = 0.7
    lamp = Lamp(p0=np.zeros(3), target=np.array([0, 0, 1.0]), spot_exponent=0.0)
    rgb, nir = shade(CAM, depth, np.ones(depth.shape, int), rows, np.zeros(3), np.array([0, 0, 1.0]), lamp,
                     intensity=2.0, ambient=0.1)
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    x, y = (u - CAM.cx) / CAM.fx * z, (v - CAM.cy) / CAM.fy * z
    d2 = x * x + y * y + z * z
    expected = 0.1 + 2.0 * (z / np.sqrt(d2)) / d2          # cos(theta_i) = z / d at the lamp in the lens
    inner = (slice(2, -2), slice(2, -2))                    # normals by central differences
    np.testing.assert_allclose(rgb[..., 0][inner], (0.8 * expected)[inner], rtol=2e-3)
    np.testing.assert_allclose(nir[inner], (0.7 * expected)[inner], rtol=2e-3)


def test_dots_shift_with_depth_by_the_emitter_baseline_parallax():
    """u = fx (b / z + a) + cx for a dot at emitter angle a: planes at z1, z2 see it shifted fx b (1/z1 - 1/z2)."""
    proj = DotProjector(np.random.default_rng(0), p_emitter_camera=np.array([0.0275, 0, 0]))
    z1, z2 = 0.30, 0.45
    a = proj.irradiance(CAM, np.full((CAM.height, CAM.width), z1)) * z1 ** 2
    b = proj.irradiance(CAM, np.full((CAM.height, CAM.width), z2)) * z2 ** 2
    expected = CAM.fx * 0.0275 * (1 / z1 - 1 / z2)          # 9.2 px
    shifts = np.arange(0, 20)
    score = [np.sum(a[:, 30:130] * b[:, 30 - s:130 - s]) for s in shifts]
    assert abs(shifts[int(np.argmax(score))] - expected) <= 1.0
    assert 0.01 < (a > 0.3 * a.max()).mean() < 0.3   # a pattern of dots, not a blur


def test_fourier_noise_is_fixed_in_the_object_frame():
    rng = np.random.default_rng(1)
    noise = FourierNoise(rng, 0.01)
    p = rng.uniform(-0.05, 0.05, (1000, 3))
    np.testing.assert_array_equal(noise(p), noise(p.copy()))
    assert 0.7 < np.std(noise(p)) < 1.3                     # ~N(0, 1) as the thresholds assume


def test_auto_exposure_follows_a_dimmed_light():
    imager = Imager(target=0.3, alpha=0.5, read_noise=0.0, gain_noise=0.0, exposure=1.0)
    rng = np.random.default_rng(2)
    bright = np.full((CAM.height, CAM.width), 0.6)
    for _ in range(20):
        imager.capture(bright, CAM, rng)
    e_bright = imager.exposure
    first_dim = imager.capture(bright / 3, CAM, rng).mean()
    for _ in range(20):
        last_dim = imager.capture(bright / 3, CAM, rng).mean()
    assert imager.exposure == pytest.approx(3 * e_bright, rel=0.02)
    assert first_dim < 0.5 * last_dim                        # lags, then recovers


def test_stream_names_are_checked():
    assert parse_streams("depth, IR,color") == ("depth", "ir", "color")
    with pytest.raises(ValueError, match="includes depth"):
        parse_streams("ir,color")
    with pytest.raises(ValueError, match="unknown: rgb"):
        parse_streams("depth,rgb")


def test_materials_order_as_in_surgery():
    lum = {k: np.dot(m.albedo, (0.2126, 0.7152, 0.0722)) for k, m in MATERIALS.items()}
    assert lum["gauze"] > lum["bone"] and lum["glove"] > lum["bone"] > lum["fat"] > lum["muscle"] > lum["blood"]


def test_glove_and_gauze_outshine_the_bone_under_the_same_light():
    """One plane under the lamp: left half glove (hand), right half bone; then tissue with the gauze swab."""
    rng = np.random.default_rng(3)
    field = OperatingField(rng, np.array([[-0.05, -0.02, -0.01], [0.05, 0.02, 0.01]]), np.array([0.0, 0.0, 0.4]))
    depth = np.full((CAM.height, CAM.width), 0.4)
    labels = np.ones(depth.shape, int)
    labels[:, : CAM.width // 2] = 4
    T_camera_base = np.eye(4)     # base = camera here: the lamp is 1 m behind the plane's side of the camera
    T_camera_base[2, 3] = 0.0
    T_objects = {1: np.eye(4), 4: np.eye(4)}
    rgb, _ = field.radiance(CAM, depth, labels, T_objects, T_camera_base, t=0.0)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    lamp_lit = lum > 0
    assert lamp_lit.mean() > 0.5
    assert np.median(lum[(labels == 4) & lamp_lit]) > np.median(lum[(labels == 1) & lamp_lit])
    # the gauze rectangle on the tissue (bone frame = tissue frame) is brighter than the tissue around it
    rows = field.textures.materials(2, np.column_stack([np.tile(field.textures.gauze_centre, (50, 1)), np.zeros(50)]))
    others = field.textures.materials(2, np.random.default_rng(4).uniform(-0.05, 0.05, (500, 3)))
    bone = field.textures.materials(1, np.random.default_rng(5).uniform(-0.05, 0.05, (500, 3)))
    assert np.median(rows[:, :3].mean(axis=1)) > np.median(bone[:, :3].mean(axis=1)) > np.median(others[:, :3].mean(axis=1))
    # bone whitish-yellow, tissue red: in albedo
    assert np.all(np.median(bone[:, :3], axis=0)[[0, 1]] > np.median(bone[:, :3], axis=0)[[1, 2]])
    r, g, b = np.median(others[:, :3], axis=0)
    assert r > 2 * g


@pytest.fixture(scope="module")
def image_trial(tmp_path_factory):
    from app.sim.scenarios import get_scenario
    from app.sim.simulator import simulate

    scenario = replace(get_scenario("static_occluded", 0.06), occlusion_profile=((0.0, 0.4), (1.0, 0.4)))
    out = tmp_path_factory.mktemp("sim") / "trial"
    simulate(out, scenario_name=scenario, seed=4, streams="depth,ir,color")
    off = tmp_path_factory.mktemp("sim") / "off"
    simulate(off, scenario_name=scenario, seed=4, streams="depth,ir", emitter=False)
    return out, off


def _labels(trial, index):
    """The exact labels of frame ``index`` re-rendered (the simulator does not store them)."""
    from app.render.context import shared_context
    from app.render.scene import SceneRenderer
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    mesh = reader.load_mesh()
    T_camera_base = np.linalg.inv(reader.camera_poses()[0][index])
    # the hand-eye in trial.yaml equals the true one in static_occluded (no calibration error)
    r = SceneRenderer(shared_context(), reader.meta.camera)
    r.add_mesh("bone", mesh.vertices, mesh.faces, 1)
    depth, labels = r.render({"bone": T_camera_base @ reader.groundtruth[index]})
    r.release()
    return labels


def test_simulated_images_look_like_surgery(image_trial):
    from app.trial.reader import open_trial

    on, off = image_trial
    reader = open_trial(on)
    assert reader.meta.streams.names == ("ir", "color") and reader.meta.streams.infrared.emitter
    frame = next(reader.iter_frames())
    assert frame.infrared.shape == (480, 640) and frame.color.shape == (480, 640, 3)
    bone = _labels(on, 0) == 1
    bone &= frame.depth_m > 0
    assert bone.sum() > 500
    # bone whitish-yellow where it is seen in the colour image: the colour camera sits 15 mm away, so
    # use the pixels of the median bone colour instead of re-registering
    rgb = frame.color[bone].astype(float)
    r, g, b = np.median(rgb, axis=0)
    assert r > g > b and r > 120 and b > 0.45 * r              # pale yellow, not red
    assert np.mean(frame.infrared[bone] == 255) < 0.05        # exposed for the field, not blown out
    # the dot pattern: bright points on the bone with the emitter, hardly any without
    f_off = next(open_trial(off).iter_frames())
    import cv2

    def peaks(ir):   # isolated bright points: local 3x3 maxima brighter than their 5x5 median by 30 grey levels
        local_max = ir >= cv2.dilate(ir, np.ones((3, 3), np.uint8))
        return (local_max & ((ir.astype(int) - cv2.medianBlur(ir, 5).astype(int)) > 30))[bone].mean()

    print(f"dot peaks on the bone: emitter on {peaks(frame.infrared):.4f}, off {peaks(f_off.infrared):.4f}")
    assert peaks(frame.infrared) > 0.008 and peaks(frame.infrared) > 10 * peaks(f_off.infrared)
    assert f_off.color is None and not open_trial(off).meta.streams.infrared.emitter


def _rerun_rows(rrd) -> dict[tuple[str, str], int]:
    """{(entity, archetype): rows} of a .rrd, from ``rerun rrd print`` (its chunk summary lines)."""
    import re
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    cli = Path(shutil.which("rerun") or Path(sys.executable).parent / "rerun")
    if not cli.exists():
        pytest.skip("rerun CLI not installed")
    text = subprocess.run([str(cli), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120).stdout
    rows: dict[tuple[str, str], int] = {}
    for n, entity, columns in re.findall(r"with (\d+) rows .* - (/\S+) - data columns: \[([^\]]*)\]", text):
        archetype = columns.split(":")[0]
        rows[entity, archetype] = rows.get((entity, archetype), 0) + int(n)
    return rows


def test_image_trial_is_accepted_by_view_and_replay(image_trial, tmp_path):
    """``view`` logs every frame's depth, infrared and colour image; ``replay`` tracks every frame."""
    from app.cli import main
    from app.trial.reader import open_trial

    on, _ = image_trial
    n = len(open_trial(on))
    assert n == 5                                              # 0.06 s at 90 Hz: 5.4 frame periods
    assert main(["view", str(on), "--save", str(tmp_path / "v.rrd")]) == 0
    rows = _rerun_rows(tmp_path / "v.rrd")
    assert rows[("/world/camera/image/depth", "DepthImage")] == n
    assert rows[("/world/camera/image/infrared", "EncodedImage")] == n
    assert rows[("/world/camera/color/image", "EncodedImage")] == n
    assert main(["replay", str(on), "--out", str(tmp_path / "r"), "--no-rrd"]) == 0
    assert (tmp_path / "r" / "status.csv").read_text().count("\n") == n + 1
    assert (tmp_path / "r" / "estimate.txt").read_text().count("\n") == n + 1


def test_simulated_session_with_images_records_a_trial_that_view_and_replay_accept(image_trial, tmp_path, monkeypatch):
    """``osteonav record`` of ``camera: simulated`` with streams depth,ir,color: the recorder writes format 1.1
    with every frame's own images (bit-exact against the played trial). On the lockstep clock
    (tests/clocks.py) the camera never falls behind its schedule, so it delivers every frame on any
    machine (in real time a loaded machine skips to the newest due frame, issue 15 item 11)."""
    import yaml

    from app.cli import main
    from app.trial.reader import open_trial
    from tests.clocks import lockstep_sessions

    clocks = lockstep_sessions(monkeypatch)
    on, _ = image_trial
    params = {"scenario": "static_occluded", "seconds": 0.06, "seed": 4, "trial_dir": str(on), "streams": "depth,ir,color"}
    session = {"camera": {"plugin": "simulated", "params": params}, "robot": {"plugin": "simulated", "params": params},
               "tracker": False, "loop": {"robot_wait_s": 30.0}}
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(session))
    rec = tmp_path / "rec"
    assert main(["record", "--config", str(path), "--out", str(rec)]) == 0
    recorded, played = open_trial(rec), open_trial(on)
    assert yaml.safe_load((rec / "trial.yaml").read_text())["format"] == "osteonav-trial/1.1"
    assert recorded.meta.streams.color.camera == played.meta.streams.color.camera
    np.testing.assert_allclose(recorded.meta.streams.color.T_depth_color, played.meta.streams.color.T_depth_color)
    # every played frame, in order, with its own depth, infrared and colour images, bit for bit
    assert clocks[0].frames_pushed == len(played) == 5
    assert list(recorded.frame_ids) == list(played.frame_ids)
    for f, g in zip(recorded.iter_frames(), played.iter_frames()):
        np.testing.assert_array_equal(f.depth_m, g.depth_m)
        np.testing.assert_array_equal(f.infrared, g.infrared)
        np.testing.assert_array_equal(f.color, g.color)
    assert main(["view", str(rec), "--save", str(tmp_path / "rec.rrd")]) == 0
    assert main(["replay", str(rec), "--out", str(tmp_path / "r"), "--no-rrd"]) == 0
