"""The marker + IMU tracker: IMU samples and camera images, in stamp order, to marker orientations.

Import as ``from app.marker.fusion import MarkerImuFusion``.

Per IMU sample (about 100 Hz): the Kalman prediction (:mod:`app.marker.kalman`) with the increment
since the previous sample, mapped into the marker frame by the calibration X = R_S_M; the output
(an orientation at the IMU's rate).

Per camera image (8-30 Hz): the predicted pose (the filter's orientation, the last measured
position; the IMU gives no position) gives the image region to search first (:mod:`app.marker.aruco`),
the whole image is the fallback; the detection resolves IPPE's planar ambiguity with the predicted
orientation, and its orientation is the Kalman measurement. An image is applied to the state of the
latest IMU sample at or before its stamp (a lag of at most one IMU period). Without a detection for
``roi_timeout_s`` the prediction is not trusted for the region (the marker may have moved: the IMU
knows nothing of translation), and the whole image is searched.

Before the first detection there is no camera-frame orientation: the outputs are None.

**The pelvic plane with the IMU** (publication C): the APP is registered in the IMU's world W,
``R_W_P = R_W_S X R_M_P`` while the box sits on the registration device
(:func:`app.marker.pelvic_plane.register_pelvic_plane` on :meth:`MarkerImuFusion.imu_marker_orientation`),
not from the marker's pose there (one static pose: its pose-dependent IPPE bias, 1.5-2°, would
enter every angle). The tracker carries the plane into the camera frame with the alignment
``R_W_C`` it keeps from its own corrections: at each image, ``R_W_M^imu (R_C_M^fused)^T`` is one
sample of R_W_C, and the estimate is their chordal mean over all images so far (the rotation
nearest to their sum: the marker's pose-dependent bias averages out over the fragment's poses; the
IMU's slow yaw drift enters as its mean). The angles then use ``R_C_P = R_W_C^T R_W_P`` and the
fused ``R_C_M`` (:meth:`MarkerImuFusion.plane_in_camera`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.geometry import quaternion as quat
from app.marker.aruco import Detection, MarkerDetector
from app.marker.kalman import OrientationKalman, marker_increment


@dataclass
class FusedEstimate:
    """stamp : s; q_C_M : (4,) (w, x, y, z) or None; t_C_M : (3,) last measured position or None;
    source : 'imu' (a prediction) or 'marker' (after a correction)."""

    stamp: float
    q_C_M: np.ndarray | None
    t_C_M: np.ndarray | None
    source: str

    @property
    def T_C_M(self) -> np.ndarray | None:
        if self.q_C_M is None or self.t_C_M is None:
            return None
        T = np.eye(4)
        T[:3, :3] = quat.to_matrix(self.q_C_M)
        T[:3, 3] = self.t_C_M
        return T


class MarkerImuFusion:
    """The stepper: call :meth:`on_imu` and :meth:`on_image` in stamp order.

    detector : the marker detector; q_S_M : (4,) the IMU-to-marker calibration X (w, x, y, z);
    kalman : the filter (a default one if None); roi_timeout_s : see the module docstring.
    """

    def __init__(self, detector: MarkerDetector, q_S_M: np.ndarray, kalman: OrientationKalman | None = None,
                 roi_timeout_s: float = 0.5):
        self.detector = detector
        self.q_S_M = quat.normalize(q_S_M)
        self.kalman = kalman or OrientationKalman()
        self.roi_timeout_s = roi_timeout_s
        self.t_C_M: np.ndarray | None = None
        self._q_W_S_prev: np.ndarray | None = None
        self._t_imu_prev: float | None = None
        self._last_detection_stamp = -np.inf
        self._align_sum = np.zeros((3, 3))
        self._align_n = 0
        self.counts = {"imu": 0, "images": 0, "roi": 0, "full": 0, "none": 0, "gated": 0}

    def on_imu(self, stamp: float, q_W_S: np.ndarray) -> FusedEstimate:
        """Predict with one IMU sample (q_W_S (4,) in the IMU's world)."""
        self.counts["imu"] += 1
        if self._q_W_S_prev is not None:
            self.kalman.predict(marker_increment(self._q_W_S_prev, q_W_S, self.q_S_M), stamp - self._t_imu_prev)
        self._q_W_S_prev, self._t_imu_prev = np.asarray(q_W_S, float), stamp
        return FusedEstimate(stamp, None if self.kalman.q is None else self.kalman.q.copy(), self.t_C_M, "imu")

    def predicted_pose(self, stamp: float) -> np.ndarray | None:
        """T_C_M (4, 4) to search around, or None (no orientation yet, or no recent detection)."""
        if self.kalman.q is None or self.t_C_M is None or stamp - self._last_detection_stamp > self.roi_timeout_s:
            return None
        T = np.eye(4)
        T[:3, :3] = quat.to_matrix(self.kalman.q)
        T[:3, 3] = self.t_C_M
        return T

    def on_image(self, gray: np.ndarray, stamp: float) -> tuple[Detection, FusedEstimate]:
        """Detect the marker (predicted region first) and correct the filter with it."""
        self.counts["images"] += 1
        det = self.detector.detect(gray, self.predicted_pose(stamp))
        self.counts[det.path] += 1
        if det.found:
            self._last_detection_stamp = stamp
            self.t_C_M = det.T_C_M[:3, 3].copy()
            if not self.kalman.update(det.q_C_M):
                self.counts["gated"] += 1
            if self._q_W_S_prev is not None and self.kalman.q is not None:
                self._align_sum += self.imu_marker_orientation() @ quat.to_matrix(self.kalman.q).T
                self._align_n += 1
        return det, FusedEstimate(stamp, None if self.kalman.q is None else self.kalman.q.copy(), self.t_C_M, "marker")


    def imu_marker_orientation(self) -> np.ndarray | None:
        """R_W_M = R_W_S X (3, 3) of the latest IMU sample (the IMU's world W), or None before one."""
        if self._q_W_S_prev is None:
            return None
        return quat.to_matrix(self._q_W_S_prev) @ quat.to_matrix(self.q_S_M)

    def camera_in_imu_world(self) -> np.ndarray | None:
        """R_W_C (3, 3): the chordal mean of the per-image alignments (module docstring), or None."""
        if self._align_n == 0:
            return None
        U, _, Vt = np.linalg.svd(self._align_sum)
        return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt

    def plane_in_camera(self, R_W_P: np.ndarray) -> np.ndarray | None:
        """R_C_P = R_W_C^T R_W_P (3, 3): an APP registered in the IMU's world, in the camera frame."""
        R_W_C = self.camera_in_imu_world()
        return None if R_W_C is None else R_W_C.T @ np.asarray(R_W_P, float)


def slerp_at(stamps: np.ndarray, q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Orientations (len(t), 4) interpolated (slerp) at times t from samples q (N, 4) at stamps (N,)
    (increasing); times outside take the nearest end."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.clip(np.asarray(t, float), stamps[0], stamps[-1])
    r = Slerp(stamps, Rotation.from_quat(quat.to_xyzw(q)))(t)
    return quat.from_xyzw(r.as_quat())
