"""Trial writer -> reader round trips (RECORDING_FORMAT.md), the YAML float rule, camera poses, and
interrupted recordings that stay readable."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from app.geometry import quaternion as quat
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.geometry.ur import UR_MODELS, DHParameters, forward_kinematics
from app.trial.meta import MARKER_FILE, TrialMeta, dump_meta, load_meta
from app.trial.reader import open_trial
from app.trial.writer import TrialWriter

WIDTH, HEIGHT = 32, 24
DEPTH_SCALE = 0.1  # mm per PNG unit


def random_pose(rng: np.random.Generator, scale: float = 0.5) -> np.ndarray:
    return se3.from_quat_trans(quat.random_uniform(rng, 1)[0], rng.uniform(-scale, scale, 3))


def make_meta(rng: np.random.Generator, robot: dict | None = None, **kw) -> TrialMeta:
    camera = PinholeCamera(np.array([[30.0, 0.0, 15.5], [0.0, 31.0, 11.5], [0.0, 0.0, 1.0]]), WIDTH, HEIGHT)
    robot = robot or {"model": "ur5e"}
    dh = UR_MODELS["ur5e"] if "model" in robot else DHParameters(**{k: np.asarray(v) for k, v in robot["dh"].items()})
    fields = dict(camera=camera, depth_scale=DEPTH_SCALE, robot=robot, dh=dh, T_flange_camera=random_pose(rng, 0.1),
                  mesh="bone.ply", initial_pose=random_pose(rng), point_prior=rng.uniform(-1, 1, 3), extra={})
    fields.update(kw)
    return TrialMeta(**fields)


def make_depth(rng: np.random.Generator) -> np.ndarray:
    depth = rng.uniform(0.2, 1.5, (HEIGHT, WIDTH)).astype(np.float32)
    depth[rng.random((HEIGHT, WIDTH)) < 0.1] = 0.0
    depth[0, 0] = np.nan
    depth[0, 1] = -0.3
    return depth


def bone_mesh(tmp_path: Path) -> Path:
    path = tmp_path / "source_bone.ply"
    if not path.exists():
        trimesh.creation.box((0.05, 0.02, 0.01)).export(path)
    return path


def write_trial(tmp_path: Path, rng: np.random.Generator, n_frames: int = 5, groundtruth: bool = True,
                close: bool = True, name: str = "trial", **meta_kw):
    """A small trial; returns (dir, dict of what was written). ``close=False`` leaves it as a killed writer would."""
    out = tmp_path / name
    meta = make_meta(rng, **meta_kw)
    frame_ids = np.cumsum(rng.integers(1, 3, n_frames)) + 10
    stamps = 12.0 + np.cumsum(rng.uniform(0.02, 0.04, n_frames))
    joint_stamps = np.arange(stamps[0] - 0.01, stamps[-1] + 0.01, 0.002)
    joints = np.column_stack([np.sin(joint_stamps * (i + 1)) for i in range(6)])
    depths = [make_depth(rng) for _ in range(n_frames)]
    T_gt = np.array([random_pose(rng) for _ in range(n_frames)])
    writer = TrialWriter(out, meta, mesh_source=bone_mesh(tmp_path))
    writer.write_joints(joint_stamps[:10], joints[:10])
    writer.write_joints(joint_stamps[10], joints[10])         # one sample
    writer.write_joints(joint_stamps[11:], joints[11:])
    for k in range(n_frames):
        writer.write_frame(frame_ids[k], stamps[k], depths[k])
        if groundtruth:
            writer.write_groundtruth(stamps[k], T_gt[k])
    if close:
        writer.close()
    return out, dict(meta=meta, frame_ids=frame_ids, stamps=stamps, joint_stamps=joint_stamps, joints=joints,
                     depths=depths, T_gt=T_gt, writer=writer)


def expected_depth(depth: np.ndarray) -> np.ndarray:
    out = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    return np.round(out * 1000 / DEPTH_SCALE) * DEPTH_SCALE / 1000


def test_round_trip_keeps_depth_to_quantisation_and_everything_else(tmp_path, rng):
    out, w = write_trial(tmp_path, rng)
    reader = open_trial(out)
    assert not reader.interrupted and not (out / MARKER_FILE).exists()
    np.testing.assert_array_equal(reader.frame_ids, w["frame_ids"])
    np.testing.assert_allclose(reader.stamps, w["stamps"], atol=1e-9)
    np.testing.assert_allclose(reader.joint_stamps, w["joint_stamps"], atol=1e-9)
    np.testing.assert_array_equal(reader.joints, w["joints"])   # repr round-trips floats exactly
    np.testing.assert_allclose(reader.groundtruth, w["T_gt"], atol=1e-8)
    frames = list(reader.iter_frames())
    assert [f.index for f in frames] == list(range(5))
    for f, depth in zip(frames, w["depths"]):
        assert f.depth_m.dtype == np.float32 and f.depth_m.shape == (HEIGHT, WIDTH)
        np.testing.assert_allclose(f.depth_m, expected_depth(depth), atol=1e-7)
        assert np.max(np.abs(f.depth_m - np.nan_to_num(depth))[f.depth_m > 0]) <= DEPTH_SCALE / 2000 + 1e-7
        assert f.depth_m[0, 0] == 0 and f.depth_m[0, 1] == 0    # NaN and negative -> no measurement
    np.testing.assert_array_equal(reader.read_depth(2), frames[2].depth_m)
    m, m0 = reader.meta, w["meta"]
    np.testing.assert_array_equal(m.camera.K, m0.camera.K)
    assert (m.camera.width, m.camera.height, m.depth_scale, m.robot, m.mesh) == (WIDTH, HEIGHT, DEPTH_SCALE, {"model": "ur5e"}, "bone.ply")
    np.testing.assert_array_equal(m.T_flange_camera, m0.T_flange_camera)
    np.testing.assert_array_equal(m.initial_pose, m0.initial_pose)
    np.testing.assert_array_equal(m.point_prior, m0.point_prior)
    assert reader.mesh_path == out / "bone.ply"
    assert len(reader.load_mesh().faces) == 12


def test_round_trip_of_dh_form_without_optional_keys(tmp_path, rng):
    dh = {"a": [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0], "d": [0.1625, 0.0, 0.0, 0.1333, 0.0997, 1e-05],
          "alpha": [1.5707963, 0.0, 0.0, 1.5707963, -1.5707963, 0.0]}
    out, _ = write_trial(tmp_path, rng, groundtruth=False, robot={"dh": dh}, initial_pose=None, point_prior=None,
                         extra={"notes": "bench test", "generator": {"seed": 3}})
    text = (out / "trial.yaml").read_text()
    assert "1.0e-05" in text and "1e-05" not in text.replace("1.0e-05", "")
    reader = open_trial(out)
    assert reader.groundtruth is None and reader.meta.initial_pose is None and reader.meta.point_prior is None
    np.testing.assert_array_equal(reader.meta.dh.d, dh["d"])
    assert reader.meta.robot == {"dh": dh}
    assert reader.meta.extra == {"notes": "bench test", "generator": {"seed": 3}}


def test_meta_accepts_floats_that_yaml_1_1_reads_as_strings(tmp_path, rng):
    path = tmp_path / "trial.yaml"
    dump_meta(make_meta(rng), path)
    data = yaml.safe_load(path.read_text())
    data["camera"]["depth_scale"] = "1e-01"
    data["point_prior"] = ["1e-3", 0, 2]
    text = yaml.safe_dump(data).replace("'1e-01'", "1e-01").replace("'1e-3'", "1e-3")
    assert "1e-01" in text
    path.write_text(text)
    assert isinstance(yaml.safe_load(text)["camera"]["depth_scale"], str)   # what PyYAML does with it
    meta = load_meta(path)
    assert meta.depth_scale == pytest.approx(0.1)
    np.testing.assert_array_equal(meta.point_prior, [1e-3, 0.0, 2.0])


def test_camera_poses_are_fk_of_interpolated_joints_and_flag_frames_outside(tmp_path, rng, caplog):
    out, w = write_trial(tmp_path, rng, n_frames=6)
    # cut the joint samples so that the last frame lies after them
    lines = (out / "joints.csv").read_text().splitlines()
    keep = [lines[0]] + [ln for ln in lines[1:] if float(ln.split(",")[0]) < w["stamps"][-1] - 0.003]
    (out / "joints.csv").write_text("\n".join(keep) + "\n")
    reader = open_trial(out)
    with caplog.at_level(logging.WARNING):
        T, valid = reader.camera_poses()
    assert valid.tolist() == [True] * 5 + [False]
    assert np.all(np.isnan(T[5])) and "1 of 6 frames" in caplog.text
    k = 2
    t = w["stamps"][k]
    q = np.array([np.interp(t, reader.joint_stamps, reader.joints[:, i]) for i in range(6)])
    np.testing.assert_allclose(T[k], forward_kinematics(UR_MODELS["ur5e"], q) @ w["meta"].T_flange_camera, atol=1e-12)


def test_writer_refuses_an_existing_trial_unless_overwrite(tmp_path, rng):
    from app.errors import TrialFormatError

    out, _ = write_trial(tmp_path, rng)
    (out / "notes.txt").write_text("keep me")
    with pytest.raises(TrialFormatError, match="already holds a trial"):
        TrialWriter(out, make_meta(rng))
    with TrialWriter(out, make_meta(rng), overwrite=True) as w:
        w.write_frame(0, 1.0, np.full((HEIGHT, WIDTH), 0.5))
    reader = open_trial(out)
    assert reader.frame_ids.tolist() == [0] and reader.groundtruth is None
    assert (out / "notes.txt").read_text() == "keep me"


def test_writer_rejects_non_increasing_input_and_wrong_shapes(tmp_path, rng):
    with TrialWriter(tmp_path / "t", make_meta(rng), mesh_source=bone_mesh(tmp_path)) as w:
        w.write_frame(3, 1.0, np.zeros((HEIGHT, WIDTH)))
        with pytest.raises(ValueError, match="frame ids must increase"):
            w.write_frame(3, 2.0, np.zeros((HEIGHT, WIDTH)))
        with pytest.raises(ValueError, match="stamps must be finite and increase"):
            w.write_frame(4, 1.0, np.zeros((HEIGHT, WIDTH)))
        with pytest.raises(ValueError, match="expected \\(24, 32\\)"):
            w.write_frame(4, 2.0, np.zeros((HEIGHT + 1, WIDTH)))
        w.write_joints([0.5, 0.6], np.zeros((2, 6)))
        with pytest.raises(ValueError, match="increase strictly"):
            w.write_joints(0.6, np.zeros(6))
        with pytest.raises(ValueError, match="finite"):
            w.write_joints(0.7, [0, 0, np.nan, 0, 0, 0])
        with pytest.raises(ValueError, match=r"q \(M, 6\)"):
            w.write_joints([0.8], np.zeros((1, 5)))
        with pytest.raises(ValueError, match="differs from frame 0"):
            w.write_groundtruth(1.5, np.eye(4))
        w.write_groundtruth(1.0, np.eye(4))
        with pytest.raises(ValueError, match="write the frame first"):
            w.write_groundtruth(2.0, np.eye(4))


def test_depth_beyond_png_range_is_clipped(tmp_path, rng):
    with TrialWriter(tmp_path / "t", make_meta(rng), mesh_source=bone_mesh(tmp_path)) as w:
        w.write_frame(0, 1.0, np.full((HEIGHT, WIDTH), 9.0))
    assert open_trial(tmp_path / "t").read_depth(0).max() == pytest.approx(65535 * DEPTH_SCALE / 1000)


# ---------------------------------------------------------------- interrupted recordings

def test_killed_writer_leaves_a_readable_interrupted_trial(tmp_path, rng, caplog):
    out, w = write_trial(tmp_path, rng, n_frames=6, close=False)
    # the kill landed mid-row in both CSV files, and after a PNG whose row never came
    with open(out / "frames.csv", "a") as f:
        f.write("99,13.4")
    with open(out / "joints.csv", "a") as f:
        f.write("14.0,0.1,0.2")
    with open(out / "groundtruth.txt", "a") as f:
        f.write("13.4 0.1 0.2")
    assert (out / MARKER_FILE).exists()
    with caplog.at_level(logging.WARNING):
        reader = open_trial(out)
    assert reader.interrupted
    assert "interrupted" in caplog.text and "6 of 6 listed frames readable" in caplog.text
    np.testing.assert_array_equal(reader.frame_ids, w["frame_ids"])
    np.testing.assert_allclose(reader.joint_stamps, w["joint_stamps"], atol=1e-9)
    assert len(reader.groundtruth) == 6
    assert len(list(reader.iter_frames())) == 6


def test_interrupted_trial_drops_frames_without_png_or_groundtruth(tmp_path, rng, caplog):
    out, w = write_trial(tmp_path, rng, n_frames=6, close=False)
    (out / f"depth/{w['frame_ids'][2]:06d}.png").unlink()
    lines = (out / "groundtruth.txt").read_text().splitlines(keepends=True)
    (out / "groundtruth.txt").write_text("".join(lines[:-1]))   # killed before the last frame's pose
    with caplog.at_level(logging.WARNING):
        reader = open_trial(out)
    assert "4 of 6 listed frames readable" in caplog.text
    np.testing.assert_array_equal(reader.frame_ids, w["frame_ids"][[0, 1, 3, 4]])
    np.testing.assert_allclose(reader.groundtruth, w["T_gt"][[0, 1, 3, 4]], atol=1e-8)
    T, valid = reader.camera_poses()
    assert T.shape == (4, 4, 4) and valid.all()


def test_exception_inside_writer_context_keeps_the_interrupted_marker(tmp_path, rng):
    with pytest.raises(RuntimeError):
        with TrialWriter(tmp_path / "t", make_meta(rng), mesh_source=bone_mesh(tmp_path)) as w:
            w.write_frame(0, 1.0, np.zeros((HEIGHT, WIDTH)))
            raise RuntimeError("camera unplugged")
    assert (tmp_path / "t" / MARKER_FILE).exists()
    assert open_trial(tmp_path / "t").interrupted
