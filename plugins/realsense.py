"""Intel RealSense depth camera (``camera: realsense``), live or from a recording, via pyrealsense2.

Live: the depth stream at ``width`` x ``height`` and ``fps`` (z16); ``depth_units`` (m per unit,
e.g. 0.0001 for 0.1 mm steps) is set on the depth sensor when given, else the device's is read;
the intrinsics come from the stream profile (``rs.intrinsics``: fx, fy, ppx, ppy; D4xx depth is
rectified, so a non-zero distortion is reported and ignored). Each frame's timestamp (ms, domain
``hardware_clock`` or ``global_time``) is mapped to the host clock by :class:`plugins._clock.ClockMapper`
(a clock jump is re-anchored and logged). A stream that stops (``wait_for_frames`` times out) is
a stall: logged, then after ``restart_after_s`` the pipeline is stopped and started again, and
again every ``restart_after_s`` until frames come back.

Recording (``recording: FILE``): a ``.bag`` (ROS1, written by librealsense up to 2.56 and by the
RealSense Viewer of that era) or ``.db3`` (ROS2, written by librealsense 2.58 and later) file,
played in real time: every frame is read (the SDK's non-real-time playback, which drops none) and
pushed when the host clock reaches its recorded timestamp mapped through the session's replay
anchor, so a recorded robot trial taken on the same clock lines up.

:func:`write_recording` writes depth images to such a file with the SDK's own software device and
recorder (the tests use it; also a way to turn a trial into a file the RealSense Viewer opens).
"""
from __future__ import annotations

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
    """

    kind, name = "camera", "realsense"

    def __init__(self, recording: str | None = None, serial: str | None = None, width: int = 848, height: int = 480,
                 fps: int = 30, depth_units: float | None = None, timeout_s: float = 0.5,
                 restart_after_s: float = 2.0):
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
        self.timeout_s, self.restart_after_s = float(timeout_s), float(restart_after_s)
        self.clock_mapper = ClockMapper(jump_threshold_s=0.5)
        self.depth_scale = None
        self.camera: PinholeCamera | None = None
        self._pipeline = None
        self._replay_origin = None

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
        else:
            if self.serial:
                config.enable_device(str(self.serial))
            config.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
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
        self.depth_scale = float(sensor.get_depth_scale())
        stream = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        self.camera = camera_from_intrinsics(stream.get_intrinsics())
        self._pipeline = pipeline
        log.info("RealSense %s: %dx%d, depth unit %.6g m", self.recording or "device", self.camera.width,
                 self.camera.height, self.depth_scale)

    def _stop_pipeline(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
            self._pipeline = None

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
                        self._on_frame(depth, now)
                        if stalled:
                            self._event("recovered", f"frames again after {now - last_frame:.2f} s")
                        stalled, last_frame = False, now
                    continue
                if self.recording is not None:
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

    def _on_frame(self, depth, arrival: float) -> None:
        device_t = depth.get_timestamp() * 1e-3
        if self.recording is not None:
            if self._replay_origin is None:
                self._replay_origin = device_t
            stamp = float(self.clock.replay_to_host(device_t, self._replay_origin))
            if not self._sleep_until(stamp):
                return
            arrival = self.clock.now()
        else:
            stamp, jump = self.clock_mapper.map(device_t, arrival)
            if jump is not None:
                self._event("clock_jump", f"camera clock jumped by {jump:+.3f} s; mapping re-anchored")
        data = np.asanyarray(depth.get_data())
        depth_m = data.astype(np.float32) * np.float32(self.depth_scale)
        self._push(DepthFrame(int(depth.get_frame_number()), stamp, depth_m, arrival))

    def session_defaults(self) -> dict:
        return {"camera": self.camera} if self.camera is not None else {}


def write_recording(path: str | Path, depth_units: np.ndarray, stamps_s: np.ndarray, camera: PinholeCamera,
                    depth_scale: float, fps: int = 30, frame_numbers: np.ndarray | None = None) -> Path:
    """Write z16 depth frames to a RealSense recording with the SDK's software device and recorder.

    Parameters
    ----------
    path : output file; its suffix must be one the installed SDK records (``.bag`` up to
        librealsense 2.56, ``.db3`` from 2.58): use :func:`recording_suffix`
    depth_units : (N, H, W) uint16 depth in units of ``depth_scale`` metres
    stamps_s : (N,) frame timestamps, s (stored as hardware-clock milliseconds)
    camera : the intrinsics to store
    """
    rs = _rs()
    depth_units = np.ascontiguousarray(depth_units, dtype=np.uint16)
    n, height, width = depth_units.shape
    if (width, height) != (camera.width, camera.height):
        raise ValueError(f"frames are {width}x{height}, the camera is {camera.width}x{camera.height}")
    device = rs.software_device()
    sensor = device.add_sensor("Depth")
    intr = rs.intrinsics()
    intr.width, intr.height = width, height
    intr.fx, intr.fy = float(camera.K[0, 0]), float(camera.K[1, 1])
    intr.ppx, intr.ppy = float(camera.K[0, 2]), float(camera.K[1, 2])
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0] * 5
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = rs.stream.depth, 0, 0
    stream.width, stream.height, stream.fps, stream.bpp = width, height, int(fps), 2
    stream.fmt = rs.format.z16
    stream.intrinsics = intr
    profile = sensor.add_video_stream(stream)
    sensor.add_read_only_option(rs.option.depth_units, float(depth_scale))
    path = Path(path)
    recorder = rs.recorder(str(path), device)
    sensor.open(profile)
    queue = rs.frame_queue(4)
    sensor.start(queue)
    numbers = np.arange(n) if frame_numbers is None else np.asarray(frame_numbers)
    for k in range(n):
        frame = rs.software_video_frame()
        frame.pixels = depth_units[k]
        frame.bpp, frame.stride = 2, 2 * width
        frame.timestamp = float(stamps_s[k] * 1e3)
        frame.domain = rs.timestamp_domain.hardware_clock
        frame.frame_number = int(numbers[k])
        frame.profile = profile.as_video_stream_profile()
        sensor.on_video_frame(frame)
        queue.poll_for_frame()
    time.sleep(0.05)
    sensor.stop()
    sensor.close()
    del recorder  # the file is finalised when the recorder goes away
    return path


def recording_suffix() -> str:
    """``.bag`` if the installed librealsense still records ROS1 bags (<= 2.56), else ``.db3``."""
    from importlib.metadata import version as dist_version

    _rs()
    version = tuple(int(v) for v in dist_version("pyrealsense2").split(".")[:2])
    return ".bag" if version < (2, 58) else ".db3"


def write_trial_recording(trial: str | Path, path_stem: str | Path) -> Path:
    """A trial's depth frames as a RealSense recording ``path_stem`` + :func:`recording_suffix`.

    Stamps, frame numbers, intrinsics and depth unit come from the trial; joints are not stored
    (play them with ``robot: recorded`` from the same trial).
    """
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    scale_m = reader.meta.depth_scale * 1e-3
    frames, ids = [], []
    for f in reader.iter_frames():
        frames.append(np.round(f.depth_m / scale_m).astype(np.uint16))
        ids.append(f.frame_id)
    return write_recording(Path(str(path_stem) + recording_suffix()), np.stack(frames), np.asarray(reader.stamps),
                           reader.meta.camera, scale_m, frame_numbers=np.asarray(ids))
