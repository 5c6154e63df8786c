"""ArUco marker detection and pose (publication C, Fig. 6): the predicted region first, the whole
image as the fallback.

Import as ``from app.marker.aruco import MarkerDetector``.

OpenCV 4.14's API: ``cv2.aruco.getPredefinedDictionary``, ``cv2.aruco.ArucoDetector(dictionary,
DetectorParameters)``. The pose is OpenCV's planar square solver (``cv2.solvePnPGeneric`` with
``SOLVEPNP_IPPE_SQUARE``), which returns the two solutions of the planar ambiguity; the one closest
to a predicted orientation is kept when a prediction is given (the IMU's), else the one with the
smaller reprojection error.

Marker frame M (OpenCV's convention for IPPE_SQUARE): origin at the marker's centre, x right, y up,
z out of the printed face; corners in OpenCV's order (top-left, top-right, bottom-right,
bottom-left) at (∓L/2, ±L/2, 0). The solver's rvec/tvec is T_C_M.

Search order (:meth:`MarkerDetector.detect`):

1. ``roi``: the region where the prediction projects the marker, enlarged by a margin, cropped and
   searched with adaptive thresholding whose window matches the expected marker size in pixels;
2. ``full``: the whole image with OpenCV's default adaptive-threshold windows (3 to 23 px), when there is no
   region or the marker was not found in it;
3. ``none``: not found. The result says which path found it.

Both searches refine the corners to sub-pixel accuracy (``CORNER_REFINE_SUBPIX``).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from app.geometry import quaternion as quat

log = logging.getLogger(__name__)

PATHS = ("roi", "full", "none")


def dictionary(name: str):
    """``cv2.aruco.getPredefinedDictionary`` by name (e.g. 'DICT_4X4_50'); unknown names list the valid ones."""
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        valid = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise ValueError(f"unknown ArUco dictionary {name!r}; valid: {', '.join(valid)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def marker_points(length_m: float) -> np.ndarray:
    """(4, 3) float64 corners in the marker frame, OpenCV's order, metres."""
    h = 0.5 * length_m
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass
class Detection:
    """One detection attempt.

    path : 'roi' | 'full' | 'none' (which search found the marker)
    corners : (4, 2) float pixel corners or None; T_C_M : (4, 4) marker pose in the camera or None
    q_C_M : (4,) its orientation (w, x, y, z) or None; reprojection_px : RMS error of the kept solution
    roi : (x0, y0, x1, y1) the searched region or None; seconds : time spent
    """

    path: str
    corners: np.ndarray | None = None
    T_C_M: np.ndarray | None = None
    q_C_M: np.ndarray | None = None
    reprojection_px: float | None = None
    roi: tuple[int, int, int, int] | None = None
    seconds: float = 0.0

    @property
    def found(self) -> bool:
        return self.path != "none"


class MarkerDetector:
    """Detects one marker id and solves its pose.

    K : (3, 3) intrinsics; dist : distortion coefficients (OpenCV order) or None;
    dictionary_name, marker_id, length_m : the printed marker (side of the black square, metres).
    """

    def __init__(self, K: np.ndarray, dist: np.ndarray | None = None, dictionary_name: str = "DICT_4X4_50",
                 marker_id: int = 0, length_m: float = 0.04, roi_margin: float = 0.6):
        self.K = np.asarray(K, float)
        self.dist = np.zeros(5) if dist is None else np.asarray(dist, float)
        self.dictionary = dictionary(dictionary_name)
        self.marker_id = int(marker_id)
        self.length_m = float(length_m)
        self.roi_margin = roi_margin
        self.object_points = marker_points(length_m)
        self._full = cv2.aruco.ArucoDetector(self.dictionary, self._parameters())

    def _parameters(self):
        """OpenCV's defaults, with sub-pixel corner refinement (without it the corners are the
        contour polygon's integer vertices, and the pose of a still marker is off by a fixed ~1-2°)."""
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        return params

    def _roi_detector(self, side_px: float):
        """Adaptive thresholding with one window matched to the expected marker side (odd, >= 3)."""
        params = self._parameters()
        win = int(np.clip(side_px / 3.0, 3, 51)) | 1
        params.adaptiveThreshWinSizeMin = win
        params.adaptiveThreshWinSizeMax = win
        params.adaptiveThreshWinSizeStep = 10
        return cv2.aruco.ArucoDetector(self.dictionary, params)

    def predicted_roi(self, T_C_M: np.ndarray, shape: tuple[int, int]) -> tuple[tuple[int, int, int, int], float] | None:
        """The image region (x0, y0, x1, y1) where a predicted pose puts the marker, and its side in
        pixels; None when it is behind the camera or outside the image."""
        p = T_C_M[:3, :3] @ self.object_points.T + T_C_M[:3, 3:4]
        if np.any(p[2] <= 1e-3):
            return None
        uv, _ = cv2.projectPoints(self.object_points, cv2.Rodrigues(T_C_M[:3, :3])[0], T_C_M[:3, 3], self.K, self.dist)
        uv = uv.reshape(4, 2)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        side = float(max(hi - lo))
        pad = self.roi_margin * side + 8.0
        h, w = shape[:2]
        x0, y0 = int(max(lo[0] - pad, 0)), int(max(lo[1] - pad, 0))
        x1, y1 = int(min(hi[0] + pad, w)), int(min(hi[1] + pad, h))
        if x1 - x0 < 8 or y1 - y0 < 8:
            return None
        return (x0, y0, x1, y1), side

    def _find(self, detector, gray: np.ndarray) -> np.ndarray | None:
        corners, ids, _ = detector.detectMarkers(gray)
        if ids is None:
            return None
        for c, i in zip(corners, ids.ravel()):
            if int(i) == self.marker_id:
                return c.reshape(4, 2).astype(np.float64)
        return None

    def solve_pose(self, corners: np.ndarray, q_pred: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """T_C_M (4, 4) and RMS reprojection error (px) by IPPE_SQUARE; the ambiguity resolved by
        ``q_pred`` (w, x, y, z) when given, else by the reprojection error."""
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(self.object_points, corners, self.K, self.dist,
                                                    flags=cv2.SOLVEPNP_IPPE_SQUARE)
        errs = np.asarray(errs).ravel()
        best = int(np.argmin(errs))
        if q_pred is not None and n > 1:
            angles = [float(quat.angle_between(quat.from_matrix(cv2.Rodrigues(r)[0]), q_pred)) for r in rvecs]
            best = int(np.argmin(angles))
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvecs[best])[0]
        T[:3, 3] = np.asarray(tvecs[best]).ravel()
        return T, float(errs[best])

    def detect(self, gray: np.ndarray, T_C_M_pred: np.ndarray | None = None, use_prediction_for_pose: bool = True,
               clock=None) -> Detection:
        """Find the marker: the predicted region first (when ``T_C_M_pred`` is given), then the whole image.

        gray : (H, W) uint8 image. T_C_M_pred : (4, 4) predicted marker pose (IMU orientation and
        the last position) or None. ``use_prediction_for_pose`` also resolves IPPE's ambiguity with it.
        """
        import time

        clock = clock or time.perf_counter
        t0 = clock()
        roi = None
        corners = None
        path = "none"
        if T_C_M_pred is not None:
            found = self.predicted_roi(T_C_M_pred, gray.shape)
            if found is not None:
                roi, side = found
                x0, y0, x1, y1 = roi
                c = self._find(self._roi_detector(side), np.ascontiguousarray(gray[y0:y1, x0:x1]))
                if c is not None:
                    corners, path = c + np.array([x0, y0], float), "roi"
        if corners is None:
            corners = self._find(self._full, gray)
            path = "full" if corners is not None else "none"
        if corners is None:
            return Detection("none", roi=roi, seconds=clock() - t0)
        q_pred = quat.from_matrix(T_C_M_pred[:3, :3]) if (T_C_M_pred is not None and use_prediction_for_pose) else None
        T, err = self.solve_pose(corners, q_pred)
        return Detection(path, corners, T, quat.from_matrix(T[:3, :3]), err, roi, clock() - t0)
