"""Intel RealSense depth camera (``camera: realsense``), live or from a recording, via pyrealsense2.

Live: the depth stream at ``width`` x ``height`` and ``fps`` (z16); ``depth_units`` (m per unit,
e.g. 0.0001 for 0.1 mm steps) is set on the depth sensor when given, else the device's is read;
the intrinsics come from the stream profile (``rs.intrinsics``: fx, fy, ppx, ppy; D4xx depth is
rectified, so a non-zero distortion is reported and ignored). Each frame's timestamp (ms, domain
``hardware_clock`` or ``global_time``) is mapped to the host clock by :class:`plugins._clock.ClockMapper`
(a clock jump is re-anchored and logged). A stream that stops (``wait_for_frames`` times out) is
a stall: logged, then after ``restart_after_s`` the pipeline is stopped and started again, and
again every ``restart_after_s`` until frames come back.

Images (``streams: depth,ir,color``): the left infrared imager (y8, index 1: the depth frame itself,
same K) and the colour camera (rgb8, its own K, distortion and ``T_depth_color`` from the SDK's
extrinsics) come with each depth frame (``DepthFrame.infrared`` / ``color``), paired by timestamp
(:mod:`plugins._rs_images`), and are declared in ``session_defaults()['image_streams']`` for the
recorder (trial format 1.1). ``emitter: false`` switches the IR dot projector off on a live
device (a cleaner calibration board).

Recording (``recording: FILE``): a ``.bag`` (ROS1, written by librealsense up to 2.56 and by the
RealSense Viewer of that era) or ``.db3`` (ROS2, written by librealsense 2.58 and later) file,
played in real time: frames are read in order (the SDK's non-real-time playback, which drops none
by itself) and pushed when the host clock reaches their recorded timestamp mapped through the
session's replay anchor, so a recorded robot trial taken on the same clock lines up. Like a live
camera it never delivers a stale frame and never queues: a frame read after its successor was
already due (a busy host: the tracker's CPU, the GIL, the sinks of the frame before) is skipped,
neither converted nor pushed (``skipped``, in the session summary), while the reader reads faster
than the frame rate, so it catches up by reading on and the latency stays flat however long the
recording. (Seeking the playback instead hangs the SDK's pipeline for 10 s now and then, 2.59.)

:func:`write_recording` writes depth images to such a file with the SDK's own software device and
recorder (the tests use it; also a way to turn a trial into a file the RealSense Viewer opens).
"""
from __future__ import annotations

import collections
import logging
import time
from pathlib import Path

import numpy as np

from app.errors import ConfigError
from app.geometry.camera import PinholeCamera
from app.interfaces import DepthFrame, SessionClock
from plugins._base import ThreadedSource
from plugins._clock import ClockMapper

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install pyrealsense2  (or: pip install 'osteonav[hardware]')"
RECORDING_SUFFIXES = (".bag", ".db3")


def _rs():
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise ConfigError("camera.plugin", f"the 'realsense' camera plugin needs pyrealsense2, which is not "
                                           f"installed ({exc}): {INSTALL_HINT}") from exc
    return rs


def camera_from_intrinsics(intr) -> PinholeCamera:
    """PinholeCamera of an ``rs.intrinsics`` (pixel centres at integers, as OpenCV and RealSense)."""
    K = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])
    if any(abs(c) > 1e-9 for c in intr.coeffs):
        log.warning("RealSense depth intrinsics carry distortion %s; the depth stream is treated as rectified",
                    list(intr.coeffs))
    return PinholeCamera(K, int(intr.width), int(intr.height))


class RealSenseCamera(ThreadedSource):
    """A RealSense depth camera or a RealSense recording as a depth source.

    Parameters
    ----------
    recording : path of a ``.bag``/``.db3`` file to play instead of a device
    serial : the device's serial number (None = the only one connected)
    width, height, fps : live depth stream mode
    depth_units : metres per depth unit to set on a live device (None = leave as is)
    timeout_s : a ``wait_for_frames`` longer than this is a stall
    restart_after_s : restart a stalled pipeline after this long (and again as often)
    streams : 'depth' or e.g. 'depth,ir,color': also the left infrared imager (y8, the depth frame's own
        K) and the colour camera (rgb8, its own K, distortion and T_depth_color), delivered with each
        depth frame (:class:`plugins._rs_images.FramePairer`) and declared in ``session_defaults()``
    emitter : switch the IR dot projector on (true) or off (false; cleaner board images) on a live
        device; None leaves it as it is (a recording says what it was, when it stored the option)
    color_width, color_height : live colour stream mode
    """

    kind, name = "camera", "realsense"

    def __init__(self, recording: str | None = None, serial: str | None = None, width: int = 848, height: int = 480,
                 fps: int = 30, depth_units: float | None = None, timeout_s: float = 0.5,
                 restart_after_s: float = 2.0, streams: str = "depth", emitter: bool | None = None,
                 color_width: int = 640, color_height: int = 480):
        from plugins._rs_images import parse_stream_names

        super().__init__()
        if recording is not None and Path(recording).suffix.lower() not in RECORDING_SUFFIXES:
            raise ConfigError("camera.params.recording", f"expected a RealSense recording ({', '.join(RECORDING_SUFFIXES)}), "
                                                         f"got {recording!r}")
        if fps not in (6, 15, 30, 60, 90):
            raise ConfigError("camera.params.fps", f"RealSense depth rates are 6, 15, 30, 60, 90 fps; got {fps}")
        if depth_units is not None and not (1e-6 <= depth_units <= 0.01):
            raise ConfigError("camera.params.depth_units", f"expected metres per unit in [1e-6, 0.01], got {depth_units}")
        self.recording = Path(recording) if recording else None
        self.serial, self.width, self.height, self.fps = serial, int(width), int(height), int(fps)
        self.depth_units = depth_units
        self.stream_names = parse_stream_names(streams)
        if emitter is not None and not isinstance(emitter, bool):
            raise ConfigError("camera.params.emitter", f"expected true or false, got {emitter!r}")
        self.emitter = emitter
        self.color_size = (int(color_width), int(color_height))
        self.image_streams = None
        self._pairer = None
        self.timeout_s, self.restart_after_s = float(timeout_s), float(restart_after_s)
        self.clock_mapper = ClockMapper(jump_threshold_s=0.5)
        self.depth_scale = None
        self.camera: PinholeCamera | None = None
        self._pipeline = None
        self._replay_origin = None
        self._period_s = None       # the recording's frame period: the smallest stamp step read so far
        self._last_read_t = None    # recorded stamp of the last frame read
        self._last_done = None      # session time the last recorded frame was pushed or skipped
        self._read_s = collections.deque(maxlen=8)   # the last reads' durations (session clock)
        self.skipped = 0            # recorded frames read when already stale, never pushed

    # -- setup -----------------------------------------------------------------------------------
    def open(self, clock: SessionClock, event) -> PinholeCamera:
        self._bind(clock, event)
        rs = _rs()
        if self.recording is not None and not self.recording.is_file():
            raise ConfigError("camera.params.recording", f"file not found: {self.recording}")
        self._start_pipeline(rs)
        return self.camera

    def _config(self, rs):
        config = rs.config()
        if self.recording is not None:
            config.enable_device_from_file(str(self.recording), False)
            config.enable_stream(rs.stream.depth)
            if "ir" in self.stream_names:
                config.enable_stream(rs.stream.infrared, 1)
            if "color" in self.stream_names:
                config.enable_stream(rs.stream.color)
        else:
            if self.serial:
                config.enable_device(str(self.serial))
            config.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
            if "ir" in self.stream_names:
                config.enable_stream(rs.stream.infrared, 1, self.width, self.height, rs.format.y8, self.fps)
            if "color" in self.stream_names:
                config.enable_stream(rs.stream.color, *self.color_size, rs.format.rgb8, self.fps)
        return config

    def _start_pipeline(self, rs) -> None:
        pipeline = rs.pipeline()
        config = self._config(rs)
        try:
            if self.recording is not None:
                # not the SDK's real-time mode: it replays the file's write times and drops frames a
                # slow reader misses; read every frame and pace by the frames' own stamps instead.
                # Set before start on the device the config resolves to (start reuses it): set
                # after start, playback has already run in real time and dropped frames meanwhile
                config.resolve(pipeline).get_device().as_playback().set_real_time(False)
            profile = pipeline.start(config)
        except RuntimeError as exc:
            what = f"recording {self.recording}" if self.recording else f"device {self.serial or '(any)'}"
            raise ConfigError("camera", f"cannot start the RealSense {what}: {exc}") from exc
        device = profile.get_device()
        if self.recording is not None and device.as_playback().is_real_time():
            pipeline.stop()
            raise ConfigError("camera", f"the RealSense SDK plays {self.recording} in real time (frames would be "
                              "dropped); this pyrealsense2 version is not supported for recordings")
        sensor = device.first_depth_sensor()
        if self.depth_units is not None and self.recording is None:
            sensor.set_option(rs.option.depth_units, float(self.depth_units))
        if self.emitter is not None and self.recording is None and sensor.supports(rs.option.emitter_enabled):
            sensor.set_option(rs.option.emitter_enabled, 1.0 if self.emitter else 0.0)
        self._describe_images(rs, profile)
        self.depth_scale = float(sensor.get_depth_scale())
        stream = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        self.camera = camera_from_intrinsics(stream.get_intrinsics())
        self._pipeline = pipeline
        log.info("RealSense %s: %dx%d, depth unit %.6g m", self.recording or "device", self.camera.width,
                 self.camera.height, self.depth_scale)

    def _describe_images(self, rs, profile) -> None:
        from plugins._rs_images import FramePairer, describe_streams

        if self.stream_names == ("depth",):
            return
        try:
            self.image_streams = describe_streams(rs, profile, self.stream_names, self.emitter)
        except RuntimeError as exc:
            raise ConfigError("camera.params.streams", f"the RealSense {self.recording or 'device'} does not deliver "
                              f"{', '.join(self.stream_names)}: {exc}") from exc
        self._pairer = FramePairer(self.image_streams, self.fps if self.recording is None else
                                   profile.get_stream(rs.stream.depth).fps())

    def _stop_pipeline(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
            self._pipeline = None

    def stop(self, timeout: float = 5.0) -> None:
        super().stop(timeout)
        if self._thread is None:   # opened but never started (a session that failed before starting)
            self._stop_pipeline()

    # -- streaming -------------------------------------------------------------------------------
    def _run(self) -> None:
        rs = _rs()
        last_frame = self.clock.now()
        stalled = False
        last_restart = last_frame
        try:
            while not self._stop.is_set():
                ok, frames = (False, None)
                if self._pipeline is not None:
                    try:
                        ok, frames = self._pipeline.try_wait_for_frames(int(self.timeout_s * 1000))
                    except RuntimeError as exc:
                        self._event("error", f"RealSense read failed: {exc}")
                now = self.clock.now()
                if ok:
                    depth = frames.get_depth_frame()
                    if depth:
                        self._on_frameset(frames, depth, now)
                        if stalled:
                            self._event("recovered", f"frames again after {now - last_frame:.2f} s")
                        stalled, last_frame = False, now
                    continue
                if self.recording is not None:
                    for item in self._pairer.flush() if self._pairer is not None else []:
                        self._on_frame(*item, arrival=self.clock.now())
                    self._event("end", f"end of the recording {self.recording}")
                    break
                if not stalled:
                    self._event("stall", f"no depth frame for {now - last_frame:.2f} s")
                    stalled = True
                if now - last_restart >= self.restart_after_s:
                    last_restart = now
                    self._event("restart", "restarting the RealSense pipeline")
                    self._stop_pipeline()
                    try:
                        self._start_pipeline(rs)
                        self.clock_mapper.reset()
                    except ConfigError as exc:
                        self._event("error", str(exc))
                        self._stop.wait(0.2)
        finally:
            self._stop_pipeline()
            self.finished.set()

    def _on_frameset(self, frames, depth, arrival: float) -> None:
        """Hand the depth frame on at once, or through the pairer when images are enabled."""
        if self._pairer is None:
            self._on_frame((depth.get_timestamp(), depth.get_frame_number(), depth), None, None, arrival)
            return

        def entry(frame):
            return (frame.get_timestamp(), frame.get_frame_number(), np.asanyarray(frame.get_data()).copy()) if frame else None

        ir = frames.get_infrared_frame(1) if "ir" in self.stream_names else None
        color = frames.get_color_frame() if "color" in self.stream_names else None
        depth_entry = (depth.get_timestamp(), depth.get_frame_number(), np.asanyarray(depth.get_data()).copy())
        for item in self._pairer.add(depth_entry, entry(ir), entry(color)):
            self._on_frame(*item, arrival=arrival)

    def _on_frame(self, depth, infrared, color, arrival: float) -> None:
        """depth : (timestamp ms, frame number, rs.depth_frame or its (H, W) uint16 array)."""
        device_t = depth[0] * 1e-3
        if self.recording is not None:
            due = self._when_due(device_t)
            if due is None:
                return
            stamp, arrival = due
        else:
            stamp, jump = self.clock_mapper.map(device_t, arrival)
            if jump is not None:
                self._event("clock_jump", f"camera clock jumped by {jump:+.3f} s; mapping re-anchored")
        data = depth[2] if isinstance(depth[2], np.ndarray) else np.asanyarray(depth[2].get_data())
        depth_m = data.astype(np.float32) * np.float32(self.depth_scale)
        self._push(DepthFrame(int(depth[1]), stamp, depth_m, arrival, infrared=infrared, color=color))
        self._last_done = self.clock.now()

    def _when_due(self, device_t: float) -> tuple[float, float] | None:
        """(host stamp, arrival) of the recorded frame stamped ``device_t`` (s), pushed once its stamp is
        due; None when stopped meanwhile or when the frame is stale and skipped.

        Stale: the next frame (a period later) is due already. It is skipped while the reader's recent
        reads were faster than the frame rate (it catches up by reading on: each stale frame costs a
        read, no conversion, no push). A reader slower than the frame rate pushes it anyway (the
        newest frame it has; skipping every frame would push none).
        """
        if self._last_done is not None:                # this frame's read
            self._read_s.append(self.clock.now() - self._last_done)
        read_s = min(self._read_s) if self._read_s else None   # what the next read may cost: the quickest of late
        if self._replay_origin is None:
            self._replay_origin = device_t
        self._learn_period(device_t)
        stamp = float(self.clock.replay_to_host(device_t, self._replay_origin))
        if not self._sleep_until(stamp):
            return None
        now = self.clock.now()
        if self._stale(device_t, now) and read_s is not None and read_s < self._period_s:
            self.skipped += 1
            self._last_done = now
            return None
        return stamp, now

    def _learn_period(self, device_t: float) -> None:
        """The recording's frame period: the smallest step between the stamps read (the stream profile's
        fps is what the recorder was told, not always the frames' rate; a dropped frame makes a larger step)."""
        last, self._last_read_t = self._last_read_t, device_t
        if last is not None and device_t > last:
            self._period_s = min(self._period_s or np.inf, device_t - last)

    def _stale(self, device_t: float, now: float) -> bool:
        """True when the recorded frame after this one (one period later) is already due on the session clock."""
        if self._period_s is None:
            return False
        return float(self.clock.replay_to_host(device_t + self._period_s, self._replay_origin)) <= now

    def session_defaults(self) -> dict:
        out = {"camera": self.camera} if self.camera is not None else {}
        if self.image_streams is not None:
            out["image_streams"] = self.image_streams
        return out


def write_recording(path: str | Path, depth_units: np.ndarray, stamps_s: np.ndarray, camera: PinholeCamera,
                    depth_scale: float, fps: int = 30, frame_numbers: np.ndarray | None = None, **images) -> Path:
    """Write depth (and infrared / colour) frames with the SDK's software device: see
    :func:`plugins.realsense_recording.write_recording` (``images``: infrared, color, color_stream, emitter)."""
    from plugins.realsense_recording import write_recording as write

    return write(path, depth_units, stamps_s, camera, depth_scale, fps, frame_numbers, **images)


def recording_suffix() -> str:
    """``.bag`` if the installed librealsense still records ROS1 bags (<= 2.56), else ``.db3``."""
    from importlib.metadata import version as dist_version

    _rs()
    version = tuple(int(v) for v in dist_version("pyrealsense2").split(".")[:2])
    return ".bag" if version < (2, 58) else ".db3"


def write_trial_recording(trial: str | Path, path_stem: str | Path) -> Path:
    """A trial's frames as a RealSense recording ``path_stem`` + :func:`recording_suffix`.

    Stamps, frame numbers, intrinsics and depth unit come from the trial, and its infrared and
    colour streams when it has them (format 1.1); joints are not stored (play them with
    ``robot: recorded`` from the same trial).
    """
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    scale_m = reader.meta.depth_scale * 1e-3
    frames, ids, ir, rgb = [], [], [], []
    for f in reader.iter_frames():
        frames.append(np.round(f.depth_m / scale_m).astype(np.uint16))
        ids.append(f.frame_id)
        ir.append(f.infrared)
        rgb.append(f.color)
    streams = reader.meta.streams
    images = {}
    if streams.infrared is not None:
        images.update(infrared=np.stack(ir), emitter=streams.infrared.emitter)
    if streams.color is not None:
        images.update(color=np.stack(rgb), color_stream=streams.color)
    return write_recording(Path(str(path_stem) + recording_suffix()), np.stack(frames), np.asarray(reader.stamps),
                           reader.meta.camera, scale_m, frame_numbers=np.asarray(ids), **images)
