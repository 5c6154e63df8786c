"""The projector as an inverse pinhole camera.

A projector is modelled exactly like the depth camera (:class:`app.geometry.camera.PinholeCamera`):
intrinsics ``K_p`` (pixels, OpenCV frame x right, y down, z forward out of the lens), a resolution,
and its pose on the rig ``T_camera_projector`` (pose of the projector in the depth camera's frame,
maps points from the projector frame to the camera frame). Lighting projector pixel (u, v) sends a
ray along ``K_p^-1 (u, v, 1)``; a point ``p_projector`` is lit by pixel ``K_p p / z``.

Chains used everywhere (DESIGN.md "Frames and conventions")::

    T_base_projector   = T_base_camera @ T_camera_projector
    T_projector_bone   = inv(T_base_projector) @ T_base_bone

Lens distortion of the projector is ignored when rendering (``dist`` is kept for calibration
reports only); a projector whose calibration finds large distortion should be rectified first.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.errors import ConfigError
from app.geometry import se3
from app.geometry.camera import PinholeCamera


@dataclass(frozen=True, eq=False)
class ProjectorModel:
    """K_p, resolution and mounting of a projector.

    Parameters
    ----------
    camera : PinholeCamera, the projector's intrinsics K_p (pixels) and resolution (width, height)
    T_camera_projector : (4, 4) float64, pose of the projector in the depth camera frame, metres
    dist : (5,) float64 OpenCV distortion of the projector lens (reported, not rendered)
    """

    camera: PinholeCamera
    T_camera_projector: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        T = np.array(self.T_camera_projector, dtype=float)
        if T.shape != (4, 4) or not se3.is_rigid(T, atol=1e-5):
            raise ValueError(f"T_camera_projector must be a rigid 4x4 pose, got {T.tolist()}")
        T.setflags(write=False)
        object.__setattr__(self, "T_camera_projector", T)
        object.__setattr__(self, "dist", np.asarray(self.dist, dtype=float).ravel())

    width = property(lambda self: self.camera.width)
    height = property(lambda self: self.camera.height)
    K = property(lambda self: self.camera.K)

    def T_base_projector(self, T_base_camera: np.ndarray) -> np.ndarray:
        """(4, 4) pose of the projector in the base frame from the camera's."""
        return np.asarray(T_base_camera, dtype=float) @ self.T_camera_projector

    def T_projector_bone(self, T_base_camera: np.ndarray, T_base_bone: np.ndarray) -> np.ndarray:
        """(4, 4) pose of the bone in the projector frame: inv(T_base_camera T_camera_projector) T_base_bone."""
        return se3.inverse(self.T_base_projector(T_base_camera)) @ np.asarray(T_base_bone, dtype=float)

    def resized(self, width: int, height: int) -> "ProjectorModel":
        """The same projector at another resolution (K scaled, pixel centres kept)."""
        return ProjectorModel(self.camera.resized(width, height), self.T_camera_projector, self.dist)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "K": self.K.tolist(),
                "dist": [float(v) for v in self.dist],
                "T_camera_projector": self.T_camera_projector.tolist()}

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None, key: str = "projector") -> "ProjectorModel":
        """From ``{width, height, K, T_camera_projector[, dist]}`` (the projector YAML block).

        Raises ConfigError naming the key at fault.
        """
        if not isinstance(d, dict):
            raise ConfigError(key, f"expected a mapping with width, height, K and T_camera_projector, got {d!r}", source)
        for name in ("width", "height", "K", "T_camera_projector"):
            if name not in d:
                raise ConfigError(f"{key}.{name}", "missing (a projector needs width, height, K (3x3) and "
                                  "T_camera_projector (4x4), e.g. from `osteonav calibrate projector`)", source)
        try:
            camera = PinholeCamera(np.asarray(d["K"], dtype=float), d["width"], d["height"])
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"{key}.K", str(exc), source) from None
        try:
            T = np.asarray(d["T_camera_projector"], dtype=float)
            dist = np.asarray(d.get("dist", [0.0] * 5), dtype=float)
            return cls(camera, T, dist)
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"{key}.T_camera_projector", str(exc), source) from None


def look_at_pose(position_camera: np.ndarray, target_camera: np.ndarray, up_camera=(0.0, -1.0, 0.0)) -> np.ndarray:
    """T_camera_projector of a projector at ``position_camera`` whose optical axis points at ``target_camera``.

    Parameters
    ----------
    position_camera, target_camera : (3,) metres in the camera frame
    up_camera : (3,) the direction that should appear upwards (OpenCV: -y) in the projector image
    """
    p = np.asarray(position_camera, dtype=float)
    z = np.asarray(target_camera, dtype=float) - p
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up_camera, dtype=float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return se3.make_pose(np.column_stack([x, y, z]), p)


def default_projector(width: int = 1280, height: int = 800) -> ProjectorModel:
    """A pico projector 6 cm beside the depth camera, aimed at the bone 0.42 m in front of it.

    Throw ratio ~1.2 (fx = 1.2 * width), principal point at the bottom-centre offset typical of
    projectors is not modelled (centred). Matches the simulator's camera-to-bone distance.
    """
    fx = 1.2 * width
    K = np.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fx, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    T = look_at_pose([0.06, 0.0, 0.0], [0.0, 0.0, 0.42])
    return ProjectorModel(PinholeCamera(K, width, height), T)
