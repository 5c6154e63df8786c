"""A pointer tool held on the crest, drawn into the simulated infrared image (issue 33, item 3).

Import as ``from app.sim.pointer import SimulatedPointer``. The live start can take its point from a
pointer's tip that the marker tracker sees (app/tracking/pointer.py, the session's ``bone.pointer``).
To run that path end to end without hardware, the simulator draws the tool's ArUco marker into each
frame's infrared image: the tool is held still with its tip ``off_m`` off the crest's top (the
simulator's ``point_prior``: the highest mesh vertex at the first frame) in a direction drawn from
the trial's seed, as a surgeon's pointing error, and moves with the bone.

Geometry. The marker frame M (app/marker/aruco.py: origin at the printed square's centre, x right,
y up, z out of the face) faces the first frame's camera (z_M = -z_camera, x_M = x_camera, so y_M =
-y_camera, up in the image), turned ``tilt_rad`` about its x axis: a tool is held at an angle, and a
small marker seen face-on has an ambiguous orientation (IPPE), which the 10 cm lever to the tip
turns into millimetres: face-on, the tip read from the simulated images moved 2-7 mm frame to frame,
at 35 deg 0.5-1.8 mm (under the pointer's 2 mm hold, app/tracking/pointer.py's HOLD_M). The tip lies at
``tip_offset_m`` in M (the tool's calibration, as ``bone.pointer.tip_offset_m``); the marker's
centre is where that puts the tip on the point:

    T_base_M = (R, p_tip - R tip_M),   R = R_base_camera0 diag(1, -1, -1) R_x(tilt)

and, held on the bone, T_bone_M = T_base_bone0^-1 T_base_M for every frame.

Drawing: the marker image (``cv2.aruco.generateImageMarker``, one-module black border, a quiet zone
of white around it) is warped by the homography of its four outer corners projected through the
depth camera (pixel centres at integers, as OpenCV's), onto the captured infrared image (after the
imager: the printed square is matte, white ``WHITE``, black ``BLACK`` 8-bit levels). Limits: the tool
is not in the depth image (its shaft and marker plate would hide a few square centimetres), and the
marker is drawn even where the bone or tissue would hide it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.geometry import se3
from app.geometry.camera import PinholeCamera

WHITE, BLACK = 235, 25          # the printed marker's 8-bit levels in the infrared image
MARKER_PIXELS = 120             # the marker's side in the drawn texture (modules of 20 px for a 4x4 + border)
QUIET_PIXELS = 20               # the white margin around it (one module)


@dataclass(frozen=True)
class SimulatedPointer:
    """The tool: ``marker_id`` of ``dictionary``, the black square's side ``marker_length_m``, the tip at
    ``tip_offset_m`` in the marker frame, held ``off_m`` off the crest's top (module docstring)."""

    marker_id: int = 7
    marker_length_m: float = 0.04
    tip_offset_m: tuple = (0.0, -0.10, -0.005)
    dictionary: str = "DICT_4X4_50"
    off_m: float = 0.003
    tilt_rad: float = 0.6          # the marker's face turned this far from the camera about its x axis (35 deg)

    def session_block(self) -> dict:
        """The session's ``bone.pointer`` that reads this tool (app/session/config.py)."""
        return {"marker_id": self.marker_id, "marker_length_m": self.marker_length_m,
                "tip_offset_m": list(self.tip_offset_m), "dictionary": self.dictionary, "stream": "ir"}


@dataclass
class PointerDrawing:
    """The tool of one trial: its pose in the bone frame and its marker's texture (module docstring)."""

    tool: SimulatedPointer
    T_bone_M: np.ndarray
    tip_base: np.ndarray            # where the tip touches at the first frame (base frame)
    texture: np.ndarray = field(repr=False, default=None)

    @classmethod
    def held(cls, tool: SimulatedPointer, top_base: np.ndarray, T_base_bone0: np.ndarray,
             T_base_camera0: np.ndarray, rng: np.random.Generator) -> "PointerDrawing":
        """The tool held with its tip ``tool.off_m`` from ``top_base`` (a uniform direction drawn from
        ``rng``), its marker facing the first frame's camera."""
        import cv2

        from app.marker.aruco import dictionary

        direction = rng.standard_normal(3)
        tip_base = np.asarray(top_base, float) + tool.off_m * direction / np.linalg.norm(direction)
        R = T_base_camera0[:3, :3] @ np.diag([1.0, -1.0, -1.0]) @ _turn_x(tool.tilt_rad)
        T_base_M = np.eye(4)
        T_base_M[:3, :3] = R
        T_base_M[:3, 3] = tip_base - R @ np.asarray(tool.tip_offset_m, float)
        marker = cv2.aruco.generateImageMarker(dictionary(tool.dictionary), tool.marker_id, MARKER_PIXELS,
                                               borderBits=1)
        n = MARKER_PIXELS + 2 * QUIET_PIXELS
        texture = np.full((n, n), float(WHITE), np.float32)
        texture[QUIET_PIXELS:QUIET_PIXELS + MARKER_PIXELS, QUIET_PIXELS:QUIET_PIXELS + MARKER_PIXELS] = \
            np.where(marker > 127, WHITE, BLACK)
        return cls(tool, se3.inverse(T_base_bone0) @ T_base_M, tip_base, texture)

    def draw(self, infrared: np.ndarray, camera: PinholeCamera, T_camera_bone: np.ndarray) -> np.ndarray:
        """``infrared`` ((H, W) uint8) with the marker warped in at T_camera_M = T_camera_bone T_bone_M;
        unchanged when the marker is not wholly in front of the camera."""
        import cv2

        T_camera_M = np.asarray(T_camera_bone, float) @ self.T_bone_M
        n = self.texture.shape[0]
        h = 0.5 * self.tool.marker_length_m * n / MARKER_PIXELS
        corners_M = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        corners_camera = corners_M @ T_camera_M[:3, :3].T + T_camera_M[:3, 3]
        if np.any(corners_camera[:, 2] <= 0.05):
            return infrared
        uv, _ = camera.project(corners_camera)
        px = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32) - 0.5
        H = cv2.getPerspectiveTransform(px, np.asarray(uv, np.float32))
        size = (camera.width, camera.height)
        warped = cv2.warpPerspective(self.texture, H, size, flags=cv2.INTER_AREA)
        cover = cv2.warpPerspective(np.ones((n, n), np.float32), H, size, flags=cv2.INTER_LINEAR)
        out = infrared.astype(np.float32) * (1.0 - cover) + warped * cover
        return np.clip(np.round(out), 0, 255).astype(np.uint8)


def _turn_x(angle: float) -> np.ndarray:
    """R_x(angle): a turn about the x axis."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
