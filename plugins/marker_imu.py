"""Publication C's marker + IMU tracker as a session plugin (``tracker: marker_imu``).

A thin adapter over :class:`app.marker.fusion.MarkerImuFusion`. The session loop is driven by the
depth camera's frames; this tracker takes each frame's stamp as its tick and reads its own inputs:

- images (``images``): ``ir`` reads each frame's infrared image from the session's camera (a
  RealSense with ``streams: depth,ir``, or ``camera: marker_simulated``, the simulator's camera),
  with the session camera's K (the infrared imager is the depth frame); ``color`` reads the colour
  image, with the colour camera's ``color_K`` (3x3) and ``color_distortion`` given in the params
  (the tracker is not told the colour stream's calibration); ``simulated`` renders
  :mod:`app.marker.simulator`'s marker image at the tick itself (the former behaviour);
- IMU (``imu``): ``simulated`` (the same simulator's drifting IMU), ``udp`` (the protocol of
  :mod:`app.marker.imu`, listening on ``imu_host``:``imu_port``, loopback by default) or ``file``
  (a CSV of :func:`app.marker.imu.read_csv`, replayed by time since the first tick).

The output pose is ``T_base_bone = T_base_camera T_C_M T_marker_bone`` (the camera's pose from the
robot; identity when the session has none). Status: ``ok`` with a marker detection within
``ok_s``, ``uncertain`` while only the IMU carries the orientation (up to ``lost_s``), else ``lost``.
The diagnostics carry the detection path ('roi' | 'full' | 'none').

**Angles**: the anterior pelvic plane is registered with the IMU (publication C) while the box sits
on the registration device, from 0.5 s to ``registration_s`` after the first tick (the IMU's
R_W_S X averaged; ``registration_s: 0`` turns it off), and carried into the camera frame by the
fusion's alignment (:meth:`app.marker.fusion.MarkerImuFusion.plane_in_camera`); from then on the
result carries ``inclination`` and ``anteversion`` (radians; None before) of the acetabular axis
``axis_M`` (in the marker frame; default the simulator's plan).

**Rerun** (``rerun``): 'auto' (default) logs to the active rerun recording if the process has one
(``rr.get_data_recording()``), a path logs to that ``.rrd`` file, 'off' not at all; see
:mod:`app.marker.rerun_log` (image, search region, corners, orientations, angles, path). Logging
never fails the session.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from app.errors import ConfigError
from app.geometry import quaternion
from app.interfaces import DepthFrame

log = logging.getLogger(__name__)


@dataclass
class MarkerImuResult:
    T_base_bone: np.ndarray
    status: str
    path: str
    q_C_M: np.ndarray | None
    diagnostics: dict = field(default_factory=dict)
    inclination: float | None = None     # radians, once the pelvic plane is registered
    anteversion: float | None = None


class MarkerImuTracker:
    kind, name = "tracker", "marker_imu"

    def __init__(self, mesh=None, camera=None, T_flange_camera=None, images: str = "simulated",
                 imu: str = "simulated", imu_host: str = "127.0.0.1", imu_port: int = 5005, imu_file: str | None = None,
                 dictionary: str = "DICT_4X4_50", marker_id: int = 7, marker_length_m: float = 0.04,
                 q_S_M: list | None = None, T_marker_bone: list | None = None, seed: int = 0,
                 ok_s: float = 0.5, lost_s: float = 2.0, registration_s: float | None = None,
                 axis_M: list | None = None, rerun="auto", rerun_image_every: int = 1,
                 color_K: list | None = None, color_distortion: list | None = None):
        from app.geometry import quaternion as quat
        from app.marker.aruco import MarkerDetector
        from app.marker.fusion import MarkerImuFusion

        if images not in ("ir", "color", "simulated"):
            raise ConfigError("tracker.params.images", f"got {images!r}; allowed: ir, color, simulated")
        if images == "ir" and camera is None:
            raise ConfigError("tracker.params.images", "images: ir needs the session camera's intrinsics")
        if images == "color" and color_K is None:
            raise ConfigError("tracker.params.color_K", "images: color needs the colour camera's 3x3 K "
                                                        "(its trial.yaml color.K or calibrate intrinsics)")
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
        self.images = images
        self.description = f"marker + IMU (images: {images}, imu: {imu})"
        self._latest: dict[str, np.ndarray | None] = {"ir": None, "color": None}
        K, dist = self.sim.K, None
        if images == "ir":
            K = np.asarray(camera.K, float)
        elif images == "color":
            K = np.asarray(color_K, float)
            dist = None if color_distortion is None else np.asarray(color_distortion, float)
        self.fusion = MarkerImuFusion(MarkerDetector(K, dist, dictionary, marker_id, marker_length_m), q)
        self.T_marker_bone = np.eye(4) if T_marker_bone is None else np.asarray(T_marker_bone, float)
        self.ok_s, self.lost_s = ok_s, lost_s
        self._t0: float | None = None
        self._imu_index = 0
        self._last_found = -np.inf
        self._T_start = np.eye(4)
        self.registration_s = self.sim.sc.registration_s if registration_s is None else float(registration_s)
        self.axis_M = self.sim.axis_M if axis_M is None else np.asarray(axis_M, float)
        if self.axis_M.shape != (3,) or np.linalg.norm(self.axis_M) < 1e-9:
            raise ConfigError("tracker.params.axis_M", f"expected a nonzero 3-vector, got {axis_M!r}")
        self._reg_samples: list[np.ndarray] = []
        self.R_W_P: np.ndarray | None = None
        self._frame = 0
        from app.marker.rerun_log import open_log

        # 'auto' is resolved in start(): the session opens its outputs (the rerun output makes its
        # recording the process's default) after creating the tracker and before starting it
        self._rerun_target, self._rerun_every = rerun, rerun_image_every
        self._rerun_auto = rerun is True or (isinstance(rerun, str) and rerun.lower() == "auto")
        self.rerun = None if self._rerun_auto else open_log(rerun, rerun_image_every)

    def start(self, T_base_bone: np.ndarray) -> None:
        if self._rerun_auto and self.rerun is None:
            from app.marker.rerun_log import open_log

            self.rerun = open_log(self._rerun_target, self._rerun_every)
        self._T_start = np.asarray(T_base_bone, float)

    def _image(self, t: float) -> np.ndarray | None:
        if self.images == "simulated":
            return self.sim.image(t, self.rng)
        image = self._latest.get(self.images)
        if image is not None and image.ndim == 3:
            import cv2

            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        return image

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

    def process(self, frame: DepthFrame, T_base_camera: np.ndarray | None) -> MarkerImuResult:
        """One tick at the frame's stamp, reading the frame's infrared / colour image (``images``)."""
        stamp = frame.stamp
        self._latest = {"ir": frame.infrared, "color": frame.color}
        if self._t0 is None:
            self._t0 = stamp
        t = min(stamp - self._t0, self.sim.sc.seconds - 1.0)
        self._feed_imu(t)
        self._register(t)
        gray = self._image(t)
        if gray is None:   # the camera delivers no such image: say so once, report lost
            if self._frame == 0:
                log.warning("tracker.params.images is %r but the camera's frames carry no %s image: enable that "
                            "stream on the camera (e.g. streams: depth,ir)", self.images, self.images)
            self._frame += 1
            return MarkerImuResult(self._T_start, "lost", "none", None, {"reason": f"no {self.images} image"})
        det, est = self.fusion.on_image(gray, t)
        if det.found:
            self._last_found = t
        age = t - self._last_found
        status = "ok" if age <= self.ok_s else ("uncertain" if age <= self.lost_s else "lost")
        inclination = anteversion = None
        R_C_P = None if (self.R_W_P is None or est.q_C_M is None) else self.fusion.plane_in_camera(self.R_W_P)
        if R_C_P is not None:
            from app.marker.pelvic_plane import fragment_angles

            inc, ant = fragment_angles(R_C_P, quaternion.to_matrix(est.q_C_M), self.axis_M)
            inclination, anteversion = float(inc), float(ant)
        if self.rerun is not None:
            self.rerun.log_step(stamp, gray, det.path, det.roi, det.corners, est.q_C_M, det.q_C_M,
                                self.fusion.imu_marker_orientation(), inclination, anteversion, self._frame)
        self._frame += 1
        T_C_M = est.T_C_M
        if T_C_M is None:
            return MarkerImuResult(self._T_start, "lost", det.path, None, {"roi": det.roi})
        T_base_C = np.eye(4) if T_base_camera is None else np.asarray(T_base_camera, float)
        return MarkerImuResult(T_base_C @ T_C_M @ self.T_marker_bone, status, det.path, est.q_C_M,
                               {"roi": det.roi, "corners": det.corners, "counts": dict(self.fusion.counts),
                                "inclination": inclination, "anteversion": anteversion},
                               inclination, anteversion)

    def _register(self, t: float) -> None:
        """Collect the IMU's marker orientation on the registration device; register the APP after."""
        if self.R_W_P is not None or self.registration_s <= 0:
            return
        if t < self.registration_s:
            R = self.fusion.imu_marker_orientation()
            if t >= min(0.5, 0.25 * self.registration_s) and R is not None:
                self._reg_samples.append(R)
        elif self._reg_samples:
            from app.marker.pelvic_plane import register_pelvic_plane

            self.R_W_P = register_pelvic_plane(np.asarray(self._reg_samples))
            log.info("pelvic plane registered with the IMU from %d samples", len(self._reg_samples))

    def particle_positions(self) -> np.ndarray:
        """No particles: the start pose's origin (the log draws it)."""
        return np.asarray(self._T_start, float)[None, :3, 3]

    def mean_timings_ms(self) -> dict[str, float]:
        return {}

    def release(self) -> None:
        if self.rerun is not None:
            self.rerun.close()
            self.rerun = None
        if self.receiver is not None:
            self.receiver.stop()
            self.receiver = None

