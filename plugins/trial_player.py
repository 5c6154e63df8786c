"""Recorded and simulated trials played as live sources, in real time.

``camera: recorded`` / ``robot: recorded`` play a trial directory (RECORDING_FORMAT.md): each frame
is pushed when the host clock reaches its stamp, and the joint samples stream alongside. Stamps
go through the session's replay anchor (:meth:`app.interfaces.SessionClock.replay_to_host`) with
the trial's earliest stamp as origin, so camera and robot stay on one clock as they were recorded,
and that clock is the session's: the anchor is fixed when the sources start, however long opening
them took. Like a real camera the player never delivers a stale frame: behind its schedule (a busy
host), it decodes the frame that will be due once decoded and skips the older ones (``skipped``, in
the summary).
``loop: true`` plays the trial again and again (a soak, or a session as long as asked).
``preload_mb`` (default 512) decodes the camera's first frames once, before the session's clock
starts, as many as fit (app/trial/preload.py): a live camera hands the host frames already made, and
a PNG decode a frame would take close to half of one of two cores from the tracker. 0 decodes every
frame when it is played.

``camera: simulated`` / ``robot: simulated`` first simulate a trial (``app.sim.simulate``) into a
cache directory named by scenario, seed and duration (reused when already there), then play it the
same way: the simplest honest live source without hardware. Both plugins of a session given the
same parameters play the same trial. ``streams: depth,ir,color`` simulates the infrared and colour
images too (:mod:`app.sim.appearance`); the camera then delivers them with each frame. ``sensor:``
names the depth sensor model (:mod:`app.sim.sensors`: ``independent``, the default, ``stereo``,
``tof``, or ``NAME:KEY=VALUE,...``). ``pointer: true`` (with ``ir`` in ``streams``) draws a pointer tool
held on the crest into the infrared images (:mod:`app.sim.pointer`): a session whose ``bone.pointer``
reads it starts from its tip (configs/sessions/simulated_pointer.yaml).

A trial also knows its calibration, robot model, mesh and initial pose: ``session_defaults``
offers them to the session, which uses them for any key its file leaves out.
"""
from __future__ import annotations

import collections
import logging
import tempfile
import threading
from pathlib import Path

import numpy as np

from app.errors import megabytes
from app.interfaces import DepthFrame, JointSamples, SessionClock
from app.trial.preload import preload
from plugins._base import ThreadedSource

log = logging.getLogger(__name__)

_SIM_LOCK = threading.Lock()
PRELOAD_MB = 512   # the camera's frames decoded ahead, MB (app/trial/preload.py): a 6 s 640x480 trial takes 330


def _open(trial: str | Path):
    from app.trial.reader import open_trial

    return open_trial(trial)


def trial_defaults(reader) -> dict:
    """What a trial offers a session: camera, robot, dh, hand-eye, mesh path, initial pose."""
    meta = reader.meta
    mesh = Path(meta.mesh)
    if not mesh.is_absolute():
        mesh = Path(reader.path) / mesh
    return {
        "camera": meta.camera, "robot": dict(meta.robot), "dh": meta.dh,
        "T_flange_camera": np.asarray(meta.T_flange_camera, float), "mesh": mesh,
        "initial_pose": None if meta.initial_pose is None else np.asarray(meta.initial_pose, float),
        "trial": Path(reader.path),
        "image_streams": meta.streams,
    }


def _trial_origin(reader) -> float:
    stamps = np.asarray(reader.stamps, float)
    joint_stamps = np.asarray(reader.joint_stamps, float)
    return float(min(stamps[0], joint_stamps[0]) if len(joint_stamps) else stamps[0])


def simulated_trial(scenario: str, seconds: float | None, seed: int, mesh: str | None, trial_dir: str | None,
                    streams: str = "depth", sensor: str = "independent", pointer: bool = False) -> Path:
    """Simulate once per (scenario, seconds, seed, mesh, streams, sensor, pointer) into ``trial_dir`` (or a
    cache dir); return it. ``pointer``: a pointer tool held on the crest is drawn into the infrared images
    (app/sim/pointer.py's default tool, read by a session's ``bone.pointer`` of
    ``SimulatedPointer().session_block()``; streams must include ir)."""
    from app.sim.pointer import SimulatedPointer
    from app.sim.sensors import parse_sensor, sensor_label
    from app.sim.simulator import simulate

    model = parse_sensor(sensor)
    if trial_dir is None:
        tag = f"{scenario}-s{seed}-{seconds or 'default'}s" + (f"-{Path(mesh).stem}" if mesh else "")
        tag += "" if streams == "depth" else "-" + streams.replace(",", "-")
        tag += "" if sensor_label(model) == "independent" else "-" + sensor_label(model)
        tag += "-pointer" if pointer else ""
        trial_dir = Path(tempfile.gettempdir()) / "osteonav-sim" / tag
    out = Path(trial_dir)
    with _SIM_LOCK:
        if not (out / "trial.yaml").is_file() or not (out / "simulation.yaml").is_file():
            log.info("simulating %s (%s s, seed %d) into %s", scenario, seconds, seed, out)
            simulate(out, mesh_path=mesh, scenario_name=scenario, seconds=seconds, seed=seed, overwrite=True,
                     streams=streams, sensor=model, pointer=SimulatedPointer() if pointer else None)
    return out


class RecordedCamera(ThreadedSource):
    """Play a trial's depth frames at their stamps (``loop: true`` starts over at the end)."""

    kind, name = "camera", "recorded"

    def __init__(self, trial: str, loop: bool = False, preload_mb: float = PRELOAD_MB):
        super().__init__()
        self.trial = Path(trial)
        self.loop = loop
        self.preload_mb = megabytes(preload_mb, "camera.params.preload_mb", PRELOAD_MB,
                                    zero_means="decode every frame when it is played")
        self.reader = None
        self.skipped = 0      # frames due while the player was behind its schedule, never pushed
        self.pushed = 0
        self._decode_s = collections.deque(maxlen=8)   # the last frame decodes' durations (session clock)

    def open(self, clock: SessionClock, event):
        self._bind(clock, event)
        self.reader = preload(_open(self.trial), self.preload_mb)
        return self.reader.meta.camera

    def session_defaults(self) -> dict:
        return trial_defaults(self.reader)

    def _run(self) -> None:
        origin = _trial_origin(self.reader)
        stamps = np.asarray(self.reader.stamps, float)
        period = float(stamps[-1] - origin) + 0.1
        lap = 0
        while not self._stop.is_set():
            host = np.asarray(self.clock.replay_to_host(stamps + lap * period, origin), float)
            if not self._play_lap(host, lap):
                return
            if not self.loop:
                break
            lap += 1
        self._event("end", f"end of the recorded frames of {self.trial}")
        self.finished.set()

    def _play_lap(self, host: np.ndarray, lap: int) -> bool:
        """Push the frames of one lap at their host times ``host``; False if stopped.

        Like a real camera, the player never delivers a stale frame: it decodes the frame that will be
        due once decoded (the next one, while it keeps up; on a busy host, where the decode takes
        longer than a period, the frame due when the decode ends, by the last decodes' durations),
        then pushes it at its time; if the host slept past the next frame's time meanwhile, it
        decodes that one instead (while a decode is quicker than a period). The frames it passes over
        are skipped (counted in ``skipped``), so a slow host never builds a backlog of old frames.
        """
        i = 0
        period = float(np.median(np.diff(host))) if len(host) > 1 else np.inf
        end = float(host[-1] + period)                   # the last frame's slot ends
        while i < len(host):
            now = self.clock.now()
            if now >= end:                                    # even the last frame is stale
                self.skipped += len(host) - i
                break
            decode_s = min(self._decode_s) if self._decode_s else 0.0   # the quickest of the last decodes
            j = max(i, int(np.searchsorted(host, now + decode_s, side="right")) - 1)
            depth = self.reader.read_depth(j)
            self._decode_s.append(self.clock.now() - now)
            if not self._sleep_until(host[j]):
                return False
            if self._overslept(host, j, period, decode_s):   # a newer frame is due already: that one
                self.skipped += j + 1 - i
                i = j + 1
                continue
            self.skipped += j - i
            self._push(DepthFrame(lap_frame_id(self.reader.frame_ids, j, lap), float(host[j]),
                                  np.asarray(depth, np.float32), self.clock.now(),
                                  infrared=self.reader.read_infrared(j), color=self.reader.read_color(j)))
            self.pushed += 1
            i = j + 1
        return True

    def _overslept(self, host: np.ndarray, j: int, period: float, decode_s: float) -> bool:
        """True when the frame after ``j`` is due already (the host slept past it) and decoding it instead
        is quicker than a period (else the player would skip every frame of a slow host)."""
        return j + 1 < len(host) and self.clock.now() >= host[j + 1] and decode_s < period


class RecordedRobot(ThreadedSource):
    """Stream a trial's joint samples at their stamps, in 10 ms batches."""

    kind, name = "robot", "recorded"
    batch_s = 0.01

    def __init__(self, trial: str, loop: bool = False):
        super().__init__()
        self.trial = Path(trial)
        self.loop = loop
        self.reader = None

    def open(self, clock: SessionClock, event) -> None:
        self._bind(clock, event)
        self.reader = _open(self.trial)

    def session_defaults(self) -> dict:
        return trial_defaults(self.reader)

    def _run(self) -> None:
        origin = _trial_origin(self.reader)
        t = np.asarray(self.reader.joint_stamps, float)
        q = np.asarray(self.reader.joints, float)
        period = float(self.reader.stamps[-1] - origin) + 0.1
        lap = 0
        while not self._stop.is_set():
            host = np.asarray(self.clock.replay_to_host(t + lap * period, origin))
            i = 0
            while i < len(host) and not self._stop.is_set():
                now = self.clock.now()
                j = int(np.searchsorted(host, now, side="right"))
                if j > i:
                    self._push(JointSamples(host[i:j].copy(), q[i:j].copy()))
                    i = j
                else:
                    self._stop.wait(min(self.batch_s, max(host[i] - now, 0.0)))
            if not self.loop:
                break
            lap += 1
        self.finished.set()


def lap_frame_id(frame_ids, j: int, lap: int) -> int:
    """The id of frame ``j`` of a looped trial on lap ``lap``: the trial's ids shifted by ``lap`` times their span
    (last - first + 1), so the laps' ids run on without a gap (a jump of millions was counted as frames the
    camera dropped, and a looped session's recording was reported incomplete)."""
    first, last = int(frame_ids[0]), int(frame_ids[-1])
    return int(frame_ids[j]) + lap * (last - first + 1)


def _check_sensor(sensor: str, kind: str) -> None:
    """A ConfigError naming ``<kind>.params.sensor`` for a sensor model :func:`app.sim.sensors.parse_sensor` refuses."""
    from app.errors import ConfigError
    from app.sim.sensors import parse_sensor

    try:
        parse_sensor(sensor)
    except ValueError as exc:
        raise ConfigError(f"{kind}.params.sensor", str(exc)) from None


def _check_pointer(pointer, streams: str, kind: str) -> None:
    """A ConfigError naming ``<kind>.params.pointer`` unless it is a bool, and with the infrared stream."""
    from app.errors import ConfigError
    from app.sim.images import parse_streams

    if not isinstance(pointer, bool):
        raise ConfigError(f"{kind}.params.pointer", f"expected true or false, got {pointer!r}")
    try:
        names = parse_streams(str(streams))
    except ValueError as exc:
        raise ConfigError(f"{kind}.params.streams", str(exc)) from None
    if pointer and "ir" not in names:
        raise ConfigError(f"{kind}.params.pointer", f"the pointer's marker is drawn into the infrared images: set "
                          f"{kind}.params.streams to include ir (e.g. \"depth,ir\"), got {streams!r}")


class SimulatedCamera(RecordedCamera):
    """A simulated trial (``app.sim``) played as a live camera; see the module docstring."""

    name = "simulated"

    def __init__(self, scenario: str = "static_clear", seconds: float | None = None, seed: int = 0,
                 mesh: str | None = None, trial_dir: str | None = None, loop: bool = False, streams: str = "depth",
                 sensor: str = "independent", pointer: bool = False, preload_mb: float = PRELOAD_MB):
        _check_sensor(sensor, "camera")
        _check_pointer(pointer, streams, "camera")
        self._sim = (scenario, seconds, seed, mesh, trial_dir, streams, sensor, bool(pointer))
        super().__init__(trial="", loop=loop, preload_mb=preload_mb)

    def open(self, clock: SessionClock, event):
        self.trial = simulated_trial(*self._sim)
        return super().open(clock, event)


class SimulatedRobot(RecordedRobot):
    """The joints of the same simulated trial as :class:`SimulatedCamera` (same parameters)."""

    name = "simulated"

    def __init__(self, scenario: str = "static_clear", seconds: float | None = None, seed: int = 0,
                 mesh: str | None = None, trial_dir: str | None = None, loop: bool = False, streams: str = "depth",
                 sensor: str = "independent", pointer: bool = False):
        _check_sensor(sensor, "robot")
        _check_pointer(pointer, streams, "robot")
        self._sim = (scenario, seconds, seed, mesh, trial_dir, streams, sensor, bool(pointer))
        super().__init__(trial="", loop=loop)

    def open(self, clock: SessionClock, event) -> None:
        self.trial = simulated_trial(*self._sim)
        super().open(clock, event)
