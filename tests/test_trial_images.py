"""Trial format 1.1 (RECORDING_FORMAT.md, last section): infrared and colour streams written, read back
bit-exactly, validated with errors that name the file and key; version 1 trials stay readable.

``tests/data/trial_v1_sim`` is a version 1 trial written by the writer of commit 635604e (before
format 1.1 existed): ``osteonav simulate`` of static_clear, 0.15 s, seed 5, 160x120 camera."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from app.errors import TrialFormatError
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.image_streams import ColorStream, ImageStreams, InfraredStream
from app.trial.meta import FORMAT, FORMAT_1_1, MARKER_FILE, load_meta
from app.trial.reader import open_trial
from app.trial.writer import TrialWriter
from tests.test_trial_io import HEIGHT, WIDTH, bone_mesh, make_depth, make_meta

V1_TRIAL = Path(__file__).parent / "data" / "trial_v1_sim"
COLOR_CAMERA = PinholeCamera(np.array([[40.0, 0.0, 19.5], [0.0, 41.0, 14.5], [0.0, 0.0, 1.0]]), 40, 30)


def color_stream(rng) -> ColorStream:
    T = se3.from_quat_trans(np.array([0.99, 0.01, -0.02, 0.1]) / np.linalg.norm([0.99, 0.01, -0.02, 0.1]),
                            np.array([0.015, 0.0002, -0.0001]))
    return ColorStream(COLOR_CAMERA, distortion=rng.normal(0, 0.05, 5), T_depth_color=T)


def write_images_trial(tmp_path, rng, streams: ImageStreams, n: int = 4, close: bool = True):
    meta = make_meta(rng, streams=streams)
    out = tmp_path / "trial11"
    written = []
    w = TrialWriter(out, meta, mesh_source=bone_mesh(tmp_path))
    w.write_joints(np.arange(0.0, 20.0, 0.01), np.zeros((2000, 6)))
    for k in range(n):
        ir = rng.integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
        cam = streams.color.camera if streams.color is not None else None
        rgb = rng.integers(0, 256, (cam.height, cam.width, 3), dtype=np.uint8) if cam is not None else None
        depth = make_depth(rng)
        w.write_frame(10 + 2 * k, 12.0 + 0.03 * k, depth, infrared=ir, color=rgb)
        written.append((ir, rgb))
    if close:
        w.close()
    return out, meta, written


def test_ir_and_unaligned_colour_round_trip_bit_exact(tmp_path):
    rng = np.random.default_rng(1)
    streams = ImageStreams(InfraredStream(emitter=False), color_stream(rng))
    out, meta, written = write_images_trial(tmp_path, rng, streams)
    data = yaml.safe_load((out / "trial.yaml").read_text())
    assert data["format"] == FORMAT_1_1
    assert data["infrared"] == {"dir": "ir", "emitter": False}
    assert data["color"]["aligned_to_depth"] is False and data["color"]["width"] == 40
    reader = open_trial(out)
    c = reader.meta.streams.color
    assert reader.meta.streams.infrared.emitter is False
    assert c.camera == COLOR_CAMERA
    np.testing.assert_allclose(c.distortion, streams.color.distortion, rtol=0, atol=1e-15)
    np.testing.assert_allclose(c.T_depth_color, streams.color.T_depth_color, rtol=0, atol=1e-15)
    frames = list(reader.iter_frames())
    assert len(frames) == 4
    for f, (ir, rgb) in zip(frames, written):
        np.testing.assert_array_equal(f.infrared, ir)
        np.testing.assert_array_equal(f.color, rgb)   # RGB in, RGB out (PNG channel order on disk)
    import cv2   # on disk: PNG channel order is RGB, so an RGB-reading tool sees the same pixels
    bgr = cv2.imread(str(out / "color" / "000010.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(bgr[..., ::-1], written[0][1])


def test_aligned_colour_has_the_depth_camera_and_no_extrinsics(tmp_path):
    rng = np.random.default_rng(2)
    depth_cam = make_meta(np.random.default_rng(2)).camera
    streams = ImageStreams(None, ColorStream(depth_cam, aligned_to_depth=True))
    out, _, written = write_images_trial(tmp_path, rng, streams, n=2)
    data = yaml.safe_load((out / "trial.yaml").read_text())
    assert data["color"] == {"dir": "color", "aligned_to_depth": True}
    assert "infrared" not in data and not (out / "ir").exists()
    reader = open_trial(out)
    assert reader.meta.streams.color.camera == reader.meta.camera
    f = next(reader.iter_frames())
    assert f.infrared is None and f.color.shape == (HEIGHT, WIDTH, 3)
    np.testing.assert_array_equal(f.color, written[0][1])


def test_writer_rejects_frames_without_the_declared_images(tmp_path):
    rng = np.random.default_rng(3)
    meta = make_meta(rng, streams=ImageStreams(InfraredStream()))
    with TrialWriter(tmp_path / "t", meta, mesh_source=bone_mesh(tmp_path)) as w:
        with pytest.raises(ValueError, match="no infrared image"):
            w.write_frame(0, 1.0, make_depth(rng))
        with pytest.raises(ValueError, match="uint8"):
            w.write_frame(0, 1.0, make_depth(rng), infrared=np.zeros((HEIGHT, WIDTH), np.uint16))
        assert w.n_frames == 0
    assert (tmp_path / "t" / "frames.csv").read_text() == "frame,stamp\n"


def test_missing_or_wrong_stream_png_is_named(tmp_path):
    rng = np.random.default_rng(4)
    out, _, _ = write_images_trial(tmp_path, rng, ImageStreams(InfraredStream(), color_stream(rng)))
    (out / "color" / "000012.png").unlink()
    with pytest.raises(TrialFormatError, match=r"color/000012.png \(frame 12\): missing.*color PNG"):
        open_trial(out)
    import cv2
    cv2.imwrite(str(out / "color" / "000012.png"), np.zeros((30, 40), np.uint8))   # grey, not RGB
    reader = open_trial(out)
    with pytest.raises(TrialFormatError, match=r"000012.png \(frame 12\): expected an 8-bit PNG with 3 channel"):
        reader.read_color(1)
    cv2.imwrite(str(out / "ir" / "000014.png"), np.zeros((HEIGHT + 1, WIDTH), np.uint8))
    with pytest.raises(TrialFormatError, match=r"ir/000014.png \(frame 14\): expected 32x24 pixels"):
        reader.read_infrared(2)


def test_interrupted_recording_drops_the_frame_whose_image_is_missing(tmp_path):
    rng = np.random.default_rng(5)
    out, _, _ = write_images_trial(tmp_path, rng, ImageStreams(InfraredStream()), close=False)
    assert (out / MARKER_FILE).exists()
    (out / "ir" / "000016.png").unlink()   # as if killed between the depth and the IR PNG
    reader = open_trial(out)
    assert reader.interrupted and list(reader.frame_ids) == [10, 12, 14]


@pytest.mark.parametrize("edit, key", [
    (lambda d: d["color"].pop("K"), "color.K"),
    (lambda d: d["color"].__setitem__("T_depth_color", np.diag([1.0, 1.0, 2.0, 1.0]).tolist()), "color.T_depth_color"),
    (lambda d: d["color"].__setitem__("distortion", [0.0, 0.1]), "color.distortion"),
    (lambda d: d["infrared"].__setitem__("emitter", "on"), "infrared.emitter"),
    (lambda d: d["infrared"].__setitem__("dir", "depth"), "infrared.dir"),
    (lambda d: d["color"].__setitem__("dir", "ir"), "color.dir"),
    (lambda d: d.__setitem__("format", "osteonav-trial/1.2"), "format"),
])
def test_bad_stream_blocks_name_their_key(tmp_path, edit, key):
    rng = np.random.default_rng(6)
    out, _, _ = write_images_trial(tmp_path, rng, ImageStreams(InfraredStream(), color_stream(rng)), n=1)
    data = yaml.safe_load((out / "trial.yaml").read_text())
    edit(data)
    (out / "trial.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(TrialFormatError, match=f"key '{key}'"):
        load_meta(out / "trial.yaml")


def test_version_1_trial_written_before_1_1_reads_unchanged(tmp_path):
    reader = open_trial(V1_TRIAL)
    assert not reader.meta.streams and len(reader) == 14
    f = next(reader.iter_frames())
    assert f.infrared is None and f.color is None and (f.depth_m > 0).mean() > 0.3
    # written back through today's writer it is still version 1, trial.yaml identical
    copy = tmp_path / "copy"
    shutil.copytree(V1_TRIAL, copy)
    with TrialWriter(copy, reader.meta, overwrite=True) as w:
        w.write_joints(reader.joint_stamps, reader.joints)
        for fr in reader.iter_frames():
            w.write_frame(fr.frame_id, fr.stamp, fr.depth_m)
    assert yaml.safe_load((copy / "trial.yaml").read_text())["format"] == FORMAT
    assert (copy / "trial.yaml").read_text() == (V1_TRIAL / "trial.yaml").read_text()
    again = open_trial(copy)
    for a, b in zip(again.iter_frames(), reader.iter_frames()):
        np.testing.assert_array_equal(a.depth_m, b.depth_m)


def test_version_1_trial_replays(tmp_path):
    from app.cli import main

    out = tmp_path / "replayed"
    assert main(["replay", str(V1_TRIAL), "--out", str(out), "--no-rrd"]) == 0
    assert (out / "status.csv").read_text().count("\n") == 14 + 1


def test_recorder_skips_and_counts_frames_missing_a_declared_image(tmp_path):
    """Format 1.1: every listed frame has one PNG per stream, so a frame whose IR image the camera dropped
    is not written (counted as incomplete) and the recording goes on."""
    from app.interfaces import DepthFrame, JointSamples
    from plugins.recorder import Recorder

    rng = np.random.default_rng(8)
    meta = make_meta(rng)
    rec = Recorder(str(tmp_path / "rec"))
    rec.open({"mesh_path": bone_mesh(tmp_path), "camera": meta.camera, "robot": {"model": "ur5e"}, "dh": meta.dh,
              "T_flange_camera": np.eye(4), "image_streams": ImageStreams(InfraredStream(emitter=True))})
    rec.on_joints(JointSamples(np.arange(0.0, 2.0, 0.01), np.zeros((200, 6))))
    ir = rng.integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    for k in range(4):
        rec.on_frame(DepthFrame(k, 0.5 + 0.1 * k, make_depth(rng), 0.0, infrared=None if k == 2 else ir))
    summary = rec.close()
    assert summary["frames"] == 3 and summary["incomplete"] == 1 and summary["error"] is None
    reader = open_trial(tmp_path / "rec")
    assert list(reader.frame_ids) == [0, 1, 3] and reader.meta.streams.infrared.emitter
    np.testing.assert_array_equal(reader.read_infrared(2), ir)
