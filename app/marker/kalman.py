"""Error-state Kalman filter on the marker's orientation: the IMU predicts, the marker corrects.

Import as ``from app.marker.kalman import OrientationKalman``.

State: the marker orientation R = R_C_M in the camera frame (a unit quaternion q_C_M) and the
3x3 covariance P of its error rotation vector δ, defined on the right (in the marker frame):
R_true = R exp(δ).

**Prediction** (publication C: the IMU's orientation, mapped into the marker frame by the
calibration X = R_S_M). Between two IMU samples k-1, k the box turns by

    ΔS = R_W_S(k-1)^T R_W_S(k)          (in the sensor frame)
    ΔM = X^T ΔS X                       (the same motion in the marker frame)
    R ← R ΔM,     P ← ΔM^T P ΔM + Q Δt,  Q = σ_q² I  (rad²/s)

The IMU's world W, whose yaw drifts without a magnetometer, cancels from ΔS: only the drift
within one step enters, which σ_q covers. Chained increments telescope, so the prediction equals
the IMU orientation mapped into the camera frame through the last correction.

**Measurement** (the marker's IPPE orientation R_m, noise covariance R_n = diag(σ_m)², in the
marker frame: a planar pose fixes the rotation about the marker's normal z far better than its
tilts about x and y, so the default σ_m is (2°, 2°, 0.5°)):

    y = log(R^T R_m)                    innovation (rotation vector, marker frame), H = I
    S = P + R_n,  K = P S^{-1},  R ← R exp(K y),  P ← (I - K) P (I - K)^T + K R_n K^T

A measurement whose Mahalanobis distance y^T S^{-1} y exceeds ``gate`` (χ² with 3 degrees of
freedom; 16.27 is the 0.999 quantile) is rejected and counted (a planar pose flip, a wrong
detection); after ``max_rejections`` rejections in a row the filter re-initialises on the marker.
"""
from __future__ import annotations

import numpy as np

from app.geometry import quaternion as quat


class OrientationKalman:
    """One filter; ``q`` (w, x, y, z) is q_C_M, ``P`` (3, 3) rad²; ``None`` until initialised.

    sigma_process : σ_q, rad/√s (IMU increment noise and drift); sigma_measure : σ_m, rad, a scalar
    or (3,) per marker axis.
    """

    def __init__(self, sigma_process: float = np.deg2rad(0.5), sigma_measure=np.deg2rad([2.0, 2.0, 0.5]),
                 gate: float = 16.27, max_rejections: int = 10):
        self.sigma_process = sigma_process
        self.sigma_measure = np.broadcast_to(np.asarray(sigma_measure, float), (3,)).copy()
        self.gate = gate
        self.max_rejections = max_rejections
        self.q: np.ndarray | None = None
        self.P = np.diag(self.sigma_measure**2)
        self.rejected = 0
        self.resets = 0
        self._rejected_in_row = 0

    @property
    def initialised(self) -> bool:
        return self.q is not None

    def initialise(self, q_C_M: np.ndarray) -> None:
        self.q = quat.normalize(q_C_M)
        self.P = np.diag(self.sigma_measure**2)
        self._rejected_in_row = 0

    def predict(self, dq_M: np.ndarray, dt: float) -> None:
        """Turn by ΔM (quaternion of the increment in the marker frame) over dt seconds."""
        if self.q is None:
            return
        self.q = quat.normalize(quat.multiply(self.q, dq_M))
        D = quat.to_matrix(dq_M)
        self.P = D.T @ self.P @ D + np.eye(3) * (self.sigma_process**2 * max(dt, 0.0))

    def update(self, q_meas: np.ndarray, sigma=None) -> bool:
        """Correct with a marker orientation q_C_M (σ: this measurement's, else ``sigma_measure``);
        False when gated out. Initialises if needed."""
        if self.q is None:
            self.initialise(q_meas)
            return True
        Rn = np.diag(np.broadcast_to(self.sigma_measure if sigma is None else np.asarray(sigma, float), (3,)) ** 2)
        y = quat.log_map(quat.multiply(quat.conjugate(self.q), q_meas))
        S = self.P + Rn
        d2 = float(y @ np.linalg.solve(S, y))
        if d2 > self.gate:
            self.rejected += 1
            self._rejected_in_row += 1
            if self._rejected_in_row >= self.max_rejections:
                self.resets += 1
                self.initialise(q_meas)
                return True
            return False
        self._rejected_in_row = 0
        K = self.P @ np.linalg.inv(S)
        self.q = quat.normalize(quat.multiply(self.q, quat.exp_map(K @ y)))
        I_K = np.eye(3) - K
        self.P = I_K @ self.P @ I_K.T + K @ Rn @ K.T
        return True


def marker_increment(q_W_S_prev: np.ndarray, q_W_S: np.ndarray, q_S_M: np.ndarray) -> np.ndarray:
    """ΔM = X^T ΔS X as a quaternion: q_S_M^* ⊗ (q_W_S_prev^* ⊗ q_W_S) ⊗ q_S_M."""
    dS = quat.multiply(quat.conjugate(q_W_S_prev), q_W_S)
    return quat.multiply(quat.multiply(quat.conjugate(q_S_M), dS), q_S_M)
