"""The intraoperative session: a session file, the plugins it names, and the live loop.

A session file (YAML, ``format: osteonav-session/1``; examples in ``configs/sessions/``)::

    camera:  {plugin: realsense, params: {width: 848, height: 480, fps: 30}}
    robot:   {plugin: ur, params: {host: 192.168.1.10}, model: ur5e}   # or dh: {a, d, alpha}
    tracker: {plugin: particle_filter, params: {config: ../default.yaml}}
    calibration:
      hand_eye: ../../calib/hand_eye.yaml     # 4x4 T_flange_camera (a file, or inline)
      intrinsics: null                        # optional; default: what the camera reports
    bone:
      mesh: ../../data/bone.ply               # the bone frame, metres
      initial_pose: ../../calib/initial_pose.yaml   # 4x4 T_base_bone (a file, or inline)
    outputs: [{plugin: rerun, params: {path: session.rrd}}]
    record: recordings/today                  # optional: record the sensors as a trial
    out: recordings/today-tracking            # estimate.txt, status.csv, events.csv, summary.json
    loop: {stall_timeout_s: 0.5, duration_s: null}   # replay_rate: 0.25 plays a recorded source slower

Every relative path is relative to the session file, as ``config:`` is: inputs (calibration
files, ``bone.mesh``, plugin parameters named ``trial``, ``recording``, ``mesh``, ``config``) and
outputs alike (``out``, ``record``, an output plugin's ``path``/``dir``, a simulated trial's
``trial_dir``); the command line's ``--out``/``--record`` are relative to the current directory.
A recorded or simulated source
knows its trial's calibration, robot, mesh and initial pose; keys the file leaves out are taken
from there. Every error names the key (dotted) and the allowed values.

The loop (:func:`run_session`), one thread (the tracker's GL context lives on it):

1. Sources push from their own threads through the *bus*, which validates each frame (size,
   dtype, finite, non-negative, increasing stamp) and each joint sample (finite, increasing),
   rejects bad ones with a logged event, hands good ones to the sinks (the recorder queues every
   one of them), and keeps only the newest frames for the tracker (a bounded drop-oldest queue:
   the tracker works on the latest frame, and says how many it skipped).
2. For each frame the joint buffer is interpolated at the frame's stamp (waiting up to
   ``robot_wait_s`` for the robot to catch up): ``T_base_camera = FK(q) T_flange_camera``.
3. The tracker steps; the status is capped at ``uncertain`` without a camera pose and at ``lost``
   after ``robot_lost_s`` without one; with no frames for ``stall_timeout_s`` the loop emits
   ``lost`` estimates (the projector shows no template) until frames return.
4. Frame-to-estimate latency (host time at the estimate minus the frame's capture stamp) is
   measured per frame, logged, and summarised (median, p99).

Ctrl-C (or SIGTERM) ends the loop; sources stop, sinks flush and close, the summary is written.
"""
from __future__ import annotations

import collections
import csv
import json
import logging
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from app import plugins_registry as registry
from app.errors import ConfigError
from app.geometry.camera import PinholeCamera
from app.interfaces import DepthFrame, DropOldestQueue, Estimate, JointSamples, SessionClock, SessionEvent
from app.metrics import STATUS_CODE as STATUS_RANK

log = logging.getLogger(__name__)

FORMAT = "osteonav-session/1"
TOP_KEYS = ("format", "camera", "robot", "tracker", "calibration", "bone", "outputs", "record", "out", "loop")
INPUT_PATH_PARAMS = ("trial", "recording", "mesh", "config")
OUTPUT_PATH_PARAMS = ("trial_dir", "path", "dir")   # resolved against the session file too


# ------------------------------------------------------------------------------------------------
# configuration
# ------------------------------------------------------------------------------------------------
@dataclass
class PluginSpec:
    kind: str
    name: str
    params: dict = field(default_factory=dict)
    key: str = ""


@dataclass
class LoopConfig:
    """Loop timing (seconds) and queue sizes."""

    stall_timeout_s: float = 0.5      # no frame for this long: the camera is stalled (status lost)
    robot_wait_s: float = 0.05        # wait this long for joints covering a frame's stamp
    max_joint_gap_s: float = 0.05     # joint samples further apart than this do not interpolate
    robot_lost_s: float = 1.0         # no camera pose for this long: status lost
    duration_s: float | None = None   # stop after this long (None: until stopped)
    tracker_queue: int = 2            # frames waiting for the tracker (newest kept)
    joint_buffer_s: float = 10.0      # joint history kept for interpolation
    event_repeat_s: float = 1.0       # the same event from the same source is logged once per this
    replay_rate: float = 1.0          # recorded/simulated sources play at this speed (0.25: a quarter)


@dataclass
class SessionConfig:
    path: Path | None
    camera: PluginSpec
    robot: PluginSpec
    tracker: PluginSpec | None
    outputs: list[PluginSpec]
    robot_model: dict | None = None
    hand_eye: np.ndarray | None = None
    intrinsics: PinholeCamera | None = None
    mesh: Path | None = None
    initial_pose: np.ndarray | None = None
    record: Path | None = None
    out: Path | None = None
    loop: LoopConfig = field(default_factory=LoopConfig)


def _allowed(key: str, value: Any, allowed) -> None:
    if value not in allowed:
        raise ConfigError(key, f"got {value!r}; allowed: {', '.join(map(str, allowed))}")


def _mapping(key: str, value: Any, src: str) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(key, f"expected a mapping, got {type(value).__name__} {value!r}", src)
    return value


def _resolve(base: Path, value: str | Path | None) -> Path | None:
    if value is None:
        return None
    p = Path(str(value)).expanduser()
    return p if p.is_absolute() else (base / p)


def _matrix4(key: str, value: Any, base: Path, src: str) -> np.ndarray | None:
    """A 4x4 rigid transform given inline or as a file (YAML: a 4x4, or a mapping with ``key``'s name)."""
    if value is None:
        return None
    if isinstance(value, (str, Path)):
        path = _resolve(base, value)
        if not path.is_file():
            raise ConfigError(key, f"file not found: {path}", src)
        if path.suffix in (".txt", ".csv"):
            value = np.loadtxt(path, delimiter="," if path.suffix == ".csv" else None).tolist()
        else:
            loaded = yaml.safe_load(path.read_text())
            if isinstance(loaded, dict):
                names = [key.split(".")[-1], "hand_eye", "T_flange_camera", "initial_pose", "T_base_bone", "T"]
                found = next((loaded[n] for n in names if n in loaded), None)
                if found is None:
                    raise ConfigError(key, f"{path} holds none of the keys {', '.join(names)}", src)
                loaded = found
            value = loaded
    try:
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(key, f"expected a 4x4 matrix of numbers, got {value!r}", src) from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ConfigError(key, f"expected a finite 4x4 matrix, got shape {T.shape}", src)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1]) or np.linalg.det(R) < 0:
        raise ConfigError(key, "not a rigid transform (rotation not orthonormal, or last row not 0 0 0 1)", src)
    return T


def _plugin(kind: str, value: Any, base: Path, src: str, default: str | None = None) -> PluginSpec:
    key = kind
    block = {"plugin": default} if value is None and default else _mapping(key, value, src)
    for k in block:
        _allowed(f"{key}.{k}", k, ("plugin", "params", "model", "dh") if kind == "robot" else ("plugin", "params"))
    name = block.get("plugin")
    if name is None:
        raise ConfigError(f"{key}.plugin", f"missing; allowed: {', '.join(registry.available(kind))}", src)
    _allowed(f"{key}.plugin", name, registry.available(kind))
    params = dict(_mapping(f"{key}.params", block.get("params"), src))
    for k, v in params.items():
        if k in INPUT_PATH_PARAMS + OUTPUT_PATH_PARAMS and isinstance(v, str):
            params[k] = str(_resolve(base, v))
    return PluginSpec(kind, name, params, key)


def load_session(path: str | Path, overrides: dict | None = None) -> SessionConfig:
    """Read and validate a session file; ``overrides`` (top-level keys) replace the file's values."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("--config", f"session file not found: {path}")
    src = str(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError("(file)", f"not valid YAML: {exc}", src) from None
    if not isinstance(raw, dict):
        raise ConfigError("(file)", "expected a mapping at the top level", src)
    raw.update(overrides or {})
    return parse_session(raw, path.parent, src, path)


def parse_session(raw: dict, base: Path, src: str = "(session)", path: Path | None = None) -> SessionConfig:
    for k in raw:
        _allowed(k, k, TOP_KEYS)
    if raw.get("format", FORMAT) != FORMAT:
        raise ConfigError("format", f"got {raw['format']!r}; allowed: {FORMAT}", src)
    for k in ("camera", "robot"):
        if k not in raw:
            raise ConfigError(k, f"missing; a session names its {k} plugin ({', '.join(registry.available(k))})", src)
    camera = _plugin("camera", raw["camera"], base, src)
    robot = _plugin("robot", raw["robot"], base, src)
    robot_block = raw["robot"] or {}
    robot_model = None
    if "model" in robot_block or "dh" in robot_block:
        from app.geometry.ur import dh_from_config

        robot_model = {k: robot_block[k] for k in ("model", "dh") if k in robot_block}
        try:
            dh_from_config(robot_model)
        except (ValueError, KeyError) as exc:
            raise ConfigError("robot.model", str(exc), src) from None
    tracker_raw = raw.get("tracker")
    tracker = None if tracker_raw is False else _plugin("tracker", tracker_raw, base, src, "particle_filter")
    outputs_raw = raw.get("outputs") or []
    if not isinstance(outputs_raw, list):
        raise ConfigError("outputs", "expected a list of {plugin, params}", src)
    outputs = []
    for i, o in enumerate(outputs_raw):
        spec = _plugin("output", o, base, src)
        spec.key = f"outputs[{i}]"
        outputs.append(spec)
    calib = _mapping("calibration", raw.get("calibration"), src)
    for k in calib:
        _allowed(f"calibration.{k}", k, ("hand_eye", "intrinsics"))
    intrinsics = None
    if calib.get("intrinsics") is not None:
        value = calib["intrinsics"]
        if isinstance(value, str):
            p = _resolve(base, value)
            if not p.is_file():
                raise ConfigError("calibration.intrinsics", f"file not found: {p}", src)
            value = yaml.safe_load(p.read_text())
            value = value.get("camera", value) if isinstance(value, dict) else value
        try:
            intrinsics = PinholeCamera.from_dict(value)
        except (TypeError, ValueError, KeyError) as exc:
            raise ConfigError("calibration.intrinsics", f"expected width, height and K (3x3): {exc}", src) from None
    bone = _mapping("bone", raw.get("bone"), src)
    for k in bone:
        _allowed(f"bone.{k}", k, ("mesh", "initial_pose"))
    mesh = _resolve(base, bone.get("mesh"))
    if mesh is not None and not mesh.is_file():
        raise ConfigError("bone.mesh", f"file not found: {mesh}", src)
    loop_raw = _mapping("loop", raw.get("loop"), src)
    loop = LoopConfig()
    for k, v in loop_raw.items():
        _allowed(f"loop.{k}", k, tuple(LoopConfig.__dataclass_fields__))
        if v is not None and (not isinstance(v, (int, float)) or isinstance(v, bool) or v <= 0):
            raise ConfigError(f"loop.{k}", f"expected a positive number, got {v!r}", src)
        setattr(loop, k, v)
    return SessionConfig(
        path=path, camera=camera, robot=robot, tracker=tracker, outputs=outputs, robot_model=robot_model,
        hand_eye=_matrix4("calibration.hand_eye", calib.get("hand_eye"), base, src), intrinsics=intrinsics,
        mesh=mesh, initial_pose=_matrix4("bone.initial_pose", bone.get("initial_pose"), base, src),
        record=_resolve(base, raw.get("record")), out=_resolve(base, raw.get("out")), loop=loop,
    )


# ------------------------------------------------------------------------------------------------
# events, joints
# ------------------------------------------------------------------------------------------------
class EventLog:
    """Thread-safe session events: logged, written to ``events.csv`` (flushed), passed to the sinks.

    The same (source, kind) within ``repeat_s`` is counted but not repeated.
    """

    def __init__(self, clock: SessionClock, path: Path | None, repeat_s: float = 1.0):
        self.clock = clock
        self.repeat_s = repeat_s
        self.counts: Counter = Counter()
        self.events: list[SessionEvent] = []
        self.sinks: list = []
        self._last: dict[tuple[str, str], float] = {}
        self._lock = threading.Lock()
        self._file = None
        if path is not None:
            self._file = open(path, "w", newline="", buffering=1)
            self._file.write("stamp,source,kind,message\n")

    def emit(self, source: str, kind: str, message: str) -> None:
        now = self.clock.now()
        with self._lock:
            self.counts[f"{source}.{kind}"] += 1
            last = self._last.get((source, kind))
            if last is not None and now - last < self.repeat_s:
                return
            self._last[(source, kind)] = now
            event = SessionEvent(now, source, kind, message)
            self.events.append(event)
            if self._file is not None:
                csv.writer(self._file).writerow([f"{now:.6f}", source, kind, message])
                self._file.flush()
        level = logging.INFO if kind in ("connected", "recovered", "end") else logging.WARNING
        log.log(level, "[%.3f s] %s %s: %s", now - self.clock.t0, source, kind, message)
        for sink in self.sinks:
            try:
                sink.on_event(event)
            except Exception:
                log.exception("output failed on an event")

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class JointBuffer:
    """The recent joint samples (host stamps), interpolated at a frame's stamp. Thread-safe."""

    def __init__(self, seconds: float = 10.0, max_gap_s: float = 0.05):
        self.seconds = seconds
        self.max_gap_s = max_gap_s
        self._t = np.empty(0)
        self._q = np.empty((0, 6))
        self._cond = threading.Condition()

    def add(self, stamps: np.ndarray, q: np.ndarray) -> None:
        with self._cond:
            self._t = np.concatenate([self._t, stamps])
            self._q = np.concatenate([self._q, q])
            keep = self._t >= self._t[-1] - self.seconds
            if not keep.all():
                self._t, self._q = self._t[keep], self._q[keep]
            self._cond.notify_all()

    def latest(self) -> float | None:
        with self._cond:
            return float(self._t[-1]) if len(self._t) else None

    def at(self, t: float, wait_s: float = 0.0) -> tuple[np.ndarray | None, str | None]:
        """Joints (6,) at host time ``t``, or (None, reason)."""
        deadline = time.monotonic() + wait_s
        with self._cond:
            while (not len(self._t) or self._t[-1] < t) and time.monotonic() < deadline:
                self._cond.wait(max(deadline - time.monotonic(), 0.0))
            stamps, q = self._t, self._q
        from app.geometry.ur import interpolate_joints

        if not len(stamps):
            return None, "no joint samples yet"
        if t > stamps[-1]:
            return None, f"joints end {t - stamps[-1]:.3f} s before the frame"
        if t < stamps[0]:
            return None, "frame older than the joint history"
        hi = int(np.searchsorted(stamps, t, side="left"))
        lo = max(hi - 1, 0)
        if stamps[hi] - stamps[lo] > self.max_gap_s:
            return None, f"joint samples {stamps[hi] - stamps[lo]:.3f} s apart around the frame"
        qi, valid = interpolate_joints(stamps[lo:hi + 1], q[lo:hi + 1], np.array([t]))
        return (qi[0], None) if valid[0] else (None, "joints not finite")


# ------------------------------------------------------------------------------------------------
# the bus: validation and fan-out, called from the sources' threads
# ------------------------------------------------------------------------------------------------
class Bus:
    """Validates what the sources push, fans it out to sinks, keeps the newest frames for the tracker."""

    def __init__(self, camera: PinholeCamera, events: EventLog, joints: JointBuffer, sinks: list, tracker_queue: int):
        self.camera = camera
        self.events = events
        self.joints = joints
        self.sinks = sinks
        self.frames = DropOldestQueue(tracker_queue)
        self.counts: Counter = Counter()
        self._last_frame_stamp = -np.inf
        self._last_joint_stamp = -np.inf
        self._lock = threading.Lock()

    def push_frame(self, frame: DepthFrame) -> None:
        self.counts["frames_received"] += 1
        d = frame.depth_m
        problem = None
        if not isinstance(d, np.ndarray) or d.ndim != 2:
            problem = ("corrupt_frame", f"frame {frame.frame_id}: not a 2-D array ({type(d).__name__})")
        elif d.shape != (self.camera.height, self.camera.width):
            problem = ("wrong_size_frame", f"frame {frame.frame_id}: {d.shape[1]}x{d.shape[0]}, expected "
                                           f"{self.camera.width}x{self.camera.height}")
        elif d.dtype != np.float32:
            problem = ("corrupt_frame", f"frame {frame.frame_id}: dtype {d.dtype}, expected float32 metres")
        elif not np.isfinite(frame.stamp):
            problem = ("clock", f"frame {frame.frame_id}: stamp {frame.stamp}")
        elif frame.stamp <= self._last_frame_stamp:
            problem = ("clock", f"frame {frame.frame_id}: stamp {frame.stamp:.6f} not after the previous "
                                f"{self._last_frame_stamp:.6f} (clock went back)")
        else:
            bad = ~np.isfinite(d) | (d < 0)
            if bad.any():
                problem = ("corrupt_frame", f"frame {frame.frame_id}: {int(bad.sum())} pixels NaN, infinite or negative")
        if problem is not None:
            self.counts[f"frames_rejected_{problem[0]}"] += 1
            self.events.emit("camera", *problem)
            return
        self._last_frame_stamp = frame.stamp
        self.counts["frames_accepted"] += 1
        for sink in self.sinks:
            sink.on_frame(frame)
        self.frames.put(frame)

    def push_joints(self, samples: JointSamples) -> None:
        t = np.asarray(samples.stamps, float)
        q = np.asarray(samples.q, float)
        self.counts["joint_samples_received"] += len(t)
        if q.ndim != 2 or q.shape != (len(t), 6):
            self.counts["joint_samples_rejected"] += len(t)
            self.events.emit("robot", "corrupt_joints", f"joint batch of shape {q.shape}, expected ({len(t)}, 6)")
            return
        with self._lock:
            finite = np.all(np.isfinite(q), axis=1) & np.isfinite(t)
            if not finite.all():
                self.events.emit("robot", "nan_joints", f"{int((~finite).sum())} joint samples not finite, dropped")
            keep = finite.copy()
            last = self._last_joint_stamp
            for k in np.flatnonzero(finite):
                if t[k] <= last:
                    keep[k] = False
                else:
                    last = t[k]
            if (finite & ~keep).any():
                self.events.emit("robot", "clock", f"{int((finite & ~keep).sum())} joint samples not after the "
                                                   "previous stamp (clock went back), dropped")
            self.counts["joint_samples_rejected"] += int((~keep).sum())
            if not keep.any():
                return
            self._last_joint_stamp = last
            good = JointSamples(t[keep], q[keep])
            self.joints.add(good.stamps, good.q)
        for sink in self.sinks:
            sink.on_joints(good)


# ------------------------------------------------------------------------------------------------
# the loop
# ------------------------------------------------------------------------------------------------
@dataclass
class SessionResult:
    """The summary (also ``out/summary.json``), the last 100,000 estimates (without images), the events."""

    summary: dict
    estimates: list[Estimate]
    events: list[SessionEvent]


def _summary_stats(values: list[float]) -> dict:
    if not values:
        return {"median": None, "p99": None, "max": None, "n": 0}
    a = np.asarray(values)
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "max": float(a.max()), "n": int(len(a))}


class LatencyLog:
    """Where a frame's time goes, per processed frame (seconds on the session clock).

    capture->arrival (``frame.arrival - frame.stamp``: the source's own delay), queue wait (the
    loop's pop minus the arrival), tracker (joint interpolation and ``tracker.process``), sinks
    (every sink's ``on_estimate``). The frame-to-estimate latency is
    ``capture->arrival + queue wait + tracker``; sinks run after the estimate is made.
    """

    STAGES = ("capture_to_arrival", "queue_wait", "tracker", "sinks")

    def __init__(self):
        self.t_estimate: list[float] = []
        self.latency: list[float] = []
        self.stages: dict[str, list[float]] = {k: [] for k in self.STAGES}

    def add(self, frame: DepthFrame, t_pop: float, t_estimate: float, t_sinks_done: float) -> None:
        self.t_estimate.append(t_estimate)
        self.latency.append(t_estimate - frame.stamp)
        for key, value in zip(self.STAGES, (frame.arrival - frame.stamp, t_pop - frame.arrival,
                                             t_estimate - t_pop, t_sinks_done - t_estimate)):
            self.stages[key].append(value)

    def summary(self, window_s: float = 10.0) -> dict:
        """Latency (ms) overall, per stage, and over the first and last ``window_s`` of the session."""
        out = {"latency_ms": _ms(_summary_stats(self.latency)),
               "latency_stages_ms": {k: _ms(_summary_stats(v)) for k, v in self.stages.items()}}
        if self.t_estimate:
            t = np.asarray(self.t_estimate)
            lat = np.asarray(self.latency)
            first, last = t <= t[0] + window_s, t >= t[-1] - window_s
            out["latency_first_ms"] = _ms(_summary_stats(list(lat[first])))
            out["latency_last_ms"] = _ms(_summary_stats(list(lat[last])))
            out["latency_window_s"] = window_s
            span = max(t[-1] - t[0], 1e-9)
            out["rate_hz"] = {"all": (len(t) - 1) / span if len(t) > 1 else None,
                              "first": int(first.sum()) / min(window_s, span), "last": int(last.sum()) / min(window_s, span)}
        return out


def rss_mb() -> float | None:
    """This process's resident memory now (MB; Linux /proc, else None)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    import os

    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def _ms(stats: dict) -> dict:
    return {k: (None if v is None else (1e3 * v if k != "n" else v)) for k, v in stats.items()}


class _EstimateFiles:
    """estimate.txt (TUM) and status.csv, one row per processed frame, flushed row by row."""

    def __init__(self, out: Path):
        self.tum = open(out / "estimate.txt", "w", buffering=1)
        self.tum.write("# stamp tx ty tz qx qy qz qw\n")
        self.status = open(out / "status.csv", "w", buffering=1)
        self.status.write("stamp,status\n")

    def write(self, est: Estimate) -> None:
        from app.geometry import quaternion as quat
        from app.geometry import se3

        if est.T_base_bone is not None:
            q, t = se3.to_quat_trans(est.T_base_bone)
            x, y, z, w = quat.to_xyzw(q)
            self.tum.write(f"{est.stamp:.6f} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {x:.8f} {y:.8f} {z:.8f} {w:.8f}\n")
        self.status.write(f"{est.stamp:.6f},{est.status}\n")

    def close(self) -> None:
        self.tum.close()
        self.status.close()


def _resolve_session(config: SessionConfig, camera_model: PinholeCamera, defaults: dict) -> dict:
    """Calibration, robot model, mesh and initial pose: the file's, else the sources'."""
    from app.geometry.ur import dh_from_config

    robot = config.robot_model or defaults.get("robot")
    if robot is None:
        raise ConfigError("robot.model", "missing: name the robot model (ur3e, ur5e, ur10e, ur16e, ...) or give dh")
    T_flange_camera = config.hand_eye if config.hand_eye is not None else defaults.get("T_flange_camera")
    if T_flange_camera is None:
        raise ConfigError("calibration.hand_eye", "missing: the 4x4 camera pose in the flange frame (a file or inline)")
    mesh = config.mesh or defaults.get("mesh")
    initial_pose = config.initial_pose if config.initial_pose is not None else defaults.get("initial_pose")
    return {"camera": config.intrinsics or camera_model, "robot": robot, "dh": dh_from_config(robot),
            "T_flange_camera": np.asarray(T_flange_camera, float), "mesh_path": Path(mesh) if mesh else None,
            "initial_pose": initial_pose}


def run_session(config: SessionConfig, stop: threading.Event | None = None, progress=None,
                clock: SessionClock | None = None) -> SessionResult:
    """Run the live loop until ``stop`` is set, Ctrl-C, ``loop.duration_s``, or a finite source ends.

    ``loop.duration_s`` counts from the sources' start (opening them, e.g. simulating a trial, is
    not part of it). ``clock`` may be injected (tests); by default the host's monotonic clock.
    """
    import trimesh

    from app.geometry.ur import forward_kinematics

    stop = stop or threading.Event()
    lc = config.loop
    clock = clock or SessionClock(replay_rate=lc.replay_rate)
    out = config.out
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    events = EventLog(clock, out / "events.csv" if out else None, lc.event_repeat_s)
    camera = registry.create("camera", config.camera.name, config.camera.params, "camera")
    robot = registry.create("robot", config.robot.name, config.robot.params, "robot")
    sinks: list = []
    tracker = None
    estimate_files = None
    started: list = []
    statuses: Counter = Counter()
    latency = LatencyLog()
    estimates: collections.deque = collections.deque(maxlen=100_000)
    t_start = clock.now()
    interrupted: list[str] = []
    restore_signals = _stop_on_signals(stop, interrupted)
    try:
        camera_model = camera.open(clock, events.emit)
        robot.open(clock, events.emit)
        defaults = {**robot.session_defaults(), **camera.session_defaults()}
        ctx = _resolve_session(config, camera_model, defaults)
        if ctx["camera"].width != camera_model.width or ctx["camera"].height != camera_model.height:
            raise ConfigError("calibration.intrinsics", f"{ctx['camera'].width}x{ctx['camera'].height} but the camera "
                                                        f"streams {camera_model.width}x{camera_model.height}")
        mesh = None
        if ctx["mesh_path"] is not None:
            from app.mesh import load_mesh

            mesh = load_mesh(ctx["mesh_path"])
        ctx.update(mesh=mesh, clock=clock, out=out, session_file=config.path)
        if config.tracker is not None:
            if mesh is None:
                raise ConfigError("bone.mesh", "missing: the tracker needs the bone mesh")
            if ctx["initial_pose"] is None:
                raise ConfigError("bone.initial_pose", "missing: the tracker starts from a coarse 4x4 T_base_bone")
            tracker = registry.create("tracker", config.tracker.name, config.tracker.params, "tracker",
                                      mesh=mesh, camera=ctx["camera"], T_flange_camera=ctx["T_flange_camera"])
        specs = list(config.outputs)
        if config.record is not None:
            specs.append(PluginSpec("output", "recorder", {"dir": str(config.record)}, "record"))
        for spec in specs:
            sink = registry.create("output", spec.name, spec.params, spec.key or "output")
            sink.open(ctx)
            sinks.append(sink)
        events.sinks = sinks
        if out is not None and tracker is not None:
            estimate_files = _EstimateFiles(out)
        joints = JointBuffer(lc.joint_buffer_s, lc.max_joint_gap_s)
        bus = Bus(ctx["camera"], events, joints, sinks, lc.tracker_queue)
        if tracker is not None:
            tracker.start(np.asarray(ctx["initial_pose"], float))
        robot.start(bus.push_joints)
        started.append(robot)
        t_sources = clock.now()
        rss = {"start": rss_mb(), "every_10s": []}
        next_rss = t_sources + 10.0
        camera.start(bus.push_frame)
        started.append(camera)
        T_flange_camera = ctx["T_flange_camera"]
        last_frame_host = clock.now()
        last_pose_host = clock.now()
        stalled = False
        last_lost_tick = 0.0
        while not stop.is_set():
            now = clock.now()
            if lc.duration_s is not None and now - t_sources >= lc.duration_s:
                break
            if now >= next_rss:
                rss["every_10s"].append(rss_mb())
                next_rss += 10.0
            frame = bus.frames.get_latest(timeout=0.05)
            now = clock.now()
            if frame is None:
                if camera.finished.is_set() and not len(bus.frames):
                    break
                if now - last_frame_host > lc.stall_timeout_s:
                    if not stalled:
                        events.emit("session", "camera_stall", f"no frame for {now - last_frame_host:.2f} s: status lost")
                        stalled = True
                    if now - last_lost_tick >= 0.1:
                        last_lost_tick = now
                        est = Estimate(now, None, None, "lost", reasons=("no frames",))
                        statuses["lost (no frames)"] += 1
                        for sink in sinks:
                            sink.on_estimate(est)
                continue
            if stalled:
                events.emit("session", "camera_recovered", f"frames again after {now - last_frame_host:.2f} s")
                stalled = False
            last_frame_host = now
            q, why = joints.at(frame.stamp, lc.robot_wait_s)
            T_base_camera = None
            reasons = []
            if q is not None:
                T_base_camera = forward_kinematics(ctx["dh"], q) @ T_flange_camera
                last_pose_host = now
            else:
                reasons.append(f"no camera pose: {why}")
                events.emit("session", "no_camera_pose", f"frame {frame.frame_id}: {why}")
            if tracker is None:
                est = Estimate(frame.stamp, frame.frame_id, None, "lost", T_base_camera, clock.now() - frame.stamp,
                               ("not tracking",))
                t_estimate = None
            else:
                result = tracker.process(frame.depth_m, frame.stamp, T_base_camera)
                status = result.status
                if T_base_camera is None:
                    floor = "lost" if now - last_pose_host > lc.robot_lost_s else "uncertain"
                    status = max(status, floor, key=STATUS_RANK.get)
                t_estimate = clock.now()
                est = Estimate(frame.stamp, frame.frame_id, np.asarray(result.T_base_bone, float), status, T_base_camera,
                               t_estimate - frame.stamp, tuple(reasons),
                               {"ess_ratio": getattr(result, "ess_ratio", None),
                                "position_spread": getattr(result, "position_spread", None),
                                "rotation_spread": getattr(result, "rotation_spread", None),
                                "frame": frame})
                if estimate_files is not None:
                    estimate_files.write(est)
            statuses[est.status] += 1
            estimates.append(_light(est))
            for sink in sinks:
                sink.on_estimate(est)
            if t_estimate is not None:
                latency.add(frame, now, t_estimate, clock.now())
            if progress:
                progress(est)
        if interrupted:
            events.emit("session", "stopped", f"interrupted ({interrupted[0]}): stopping cleanly")
    except KeyboardInterrupt:
        events.emit("session", "stopped", "interrupted (a second signal or Ctrl-C while starting): stopping now")
    except Exception as exc:
        events.emit("session", "error", f"{type(exc).__name__}: {exc}")
        raise
    finally:
        restore_signals()
        for source in reversed(started):
            source.stop()
        sink_reports = {}
        for sink in sinks:
            try:
                sink_reports[type(sink).__name__] = sink.close()
            except Exception as exc:
                log.exception("closing an output failed")
                sink_reports[type(sink).__name__] = {"error": str(exc)}
        if estimate_files is not None:
            estimate_files.close()
        if tracker is not None:
            tracker.release()
        summary = {
            "session": str(config.path) if config.path else None,
            "seconds": clock.now() - t_start,
            "camera": config.camera.name, "robot": config.robot.name,
            "frames": dict(bus.counts) if "bus" in locals() else {},
            "frames_skipped_by_tracker": bus.frames.dropped if "bus" in locals() else 0,
            "frames_skipped_by_camera": int(getattr(camera, "skipped", 0)),
            "processed": sum(v for k, v in statuses.items() if "(" not in k),
            "status_counts": dict(statuses),
            **latency.summary(),
            "events": dict(events.counts),
            "rss_mb": {**(rss if "rss" in locals() else {}), "end": rss_mb()},
            "outputs": sink_reports,
        }
        if out is not None:
            (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        events.close()
    return SessionResult(summary, list(estimates), list(events.events))


def _light(est: Estimate) -> Estimate:
    """The estimate without its depth image (kept in memory for the whole session)."""
    diag = {k: v for k, v in est.diagnostics.items() if k != "frame"}
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
