"""Running a live hand-eye capture on a session's camera and robot plugins (``osteonav calibrate capture``).

The session file names the plugins as for ``osteonav track`` (its tracker and outputs are not
used): e.g. ``camera: {plugin: realsense, params: {streams: depth,ir, emitter: false}}`` and
``robot: {plugin: ur, params: {host: ...}, model: ur5e}``. Frames and joint samples are pushed by
the plugins' own threads; this loop pops the newest frame (older ones are dropped, as the live loop
does), waits briefly for the joint samples to reach its stamp, and hands its image to
:class:`calibration.live.LiveCapturer`. The capture folder gets ``camera.yaml`` with the
intrinsics of the image stream used (infrared: the depth camera's K, no distortion; colour: its
own K and distortion), so ``calibrate hand-eye --captures DIR`` needs nothing else.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path

import numpy as np

from app.errors import ConfigError

log = logging.getLogger(__name__)

JOINT_WAIT_S = 0.2   # how long a frame waits for the joint samples to reach its stamp


class CaptureRerun:
    """The live detection in rerun: the image and the corners found, on the ``stamp`` timeline."""

    def __init__(self, path: str | Path | None):
        import rerun as rr

        self.rr = rr
        from app.viz.rrd_file import RrdFile

        self.rec = rr.RecordingStream("osteonav-capture")
        self.file = RrdFile(self.rec, path) if path else None
        if not path:
            self.rec.spawn()

    def log_detection(self, stamp: float, image: np.ndarray, detection) -> None:
        rr = self.rr
        self.rec.set_time("stamp", duration=float(stamp))
        self.rec.log("camera/image", rr.Image(image).compress(jpeg_quality=80))
        if detection is None:
            self.rec.log("camera/image/corners", rr.Clear(recursive=False))
        else:
            self.rec.log("camera/image/corners", rr.Points2D(detection.corners_px, radii=2.0, colors=(60, 220, 60)))

    def log_status(self, text: str) -> None:
        self.rec.log("capture/status", self.rr.TextLog(text))

    def close(self) -> None:
        """Flush; with a file, raises OutputError when writing it failed (a full disk)."""
        if self.file is not None:
            self.file.close()
        else:
            self.rec.flush()


def _image_of(frame, which: str) -> np.ndarray | None:
    import cv2

    if which == "ir":
        return frame.infrared
    return None if frame.color is None else cv2.cvtColor(frame.color, cv2.COLOR_RGB2GRAY)


def _intrinsics(which: str, camera_model, streams):
    from calibration.intrinsics import CameraIntrinsics

    if which == "ir":
        return CameraIntrinsics(np.asarray(camera_model.K), np.zeros(5), camera_model.width, camera_model.height)
    c = streams.color
    return CameraIntrinsics(np.asarray(c.camera.K), np.asarray(c.distortion), c.camera.width, c.camera.height)


def _open_sources(config, clock):
    from app import plugins_registry as registry

    camera = registry.create("camera", config.camera.name, config.camera.params, "camera")
    robot = registry.create("robot", config.robot.name, config.robot.params, "robot")
    events = lambda source, kind, message: log.info("%s %s: %s", source, kind, message)  # noqa: E731
    camera_model = camera.open(clock, events)
    robot.open(clock, events)
    return camera, robot, camera_model


def _check_stream(which: str, streams, src: str) -> None:
    have = streams.names if streams is not None else ()
    if which not in have:
        raise ConfigError("camera.params.streams", f"the camera delivers no {which} images (it delivers "
                          f"{', '.join(('depth',) + tuple(have))}); add {which} to its streams "
                          "(e.g. streams: depth,ir and emitter: false for a clean board)", src)


def run_live_capture(session: str | Path, out: str | Path, count: int = 15, which: str = "ir", auto: bool = True,
                     board: str | None = None, rrd: str | Path | None = None, keys=None, clock=None,
                     stop: threading.Event | None = None, report=print) -> int:
    """Collect up to ``count`` captures into ``out``; returns how many were written.

    keys : a text stream whose lines request captures (default: stdin when it is a terminal; None
        in tests); clock : the :class:`app.interfaces.SessionClock` (a test shares it with its robot)
    """
    from app.geometry.ur import dh_from_config, forward_kinematics
    from app.interfaces import DropOldestQueue, SessionClock
    from app.session import load_session
    from calibration.board import DEFAULT_BOARD_SPEC, BoardDetector, parse_board_spec
    from calibration.captures import CaptureWriter
    from calibration.intrinsics import write_camera_yaml
    from calibration.live import CaptureRules, JointHistory, LiveCapturer, key_presses

    config = load_session(session, {"tracker": False, "outputs": [], "record": None, "out": None})
    stop = stop or threading.Event()
    clock = clock or SessionClock()
    camera, robot, camera_model = _open_sources(config, clock)
    try:
        robot_block = config.robot_model or robot.session_defaults().get("robot") or {"model": "ur5e"}
        dh = dh_from_config(robot_block)
        streams = camera.session_defaults().get("image_streams")
        _check_stream(which, streams, str(session))
    except Exception:
        camera.stop()
        robot.stop()
        raise
    spec = parse_board_spec(board or DEFAULT_BOARD_SPEC)
    joints, frames = JointHistory(), DropOldestQueue(4)
    sink = CaptureRerun(rrd) if rrd is not False else None
    writer = CaptureWriter(out, robot=robot_block, board=spec.to_string())
    write_camera_yaml(Path(out) / "camera.yaml", _intrinsics(which, camera_model, streams),
                      {"source": f"the session camera's {which} stream ({config.camera.name})"})
    capturer = LiveCapturer(BoardDetector(spec), writer, joints, lambda q: forward_kinematics(dh, q),
                            CaptureRules(count=int(count), auto=auto), rerun=sink)
    if keys is None and sys.stdin is not None and sys.stdin.isatty():
        keys = sys.stdin
    if keys is not None:
        key_presses(capturer, stop, keys)
    robot.start(lambda samples: joints.add(samples.stamps, samples.q))
    camera.start(frames.put)
    try:
        _loop(capturer, camera, frames, joints, which, stop, report, sink)
    finally:
        camera.stop()
        robot.stop()
        writer.close()
        if sink is not None:
            sink.close()
    return len(capturer.captured_q)


def _loop(capturer, camera, frames, joints, which, stop, report, sink) -> None:
    last = None
    while not capturer.done and not stop.is_set():
        frame = frames.get(timeout=0.1)
        if frame is None:
            if camera.finished.is_set() and not len(frames):
                report("the camera's stream ended")
                return
            continue
        image = _image_of(frame, which)
        if image is None:
            continue
        deadline = time.monotonic() + JOINT_WAIT_S
        while joints.window(frame.stamp, frame.stamp + 1e9)[0].size < 2 and time.monotonic() < deadline:
            time.sleep(0.005)
        status = capturer.on_frame(frame.stamp, image)
        kind = status.split(":")[0].split(";")[0]
        if status.startswith("capture") or kind != last:   # what changed, not every frame
            report(status)
            if sink is not None:
                sink.log_status(status)
        last = kind
    if capturer.warnings and capturer.captured_q:
        report("warning: " + "; ".join(capturer.warnings))


def run_command(args) -> int:
    """``osteonav calibrate capture`` on a live session (app/commands/calibrate.py has the arguments)."""
    from app.commands.outdir import prepare_dir
    from calibration.board import parse_board_spec

    if args.count < 3:
        raise ConfigError("--count", f"hand-eye calibration needs at least 3 captures, got {args.count}")
    try:
        parse_board_spec(args.board)
    except (ValueError, OSError) as exc:
        raise ConfigError("--board", str(exc)) from None
    rrd = False if args.no_viewer else args.rrd
    if rrd is None:   # spawn a viewer: only where one can open
        import os

        if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise ConfigError("--rrd", "no display for the rerun viewer here; pass --rrd FILE.rrd (or --no-viewer)")
    prepare_dir(args.out, args.overwrite)
    print("capturing: move the robot to varied poses with the board in view; it captures when the robot has "
          f"rested 0.5 s{'' if args.manual else ' (and on Enter)'}; q + Enter stops")
    n = run_live_capture(args.config, args.out, args.count, args.image, auto=not args.manual, board=args.board,
                         rrd=rrd)
    print(f"wrote {n} captures to {args.out}; next: osteonav calibrate hand-eye --captures {args.out}")
    return 0 if n >= 3 else 1
