"""The live loop (:func:`run_session`): sources -> bus -> newest frame -> tracker -> estimate -> sinks.

One thread (the tracker's GL context lives on it). See :mod:`app.session` for the steps; the
per-frame work is :meth:`LiveLoop.process` (the camera pose, then the per-frame core shared with
replay, :class:`app.pipeline.frame_core.FrameCore`), the tick without frames :meth:`LiveLoop.no_frame`.
"""
from __future__ import annotations

import collections
import json
import logging
import signal
import threading
from collections import Counter

import numpy as np

from app import plugins_registry as registry
from app.filter.status import LOST_NO_POSE_S, Reason, codes
from app.errors import ConfigError
from app.interfaces import DepthFrame, Estimate, SessionClock
from app.pipeline.frame_core import FrameCore
from app.outputs import wrote
from app.pipeline.sinks import EstimateFiles
from app.pipeline.tracker import start_tracker, tracker_report, use_projector_plan
from app.session.bus import Bus, EventLog, JointBuffer
from app.session.config import PluginSpec, SessionConfig, resolve_session
from app.session.summary import ESTIMATE_HISTORY, EVENT_HISTORY, LatencyLog, SessionResult, rss_mb

log = logging.getLogger("app.session")

RSS_EVERY_S = 10.0
LOST_TICK_S = 0.1     # while the camera is stalled, a lost estimate this often


def run_session(config: SessionConfig, stop: threading.Event | None = None, progress=None,
                clock: SessionClock | None = None) -> SessionResult:
    """Run the live loop until ``stop`` is set, Ctrl-C, ``loop.duration_s``, or a finite source ends.

    ``loop.duration_s`` counts from the sources' start (opening them, e.g. simulating a trial, is
    not part of it). ``clock`` may be injected (tests); by default the host's monotonic clock.
    """
    loop = LiveLoop(config, stop or threading.Event(), progress, clock)
    interrupted: list[str] = []
    restore_signals = _stop_on_signals(loop.stop, interrupted)
    try:
        loop.open()
        loop.start()
        loop.run()
        if interrupted:
            loop.events.emit("session", "stopped", f"interrupted ({interrupted[0]}): stopping cleanly")
    except KeyboardInterrupt:
        loop.events.emit("session", "stopped", "interrupted (a second signal or Ctrl-C while starting): stopping now")
    except Exception as exc:
        loop.events.emit("session", "error", f"{type(exc).__name__}: {exc}")
        raise
    finally:
        restore_signals()
        summary = loop.close()
    return SessionResult(summary, list(loop.estimates), list(loop.events.events))


class LiveLoop:
    """The loop's state: sources, tracker, sinks, the bus, and what the summary counts."""

    def __init__(self, config: SessionConfig, stop: threading.Event, progress=None, clock: SessionClock | None = None):
        self.config, self.stop, self.progress = config, stop, progress
        self.lc = config.loop
        self.clock = clock or SessionClock(replay_rate=self.lc.replay_rate)
        self.out = config.out
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
        self.events = EventLog(self.clock, self.out / "events.csv" if self.out else None, self.lc.event_repeat_s,
                               history=EVENT_HISTORY)
        self.camera = registry.create("camera", config.camera.name, config.camera.params, "camera")
        self.robot = registry.create("robot", config.robot.name, config.robot.params, "robot")
        self.sinks: list = []
        self.tracker = None
        self.estimate_files: EstimateFiles | None = None
        self.core = FrameCore(None, [], now=self.clock.now)   # wired in open(): tracker, files + output sinks
        self.bus: Bus | None = None
        self.point_source = None                # a live point for the start (bone.pointed_pixel / bone.pointer)
        self.ctx: dict = {}
        self.started: list = []
        self.statuses: Counter = Counter()
        self.blocked: Counter = Counter()       # reason code -> processed frames it kept from ok
        self.latency = LatencyLog()
        self.estimates: collections.deque = collections.deque(maxlen=ESTIMATE_HISTORY)
        self.rss: dict = {}
        self.t_start = self.clock.now()

    # ------------------------------------------------------------------ setup
    def open(self) -> None:
        """Open the sources, resolve the session against what they offer, create the tracker and sinks."""
        config = self.config
        camera_model = self.camera.open(self.clock, self.events.emit)
        self.robot.open(self.clock, self.events.emit)
        defaults = {**self.robot.session_defaults(), **self.camera.session_defaults()}
        ctx = resolve_session(config, camera_model, defaults)
        if ctx["camera"].width != camera_model.width or ctx["camera"].height != camera_model.height:
            raise ConfigError("calibration.intrinsics", f"{ctx['camera'].width}x{ctx['camera'].height} but the camera "
                                                        f"streams {camera_model.width}x{camera_model.height}")
        mesh = None
        if ctx["mesh_path"] is not None:
            from app.mesh import load_mesh

            mesh = load_mesh(ctx["mesh_path"])
        ctx.update(mesh=mesh, clock=self.clock, out=self.out, session_file=config.path,
                   image_streams=defaults.get("image_streams"))
        self.ctx = ctx
        if config.tracker is not None:
            self.tracker = self.core.tracker = self._create_tracker(mesh)
        self._open_sinks()
        use_projector_plan(self.tracker, self.sinks, mesh)   # the status bounds the plan's template points
        if self.out is not None and self.tracker is not None:
            self.estimate_files = EstimateFiles(self.out)
        self.core.sinks = [self.estimate_files, *self.sinks] if self.estimate_files is not None else list(self.sinks)
        joints = JointBuffer(self.lc.joint_buffer_s, self.lc.max_joint_gap_s)
        self.bus = Bus(ctx["camera"], self.events, joints, self.sinks, self.lc.tracker_queue)

    def _create_tracker(self, mesh):
        if mesh is None:
            raise ConfigError("bone.mesh", "missing: the tracker needs the bone mesh")
        if all(self.ctx.get(k) is None for k in ("initial_pose", "point_prior", "pointed_pixel", "pointer")):
            raise ConfigError("bone.initial_pose", "missing: the tracker starts from a coarse 4x4 T_base_bone "
                              "(or a point on the bone: bone.point_prior, bone.pointed_pixel or bone.pointer)")
        spec = self.config.tracker
        return registry.create("tracker", spec.name, spec.params, "tracker", mesh=mesh, camera=self.ctx["camera"],
                               T_flange_camera=self.ctx["T_flange_camera"])

    def _point_source(self):
        """The session's live point, or None: ``bone.pointed_pixel`` (app/tracking/start.py's PointedPixel
        on the depth camera the tracker was given) or ``bone.pointer`` (app/tracking/pointer.py's
        PointerTip in the camera's infrared or colour stream, which must be delivered)."""
        pixel, pointer = self.ctx.get("pointed_pixel"), self.ctx.get("pointer")
        if pixel is not None:
            from app.tracking.start import PointedPixel

            return PointedPixel(pixel, self.ctx["camera"])
        if pointer is None:
            return None
        from app.tracking.pointer import PointerTip

        streams = self.ctx.get("image_streams")
        stream = pointer["stream"]
        delivered = getattr(streams, "infrared" if stream == "ir" else "color", None)
        if delivered is None:
            raise ConfigError("bone.pointer.stream", f"the pointer is seen in the camera's {stream!r} stream, which "
                              f"this camera does not deliver ({', '.join(streams.names) if streams else 'depth only'}"
                              f"): add it to the camera's streams (e.g. camera.params.streams: "
                              f"\"depth,{stream}\") or set bone.pointer.stream to one it delivers")
        marker = {k: pointer[k] for k in ("marker_id", "marker_length_m", "tip_offset_m", "dictionary")}
        if stream == "ir":
            return PointerTip(**marker, camera=self.ctx["camera"], stream="ir")
        return PointerTip(**marker, camera=delivered.camera, stream="color", distortion=delivered.distortion,
                          T_depth_image=delivered.T_depth_color)

    def _open_sinks(self) -> None:
        specs = list(self.config.outputs)
        if self.config.record is not None:
            specs.append(PluginSpec("output", "recorder", {"dir": str(self.config.record)}, "record"))
        for spec in specs:
            sink = registry.create("output", spec.name, spec.params, spec.key or "output")
            sink.open(self.ctx)
            self.sinks.append(sink)
        self.events.sinks = self.sinks

    def start(self) -> None:
        """Start the tracker and the sources (robot first); the duration counts from here."""
        if self.tracker is not None:
            self.point_source = self._point_source()
            start_tracker(self.tracker, self.ctx["initial_pose"], self.ctx.get("point_prior"), self.point_source)
        self.robot.start(self.bus.push_joints)
        self.started.append(self.robot)
        self.t_sources = self.clock.now()
        self.rss = {"start": rss_mb(), "every_10s": []}
        self.next_rss = self.t_sources + RSS_EVERY_S
        self.camera.start(self.bus.push_frame)
        self.started.append(self.camera)
        self.last_frame_host = self.last_pose_host = self.clock.now()
        self.stalled = False
        self.last_lost_tick = 0.0

    # ------------------------------------------------------------------ the loop
    def run(self) -> None:
        """Until stopped, the duration is over or a finite camera has delivered everything."""
        lc, clock, frames = self.lc, self.clock, self.bus.frames
        while not self.stop.is_set():
            now = clock.now()
            if lc.duration_s is not None and now - self.t_sources >= lc.duration_s:
                break
            if now >= self.next_rss:
                self.rss["every_10s"].append(rss_mb())
                self.next_rss += RSS_EVERY_S
            frame = frames.get_latest(timeout=0.05)
            now = clock.now()
            if frame is None:
                if self.camera.finished.is_set() and not len(frames):
                    break
                self.no_frame(now)
                continue
            self.process(frame, now)

    def no_frame(self, now: float) -> None:
        """No frame: after ``stall_timeout_s``, the camera is stalled and the loop emits lost ticks."""
        if now - self.last_frame_host <= self.lc.stall_timeout_s:
            return
        if not self.stalled:
            self.events.emit("session", "camera_stall", f"no frame for {now - self.last_frame_host:.2f} s: status lost")
            self.stalled = True
        if now - self.last_lost_tick >= LOST_TICK_S:
            self.last_lost_tick = now
            est = Estimate(now, None, None, "lost", reasons=(Reason("no_frames", "no frames"),))
            self.statuses["lost (no frames)"] += 1
            for sink in self.sinks:
                sink.on_estimate(est)

    def process(self, frame: DepthFrame, t_pop: float) -> None:
        """One frame (popped at ``t_pop``): camera pose, then the core (tracker, estimate, sinks), latency."""
        if self.stalled:
            self.events.emit("session", "camera_recovered", f"frames again after {t_pop - self.last_frame_host:.2f} s")
            self.stalled = False
        self.last_frame_host = t_pop
        T_base_camera, reasons = self._camera_pose(frame, t_pop)
        floor = None
        if T_base_camera is None:   # capped without a camera pose: uncertain, lost after the tracker's lost_no_pose_s
            floor = "lost" if t_pop - self.last_pose_host > self._lost_no_pose_s() else "uncertain"
        if hasattr(self.point_source, "observe"):   # the pointer sees this frame's image before the tracker asks
            self.point_source.observe(frame)
        est = self.core.process(frame, T_base_camera, reasons, floor)
        self.statuses[est.status] += 1
        self.blocked.update(codes(est.reasons))
        self.estimates.append(_light(est))
        if self.core.t_estimate is not None:
            self.latency.add(frame, t_pop, self.core.t_estimate, self.clock.now())
        if self.progress:
            self.progress(est)

    def _lost_no_pose_s(self) -> float:
        """The one missing-pose clock (issue 32): the tracker's ``recovery.after_uncertain_s``
        (:attr:`app.pipeline.engine_tracker.EngineTracker.lost_no_pose_s`), the status module's default for a
        tracker that has none."""
        return float(getattr(self.tracker, "lost_no_pose_s", LOST_NO_POSE_S))

    def _camera_pose(self, frame: DepthFrame, now: float) -> tuple[np.ndarray | None, list[str]]:
        """``T_base_camera = FK(q(stamp)) T_flange_camera``, q interpolated at the frame's stamp, or None."""
        from app.geometry.ur import forward_kinematics

        q, why = self.bus.joints.at(frame.stamp, self.lc.robot_wait_s)
        if q is None:
            self.events.emit("session", "no_camera_pose", f"frame {frame.frame_id}: {why}")
            return None, [Reason("no_pose", f"no camera pose: {why}")]
        self.last_pose_host = now
        return forward_kinematics(self.ctx["dh"], q) @ self.ctx["T_flange_camera"], []

    # ------------------------------------------------------------------ shutdown
    def close(self) -> dict:
        """Stop the sources, close sinks and files, release the tracker; the summary (also summary.json)."""
        for source in reversed(self.started):
            source.stop()
        if not self.core.sinks:                 # open() stopped before wiring the core: close what it opened
            self.core.sinks = list(self.sinks)
        sink_reports = self.core.close()        # the outputs (last first), the files, then the tracker
        sink_reports.pop("EstimateFiles", None)
        summary = self.summary(sink_reports)
        if self.out is not None:
            wrote(self.out / "summary.json")
            (self.out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        self.events.close()
        return summary

    def summary(self, sink_reports: dict) -> dict:
        bus = self.bus
        return {
            "session": str(self.config.path) if self.config.path else None,
            "seconds": self.clock.now() - self.t_start,
            "camera": self.config.camera.name, "robot": self.config.robot.name,
            "frames": dict(bus.counts) if bus else {},
            "frames_skipped_by_tracker": bus.frames.dropped if bus else 0,
            "frames_skipped_by_camera": int(getattr(self.camera, "skipped", 0)),
            "processed": sum(v for k, v in self.statuses.items() if "(" not in k),
            "status_counts": dict(self.statuses),
            "blocked_by": {code: n / max(sum(v for k, v in self.statuses.items() if "(" not in k), 1)
                           for code, n in self.blocked.most_common()},
            **self.latency.summary(),
            "events": dict(self.events.counts),
            "rss_mb": {**self.rss, "end": rss_mb()},
            "outputs": sink_reports,
            **tracker_report(self.tracker),     # re-initialisations, template points (app/pipeline/tracker.py)
        }


def _light(est: Estimate) -> Estimate:
    """The estimate without its images, tracker result and particles (the loop keeps the last
    ESTIMATE_HISTORY in memory)."""
    diag = {k: v for k, v in est.diagnostics.items() if k not in ("frame", "result", "particles", "T_base_bone_true")}
    return Estimate(est.stamp, est.frame_id, est.T_base_bone, est.status, est.T_base_camera, est.latency_s,
                    est.reasons, diag)


def _stop_on_signals(stop: threading.Event, interrupted: list[str]):
    """Make Ctrl-C (SIGINT) and SIGTERM set ``stop`` (main thread only); returns a function that restores the
    previous handlers.

    The handler only sets a flag, which the loop reads at least every 50 ms: an exception raised at an
    arbitrary point of the main thread (Python's default for SIGINT) can land inside a lock's acquire or a
    sink's write and hang or corrupt the shutdown. A second signal while stopping raises
    KeyboardInterrupt, for a user who wants out now.
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        interrupted.append("Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}

    def restore():
        for sig, old in previous.items():
            signal.signal(sig, old)

    return restore
