"""A simulated augmented-marker session: a marker box on a moving acetabular fragment, seen by a
camera, with a noisy, drifting IMU inside the box.

Import as ``from app.marker.simulator import MarkerScenario, MarkerSimulator``.

The scene (camera frame C, OpenCV; the camera and the pelvis stay still):

- the anterior pelvic plane P is fixed in C (``R_C_P``), seen from above and obliquely;
- ``motion='pao'``: for ``registration_s`` the box sits on the registration device, its marker
  face parallel to the APP (R_M_P = I); it is then carried to the fragment within ``transfer_s``
  (smoothstep); then the fragment turns about the acetabulum's centre (sums of sinusoids, about
  ``amplitude_deg`` per axis, up to ~15-20 °/s), as a surgeon reorients it;
- ``motion='calibration'``: the box is turned by hand in front of the camera (larger rotations
  about all three axes) for the IMU-to-marker calibration.

The images (:meth:`MarkerSimulator.image`): ``cv2.aruco.generateImageMarker`` on a white quiet
zone, warped by the homography of the marker plane into a textured background, then lighting
(a global gain and a moving gradient, with dim spells), motion blur along the marker's image
motion during the exposure, and sensor noise; uint8.

The IMU (:meth:`MarkerSimulator.imu`): R_W_S = R_W_C R_C_M X^T with X = R_S_M the box's fixed
IMU-to-marker rotation and W gravity-aligned (z up); measured with white orientation noise and a
yaw drift about W's z (a constant rate plus a random walk: no magnetometer). Sensor stamps run on
their own clock (``sensor_clock_offset_s`` ahead of the simulation's).

All randomness comes from the scenario's seed (``np.random.default_rng``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from app.marker import pelvic_plane as app_plane
from app.marker.aruco import dictionary


def _rot(rotvec_deg) -> np.ndarray:
    return Rotation.from_rotvec(np.deg2rad(rotvec_deg)).as_matrix()


R_FACE = np.diag([1.0, -1.0, -1.0])  # marker facing the camera, upright: x_M = x_C, y_M = -y_C, z_M = -z_C


@dataclass
class MarkerScenario:
    """Parameters of one simulated sequence (SI units, angles in degrees where the name says so)."""

    seconds: float = 30.0
    motion: str = "pao"                       # 'pao' | 'calibration'
    seed: int = 0
    width: int = 640
    height: int = 480
    focal_px: float = 600.0
    camera_fps: float = 10.0                  # publication C: 8-12 Hz marker updates
    imu_rate_hz: float = 100.0
    dictionary: str = "DICT_4X4_50"
    marker_id: int = 7
    marker_length_m: float = 0.04
    registration_s: float = 2.0
    transfer_s: float = 1.0
    amplitude_deg: float = 8.0
    imu_noise_deg: float = 0.15               # white, per axis, per sample
    yaw_drift_deg_s: float = 0.05             # 3 °/min
    yaw_walk_deg_sqrt_s: float = 0.02
    exposure_s: float = 0.02                  # motion blur
    pixel_noise: float = 3.0                  # grey levels
    lighting: bool = True
    sensor_clock_offset_s: float = 1000.0
    R_S_M: np.ndarray = field(default_factory=lambda: _rot([25.0, -70.0, 40.0]))
    initial_inclination_deg: float = 50.0      # dysplastic hip before the reorientation
    initial_anteversion_deg: float = 8.0


class MarkerSimulator:
    """Ground truth, IMU samples and camera images of one :class:`MarkerScenario`."""

    def __init__(self, scenario: MarkerScenario):
        if scenario.motion not in ("pao", "calibration"):
            raise ValueError(f"motion must be 'pao' or 'calibration', got {scenario.motion!r}")
        self.sc = sc = scenario
        rng = np.random.default_rng(sc.seed)
        self.K = np.array([[sc.focal_px, 0, (sc.width - 1) / 2], [0, sc.focal_px, (sc.height - 1) / 2], [0, 0, 1.0]])
        self.R_C_P = _rot([20.0, 0, 0]) @ _rot([0, -25.0, 0]) @ R_FACE
        self.R_W_C = _rot([0, 0, rng.uniform(-180, 180)]) @ _rot([-120.0, 0, 0])
        self.t_reg = np.array([0.0, 0.0, 0.45])
        self.pivot = np.array([0.03, 0.02, 0.50])
        self.R_C_M_frag = _rot([0, 15.0, 0]) @ _rot([-10.0, 0, 0]) @ R_FACE
        self.t_frag = self.pivot + np.array([-0.04, -0.03, -0.03])
        self.axis_M = app_plane.axis_in_marker(self.R_C_P, self.R_C_M_frag, np.deg2rad(sc.initial_inclination_deg),
                                               np.deg2rad(sc.initial_anteversion_deg), "right")
        self._freq = rng.uniform(0.06, 0.2, 3)
        self._phase = rng.uniform(0, 2 * np.pi, 3)
        self._freq2 = rng.uniform(0.2, 0.45, 3)
        self._phase2 = rng.uniform(0, 2 * np.pi, 3)
        self._rng_seed = int(rng.integers(2**31))
        self._imu = None
        self._background = self._make_background(rng)
        self._marker_canvas, self._canvas_pts = self._make_marker()
        self._dim = np.sort(rng.uniform(0, sc.seconds, 2))

    # ---- ground truth ------------------------------------------------------------------------
    @property
    def fragment_start(self) -> float:
        return 0.0 if self.sc.motion == "calibration" else self.sc.registration_s + self.sc.transfer_s

    def _fragment_rotvec(self, t: np.ndarray) -> np.ndarray:
        sc = self.sc
        tau = np.maximum(t - self.fragment_start, 0.0)[:, None]
        if sc.motion == "calibration":
            amp = np.deg2rad([35.0, 35.0, 30.0])
            return amp * np.sin(2 * np.pi * self._freq2 * tau + self._phase2) - amp * np.sin(self._phase2)
        ramp = np.minimum(tau / 2.0, 1.0)
        amp = np.deg2rad(sc.amplitude_deg)
        return ramp * amp * (np.sin(2 * np.pi * self._freq * tau + self._phase) - np.sin(self._phase))

    def pose(self, t) -> tuple[np.ndarray, np.ndarray]:
        """True R_C_M (N, 3, 3) and t_C_M (N, 3) at times t (N,) s."""
        t = np.atleast_1d(np.asarray(t, float))
        R_mot = Rotation.from_rotvec(self._fragment_rotvec(t)).as_matrix()
        R = R_mot @ self.R_C_M_frag
        p = self.pivot + np.einsum("nij,j->ni", R_mot, self.t_frag - self.pivot)
        if self.sc.motion == "pao":
            R_reg = self.R_C_P  # R_M_P = I on the device
            s = np.clip((t - self.sc.registration_s) / self.sc.transfer_s, 0.0, 1.0)
            s = s * s * (3 - 2 * s)
            rv = Rotation.from_matrix(self.R_C_M_frag @ R_reg.T).as_rotvec()
            R_tr = Rotation.from_rotvec(s[:, None] * rv).as_matrix() @ R_reg
            before = t < self.fragment_start
            R[before] = R_tr[before]
            p[before] = self.t_reg + s[before, None] * (self.t_frag - self.t_reg)
        return R, p

    def angles(self, t) -> tuple[np.ndarray, np.ndarray]:
        """True (inclination, anteversion) of the fragment, radians, at times t."""
        R, _ = self.pose(t)
        return app_plane.fragment_angles(self.R_C_P, R, self.axis_M)

    # ---- IMU ---------------------------------------------------------------------------------
    def imu(self) -> dict:
        """IMU samples of the whole sequence: 'stamp' (N,) s (simulation clock), 'sensor_stamp' (N,),
        'seq' (N,), 'q_W_S' (N, 4) measured, 'q_W_S_true' (N, 4), 'yaw_drift' (N,) rad."""
        if self._imu is None:
            sc = self.sc
            rng = np.random.default_rng(self._rng_seed)
            t = np.arange(0.0, sc.seconds, 1.0 / sc.imu_rate_hz)
            R_C_M, _ = self.pose(t)
            R_W_S = self.R_W_C @ R_C_M @ sc.R_S_M.T
            dt = 1.0 / sc.imu_rate_hz
            walk = np.cumsum(rng.normal(0, np.deg2rad(sc.yaw_walk_deg_sqrt_s) * np.sqrt(dt), len(t)))
            yaw = np.deg2rad(sc.yaw_drift_deg_s) * t * rng.choice([-1.0, 1.0]) + walk
            R_yaw = Rotation.from_rotvec(np.outer(yaw, [0, 0, 1.0]))
            noise = Rotation.from_rotvec(rng.normal(0, np.deg2rad(sc.imu_noise_deg), (len(t), 3)))
            meas = R_yaw * Rotation.from_matrix(R_W_S) * noise
            wxyz = lambda r: np.roll(r.as_quat(canonical=False), 1, axis=1)  # noqa: E731 scipy is xyzw
            self._imu = {"stamp": t, "sensor_stamp": t + sc.sensor_clock_offset_s, "seq": np.arange(len(t)),
                         "q_W_S": wxyz(meas), "q_W_S_true": wxyz(Rotation.from_matrix(R_W_S)), "yaw_drift": yaw}
        return self._imu

    # ---- camera ------------------------------------------------------------------------------
    def frame_stamps(self) -> np.ndarray:
        return np.arange(0.0, self.sc.seconds, 1.0 / self.sc.camera_fps) + 0.5 / self.sc.imu_rate_hz

    def _make_background(self, rng) -> np.ndarray:
        sc = self.sc
        noise = rng.normal(0, 1, (sc.height // 8, sc.width // 8)).astype(np.float32)
        bg = cv2.resize(cv2.GaussianBlur(noise, (0, 0), 2.0), (sc.width, sc.height), interpolation=cv2.INTER_CUBIC)
        bg = 120 + 35 * bg / (np.abs(bg).max() + 1e-6)
        return bg.astype(np.float32)

    def _make_marker(self) -> tuple[np.ndarray, np.ndarray]:
        sc = self.sc
        side = 120
        quiet = 30
        img = cv2.aruco.generateImageMarker(dictionary(sc.dictionary), sc.marker_id, side, borderBits=1)
        canvas = np.full((side + 2 * quiet, side + 2 * quiet), 235, np.uint8)
        canvas[quiet:quiet + side, quiet:quiet + side] = np.where(img > 127, 235, 25)
        n = side + 2 * quiet
        px = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32) - 0.5
        h = 0.5 * sc.marker_length_m * n / side
        pts = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
        return canvas.astype(np.float32), (px, pts)

    def _project(self, R: np.ndarray, p: np.ndarray, pts: np.ndarray) -> np.ndarray:
        c = pts @ R.T + p
        uv = c @ self.K.T
        return uv[:, :2] / uv[:, 2:3]

    def image(self, t: float, rng: np.random.Generator) -> np.ndarray:
        """The camera image at time t, (H, W) uint8 (its blur, lighting and noise drawn from rng)."""
        sc = self.sc
        (R,), (p,) = self.pose([t])
        px, pts = self._canvas_pts
        uv = self._project(R, p, pts).astype(np.float32)
        H = cv2.getPerspectiveTransform(px, uv)
        size = (sc.width, sc.height)
        warped = cv2.warpPerspective(self._marker_canvas, H, size, flags=cv2.INTER_AREA)
        mask = cv2.warpPerspective(np.ones_like(self._marker_canvas), H, size, flags=cv2.INTER_LINEAR)
        img = self._background * (1 - mask) + warped * mask
        if sc.exposure_s > 0:
            (Ra, Rb), (pa, pb) = self.pose([t - sc.exposure_s / 2, t + sc.exposure_s / 2])
            centre = np.zeros((1, 3))
            d = self._project(Rb, pb, centre)[0] - self._project(Ra, pa, centre)[0]
            length = float(np.hypot(*d))
            if length > 1.0:
                k = int(np.ceil(length)) | 1
                kernel = np.zeros((k, k), np.float32)
                c = k // 2
                for s in np.linspace(-0.5, 0.5, 2 * k):
                    kernel[int(round(c + s * d[1])), int(round(c + s * d[0]))] = 1.0
                img = cv2.filter2D(img, -1, kernel / kernel.sum())
        if sc.lighting:
            gain = 1.0 + 0.3 * np.sin(2 * np.pi * t / 7.0)
            if np.any(np.abs(t - self._dim) < 0.6):
                gain *= 0.35                            # a dim spell (a shadow, the lamp turned)
            x = np.linspace(-1, 1, sc.width, dtype=np.float32)
            gradient = 1.0 + 0.25 * np.sin(np.pi * x + t)[None, :]
            img = img * (gain * gradient)
        img = img + rng.normal(0, sc.pixel_noise, img.shape).astype(np.float32)
        return np.clip(img, 0, 255).astype(np.uint8)
