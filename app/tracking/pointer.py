"""A pointer tool's tip as the start's point (issue 33, item 3): the session's ``bone.pointer``.

Import as ``from app.tracking.pointer import PointerTip``; a :class:`app.tracking.start.PointSource`.
The tool carries an ArUco marker (``marker_id``, ``marker_length_m``, ``dictionary``), seen by the
depth camera's infrared imager (the depth frame itself: same K, no extrinsics) or by its colour
camera (its own K, distortion and ``T_depth_color``; app/image_streams.py). The marker's pose comes
from app/marker/aruco.py (OpenCV's detector, IPPE_SQUARE): the marker frame M has its origin at the
printed square's centre, x right, y up, z out of the face. The tip is at ``tip_offset_m`` in M,
measured once on the tool. Per frame::

    p_base = T_base_camera · T_depth_image · T_image_M · (tip_M, 1)

with ``T_depth_image`` the identity for the infrared stream and ``T_depth_color`` for colour.

A tool moving into place is not a point on the bone: the tip counts once it has stayed within
HOLD_M of where it was first seen for HOLD_S of frame stamps (data time, never the wall clock), and
the point is the mean of those tips. The start (app/tracking/start.py) keeps the first such point.

The session gives each frame's images to :meth:`PointerTip.observe` before the tracker processes the
frame (app/session/loop.py); the start then asks :meth:`PointerTip.locate` on that frame.

Limits: IPPE's planar ambiguity is resolved by the reprojection error alone (no orientation is
predicted), so a small marker seen face-on can flip; an orientation error θ moves the tip by about
|tip_offset| θ (10 cm at 3 deg: 5 mm, inside the detector's 2 cm point radius; a flip is more). With
the RealSense's emitter on, the infrared image carries its dot pattern: use ``stream: color``, or
the emitter off (``camera.params.emitter: false``).
"""
from __future__ import annotations

import cv2
import numpy as np

HOLD_S = 0.3      # the tip held this long (frame stamps) ...
HOLD_M = 0.002    # ... within this of where it was first seen counts as pointed


class PointerTip:
    """The tip of a pointer tool with an ArUco marker (module docstring).

    Parameters
    ----------
    marker_id, marker_length_m, dictionary : the printed marker (side of the black square, metres)
    tip_offset_m : (3,) the tip in the marker frame M, metres
    camera : the PinholeCamera of the images searched (the depth camera's for infrared)
    stream : 'ir' (DepthFrame.infrared) or 'color' (DepthFrame.color, RGB)
    distortion : (5,) of that camera (OpenCV order), zeros for infrared
    T_depth_image : (4, 4) the image's optical frame in the depth optical frame (identity for infrared)
    """

    def __init__(self, marker_id: int, marker_length_m: float, tip_offset_m, camera, stream: str = "ir",
                 dictionary: str = "DICT_4X4_50", distortion=None, T_depth_image=None):
        from app.marker.aruco import MarkerDetector

        if stream not in ("ir", "color"):
            raise ValueError(f"a pointer is seen in the 'ir' or the 'color' stream, got {stream!r}")
        self.detector = MarkerDetector(camera.K, distortion, dictionary, marker_id, marker_length_m)
        self.tip_M = np.append(np.asarray(tip_offset_m, float).reshape(3), 1.0)
        self.stream = stream
        self.T_depth_image = np.eye(4) if T_depth_image is None else np.asarray(T_depth_image, float)
        self.description = f"pointer (marker {int(marker_id)})"
        self._gray: np.ndarray | None = None
        self._stamp = 0.0
        self._held: list[np.ndarray] = []
        self._held_since = 0.0

    def observe(self, frame) -> None:
        """This frame's image of the stream (a :class:`app.interfaces.DepthFrame`), for :meth:`locate`."""
        image = frame.infrared if self.stream == "ir" else frame.color
        if image is not None and image.ndim == 3:
            image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
        self._gray, self._stamp = image, float(frame.stamp)

    def tip(self, T_base_camera: np.ndarray) -> np.ndarray | None:
        """The tip in the base frame (3,) on the observed image, or None when the marker is not found."""
        if self._gray is None:
            return None
        found = self.detector.detect(self._gray)
        if not found.found:
            return None
        return (np.asarray(T_base_camera, float) @ self.T_depth_image @ found.T_C_M @ self.tip_M)[:3]

    def locate(self, depth_m: np.ndarray, T_base_camera: np.ndarray) -> tuple[np.ndarray | None, str]:
        """The held tip (3,) in the base frame and '', or None and why (module docstring)."""
        if self._gray is None:
            return None, f"no {self.stream} image on this frame for the {self.description}"
        tip = self.tip(T_base_camera)
        if tip is None:
            self._held = []
            return None, f"the {self.description} is not seen"
        if not self._held or np.linalg.norm(tip - self._held[0]) > HOLD_M:
            self._held, self._held_since = [tip], self._stamp
        else:
            self._held.append(tip)
        if self._stamp - self._held_since < HOLD_S:
            return None, f"the {self.description} is seen: hold its tip still on the bone for {HOLD_S:g} s"
        return np.mean(self._held, axis=0), ""
