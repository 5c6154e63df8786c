"""Publication C's marker + IMU tracker as a session plugin (``tracker: marker_imu``).

A thin adapter over :class:`app.marker.fusion.MarkerImuFusion`. The session loop is driven by the
depth camera's frames; this tracker takes each frame's stamp as its tick and reads its own inputs:

- images (``images``): ``simulated`` renders :mod:`app.marker.simulator`'s marker image at the
  tick (a live grey/IR stream needs an image source in the session; not wired yet);
- IMU (``imu``): ``simulated`` (the same simulator's drifting IMU), ``udp`` (the protocol of
  :mod:`app.marker.imu`, listening on ``imu_host``:``imu_port``, loopback by default) or ``file``
  (a CSV of :func:`app.marker.imu.read_csv`, replayed by time since the first tick).

The output pose is ``T_base_bone = T_base_camera T_C_M T_marker_bone`` (the camera's pose from the
robot; identity when the session has none). Status: ``ok`` with a marker detection within
``ok_s``, ``uncertain`` while only the IMU carries the orientation (up to ``lost_s``), else ``lost``.
The diagnostics carry the detection path ('roi' | 'full' | 'none') and, when the fusion has an
APP registration, the inclination and anteversion.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from app.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class MarkerImuResult:
    T_base_bone: np.ndarray
    status: str
    path: str
    q_C_M: np.ndarray | None
    diagnostics: dict = field(default_factory=dict)


class MarkerImuTracker:
    kind, name = "tracker", "marker_imu"

    def __init__(self, mesh=None, camera=None, T_flange_camera=None, images: str = "simulated",
                 imu: str = "simulated", imu_host: str = "127.0.0.1", imu_port: int = 5005, imu_file: str | None = None,
                 dictionary: str = "DICT_4X4_50", marker_id: int = 7, marker_length_m: float = 0.04,
                 q_S_M: list | None = None, T_marker_bone: list | None = None, seed: int = 0,
                 ok_s: float = 0.5, lost_s: float = 2.0):
        from app.geometry import quaternion as quat
        from app.marker.aruco import MarkerDetector
        from app.marker.fusion import MarkerImuFusion

        if images != "simulated":
            raise ConfigError("tracker.params.images", f"got {images!r}; allowed: simulated")
        if imu not in ("simulated", "udp", "file"):
            raise ConfigError("tracker.params.imu", f"got {imu!r}; allowed: simulated, udp, file")
        if imu == "file" and not imu_file:
            raise ConfigError("tracker.params.imu_file", "required with imu: file (a CSV seq,sensor_stamp,qw,qx,qy,qz)")
        from app.marker.simulator import MarkerScenario, MarkerSimulator

        self.sim = MarkerSimulator(MarkerScenario(seconds=600.0, seed=seed, dictionary=dictionary,
                                                  marker_id=marker_id, marker_length_m=marker_length_m))
        self.rng = np.random.default_rng(seed)
        self.imu_mode = imu
        self.receiver = None
        self._file_samples = None
        if imu == "udp":
            from app.marker.imu import UdpReceiver

            self.receiver = UdpReceiver(imu_host, imu_port).start()
        elif imu == "file":
            from app.marker.imu import read_csv

            self._file_samples, counts = read_csv(imu_file)
            log.info("IMU file %s: %s", imu_file, counts)
        q = quat.from_matrix(self.sim.sc.R_S_M) if q_S_M is None else np.asarray(q_S_M, float)
        if q.shape != (4,) or abs(np.linalg.norm(q) - 1) > 1e-3:
            raise ConfigError("tracker.params.q_S_M", f"expected a unit quaternion (w, x, y, z), got {q_S_M!r}")
        self.fusion = MarkerImuFusion(MarkerDetector(self.sim.K, None, dictionary, marker_id, marker_length_m), q)
        self.T_marker_bone = np.eye(4) if T_marker_bone is None else np.asarray(T_marker_bone, float)
        self.ok_s, self.lost_s = ok_s, lost_s
        self._t0: float | None = None
        self._imu_index = 0
        self._last_found = -np.inf
        self._T_start = np.eye(4)

    def start(self, T_base_bone: np.ndarray) -> None:
        self._T_start = np.asarray(T_base_bone, float)

    def _feed_imu(self, t: float) -> None:
        if self.receiver is not None:
            for s in self.receiver.drain():
                self.fusion.on_imu(s.stamp, s.q_W_S)
            return
        if self._file_samples is not None:
            t_first = self._file_samples[0].stamp if self._file_samples else 0.0
            while self._imu_index < len(self._file_samples) and \
                    self._file_samples[self._imu_index].stamp - t_first <= t:
                s = self._file_samples[self._imu_index]
                self.fusion.on_imu(s.stamp - t_first, s.q_W_S)
                self._imu_index += 1
            return
        imu = self.sim.imu()
        while self._imu_index < len(imu["stamp"]) and imu["stamp"][self._imu_index] <= t:
            self.fusion.on_imu(imu["stamp"][self._imu_index], imu["q_W_S"][self._imu_index])
            self._imu_index += 1

    def process(self, depth_m: np.ndarray, stamp: float, T_base_camera: np.ndarray | None) -> MarkerImuResult:
        if self._t0 is None:
            self._t0 = stamp
        t = min(stamp - self._t0, self.sim.sc.seconds - 1.0)
        self._feed_imu(t)
        det, est = self.fusion.on_image(self.sim.image(t, self.rng), t)
        if det.found:
            self._last_found = t
        age = t - self._last_found
        status = "ok" if age <= self.ok_s else ("uncertain" if age <= self.lost_s else "lost")
        T_C_M = est.T_C_M
        if T_C_M is None:
            return MarkerImuResult(self._T_start, "lost", det.path, None, {"roi": det.roi})
        T_base_C = np.eye(4) if T_base_camera is None else np.asarray(T_base_camera, float)
        return MarkerImuResult(T_base_C @ T_C_M @ self.T_marker_bone, status, det.path, est.q_C_M,
                               {"roi": det.roi, "corners": det.corners, "counts": dict(self.fusion.counts)})

    def release(self) -> None:
        if self.receiver is not None:
            self.receiver.stop()
            self.receiver = None
