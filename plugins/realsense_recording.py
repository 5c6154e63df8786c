"""Writing RealSense recordings (``.bag`` / ``.db3``) with the SDK's own software device and recorder.

The tests use it to make recordings the RealSense plugin plays exactly as it plays a camera's; it
is also a way to turn a trial into a file the RealSense Viewer opens. Streams as on a D415:
depth (z16) and the left infrared imager (y8, index 1) on the "Stereo Module" sensor, colour
(rgb8) with the extrinsics depth -> colour registered
(``T_color_depth``, the inverse of a trial's ``T_depth_color``) and the emitter state stored as the
depth sensor's read-only ``emitter_enabled`` option. Frames of one instant share a timestamp and
frame number; the software device's matcher (depth + infrared + colour) groups them for playback.

The colour stream is written on the "Stereo Module" sensor too, not on a separate "RGB Camera"
sensor as a D415 has it (``separate_color_sensor=True`` does that): with pyrealsense2 2.59, a
recording whose streams come from two sensors sometimes plays back nothing, or only its last
frameset, through a pipeline (measured: 1 run in 4 gave no frame; 8 of 8 runs with one sensor
delivered every frame). A camera's own two-sensor recordings may therefore play unreliably.

Every frame is stored, however slow the disk. The SDK's recorder hands each frame to one writer
thread through an unbounded queue (``record_device``'s dispatcher) and drops nothing while frames
come; but when the recorder is destroyed it waits at most 10 s for that queue to drain
(``dispatcher::flush``) and then discards what is left ("timeout waiting for flush"): pushing a
60 s trial as fast as Python can kept 2,257-2,652 of its 5,347 frames, the first ones. So the frames
are pushed :data:`IN_FLIGHT` instants at a time, and after each batch the writer is waited for:
``recorder.pause()`` queues a marker behind the frames and returns once the writer has reached it
(the same flush, so within 10 s; a return that took the whole 10 s may be a timeout and is
repeated). The writer never holds more than one batch, and its queue is empty before the recorder
goes. The file is written under a temporary name beside ``path`` and renamed to ``path`` only once
it holds every depth frame (counted by playing it back); otherwise it is removed and OSError raised.
"""
from __future__ import annotations

import os
import secrets
import time
from pathlib import Path

import numpy as np

from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.image_streams import ColorStream

_POLL_MS = 50   # count_depth_frames' poll for the next frame
IN_FLIGHT = 32  # instants (depth + infrared + colour frames) pushed before waiting for the recorder's writer
_SDK_FLUSH_S = 10.0   # the recorder's flush gives up after this (librealsense dispatcher::flush)
WRITER_LIMIT_S = 120.0   # a writer that has not written one batch in this long: OSError (a hung disk)
_monotonic = time.monotonic


def _intrinsics(rs, camera: PinholeCamera, distortion=None):
    intr = rs.intrinsics()
    intr.width, intr.height = camera.width, camera.height
    intr.fx, intr.fy = float(camera.K[0, 0]), float(camera.K[1, 1])
    intr.ppx, intr.ppy = float(camera.K[0, 2]), float(camera.K[1, 2])
    intr.model = rs.distortion.brown_conrady   # OpenCV's k1, k2, p1, p2, k3
    intr.coeffs = [float(c) for c in (np.zeros(5) if distortion is None else distortion)]
    return intr


def _video_stream(rs, kind, index: int, uid: int, camera: PinholeCamera, fmt, bpp: int, fps: int, distortion=None):
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = kind, index, uid
    stream.width, stream.height, stream.fps, stream.bpp = camera.width, camera.height, int(fps), bpp
    stream.fmt = fmt
    stream.intrinsics = _intrinsics(rs, camera, distortion)
    return stream


def _extrinsics(rs, T_to_from: np.ndarray):
    """rs.extrinsics of a pose T_to_from (rotation stored column-major, as librealsense does)."""
    ext = rs.extrinsics()
    ext.rotation = [float(x) for x in np.asarray(T_to_from)[:3, :3].T.ravel()]
    ext.translation = [float(x) for x in np.asarray(T_to_from)[:3, 3]]
    return ext


def write_recording(path: str | Path, depth_units: np.ndarray, stamps_s: np.ndarray, camera: PinholeCamera,
                    depth_scale: float, fps: int = 30, frame_numbers: np.ndarray | None = None,
                    infrared: np.ndarray | None = None, color: np.ndarray | None = None,
                    color_stream: ColorStream | None = None, emitter: bool | None = None,
                    separate_color_sensor: bool = False, overwrite: bool = False) -> Path:
    """Write z16 depth frames (and optionally y8 infrared and rgb8 colour frames) to a RealSense recording.

    Parameters
    ----------
    path : output file; its suffix must be one the installed SDK records (``.bag`` up to
        librealsense 2.56, ``.db3`` from 2.58): use :func:`plugins.realsense.recording_suffix`
    depth_units : (N, H, W) uint16 depth in units of ``depth_scale`` metres
    stamps_s : (N,) frame timestamps, s (stored as hardware-clock milliseconds)
    camera : the depth (and infrared) intrinsics to store
    infrared : (N, H, W) uint8 left-imager frames, or None
    color, color_stream : (N, Hc, Wc, 3) uint8 RGB frames and their camera (K, distortion, T_depth_color)
    emitter : stored as the depth sensor's ``emitter_enabled`` option (None: not stored)
    overwrite : replace a file already at ``path`` (once the new recording is complete); without it an
        existing file is refused (FileExistsError) and left as it is
    """
    from plugins.realsense import _rs

    rs = _rs()
    depth_units = np.ascontiguousarray(depth_units, dtype=np.uint16)
    n, height, width = depth_units.shape
    if (width, height) != (camera.width, camera.height):
        raise ValueError(f"frames are {width}x{height}, the camera is {camera.width}x{camera.height}")
    if (color is None) != (color_stream is None):
        raise ValueError("give both color frames and color_stream, or neither")
    device = rs.software_device()
    streams = [("depth", depth_units, 2)]
    if infrared is not None or color is not None:
        device.create_matcher(rs.matchers.di_c if infrared is not None and color is not None else
                              rs.matchers.di if infrared is not None else rs.matchers.default)
    stereo = device.add_sensor("Stereo Module" if infrared is not None or color is not None else "Depth")
    profiles = {"depth": stereo.add_video_stream(_video_stream(rs, rs.stream.depth, 0, 0, camera, rs.format.z16, 2, fps))}
    stereo.add_read_only_option(rs.option.depth_units, float(depth_scale))
    if emitter is not None:
        stereo.add_read_only_option(rs.option.emitter_enabled, 1.0 if emitter else 0.0)
    if infrared is not None:
        profiles["ir"] = stereo.add_video_stream(_video_stream(rs, rs.stream.infrared, 1, 1, camera, rs.format.y8, 1, fps))
        streams.append(("ir", np.ascontiguousarray(infrared, dtype=np.uint8), 1))
    rgb_sensor = None
    if color is not None:
        rgb_sensor = device.add_sensor("RGB Camera") if separate_color_sensor else stereo
        profiles["color"] = rgb_sensor.add_video_stream(_video_stream(rs, rs.stream.color, 0, 2, color_stream.camera,
                                                                      rs.format.rgb8, 3, fps, color_stream.distortion))
        profiles["depth"].register_extrinsics_to(profiles["color"], _extrinsics(rs, se3.inverse(color_stream.T_depth_color)))
        streams.append(("color", np.ascontiguousarray(color, dtype=np.uint8), 3))
    numbers = np.arange(n) if frame_numbers is None else np.asarray(frame_numbers)
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists: choose another path, or pass overwrite=True to replace it "
                              "once the new recording is complete")
    partial = _partial_path(path)
    try:
        _record(rs, partial, device, stereo, rgb_sensor, profiles, streams, stamps_s, numbers)
        stored = count_depth_frames(partial)
        if stored != n:
            raise OSError(f"the RealSense recording {path} holds {stored} of the {n} depth frames written (the SDK's "
                          "recorder lost the rest); not kept")
        os.replace(partial, path)
    except BaseException:
        _remove_partial(partial)
        raise
    return path


def _partial_path(path: Path) -> Path:
    """A name beside ``path`` (same directory and suffix, which the SDK reads the format from) that no file has."""
    while True:
        partial = path.with_name(f".{path.stem}.partial-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}")
        if not partial.exists():
            return partial


def _remove_partial(partial: Path) -> None:
    for name in (partial, *(partial.with_name(partial.name + s) for s in ("-journal", "-wal", "-shm"))):
        name.unlink(missing_ok=True)


def _record(rs, path: Path, device, stereo, rgb_sensor, profiles: dict, streams: list, stamps_s, numbers) -> None:
    """Push every instant's frames to the software device under an rs.recorder writing ``path``, at most
    :data:`IN_FLIGHT` instants ahead of the recorder's writer; returns once the recorder is gone (the file
    finalised)."""
    recorder = rs.recorder(str(path), device)
    try:
        stereo.open([profiles[k] for k in ("depth", "ir", "color") if k in profiles and (k != "color" or rgb_sensor is stereo)])
        queue = rs.frame_queue(16)
        stereo.start(queue)
        if rgb_sensor is not None and rgb_sensor is not stereo:
            rgb_sensor.open(profiles["color"])
            rgb_sensor.start(queue)
        n = len(streams[0][1])
        for k in range(n):
            for name, frames, bpp in streams:
                frame = rs.software_video_frame()
                frame.pixels = frames[k]
                frame.bpp, frame.stride = bpp, bpp * frames.shape[2]
                frame.timestamp = float(stamps_s[k] * 1e3)
                frame.domain = rs.timestamp_domain.hardware_clock
                frame.frame_number = int(numbers[k])
                frame.profile = profiles[name].as_video_stream_profile()
                (rgb_sensor if name == "color" else stereo).on_video_frame(frame)
            while queue.poll_for_frame():
                pass
            if ((k + 1) % IN_FLIGHT == 0 or k + 1 == n) and wait_for_writer(recorder) is None:
                raise OSError(f"the RealSense recorder's writer has not written its queued frames in {WRITER_LIMIT_S:.0f} s "
                              "(a hung or very slow disk?)")
        for sensor in (stereo, rgb_sensor if rgb_sensor is not stereo else None):
            if sensor is not None:
                sensor.stop()
                sensor.close()
    finally:
        del recorder  # the file is finalised when the recorder goes away (its queue is empty: nothing dropped)


def wait_for_writer(recorder, limit_s: float | None = None) -> float | None:
    """Wait until the recorder's writer thread has written every frame handed to it so far: the seconds
    waited, or None when it had not after ``limit_s`` (:data:`WRITER_LIMIT_S`).

    ``recorder.pause()`` queues a marker behind the frames and waits for the writer to reach it, but at most
    10 s (the SDK's flush): a pause that returned sooner has seen every frame written; one that took the
    whole 10 s may have timed out and is repeated. ``resume()`` is queued behind the marker, so the frames
    pushed after it are recorded.
    """
    limit_s = WRITER_LIMIT_S if limit_s is None else limit_s
    start = _monotonic()
    while True:
        t = _monotonic()
        recorder.pause()
        done = _monotonic()
        if done - t < _SDK_FLUSH_S or done - start >= limit_s:
            break
    recorder.resume()
    return done - start if done - t < _SDK_FLUSH_S else None


def count_depth_frames(path: str | Path, timeout_ms: int = 5000) -> int:
    """The depth frames a RealSense recording holds, read in order (the SDK's non-real-time playback) to
    the file's end: the playback has stopped and no frame is left. In non-real-time playback the SDK
    hands each frame on before it reads the next, so once it reports ``stopped`` every frame is queued;
    the count ends at the first empty poll after that, not after a wait (it waited ``timeout_ms`` for a
    frame that never came: 5 s of every recording written). ``timeout_ms`` without a frame while it
    still plays ends the count too (a stalled reader)."""
    from plugins.realsense import _rs

    rs = _rs()
    pipeline, config = rs.pipeline(), rs.config()
    config.enable_device_from_file(str(Path(path)), False)
    config.enable_stream(rs.stream.depth)
    config.resolve(pipeline).get_device().as_playback().set_real_time(False)
    playback = pipeline.start(config).get_device().as_playback()
    count, quiet_ms = 0, 0
    try:
        while quiet_ms < timeout_ms:
            ended = playback.current_status() == rs.playback_status.stopped    # before the poll: all queued
            ok, frames = pipeline.try_wait_for_frames(_POLL_MS)
            if ok:
                count += bool(frames.get_depth_frame())
                quiet_ms = 0
            elif ended:
                break
            else:
                quiet_ms += _POLL_MS
        return count
    finally:
        pipeline.stop()
