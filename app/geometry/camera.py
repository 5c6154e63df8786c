"""The pinhole depth camera: intrinsics K, resize and crop ((B) eq. 4.23-4.25), projection, and
the OpenGL projection built from K.

Conventions (RECORDING_FORMAT.md): the camera frame is OpenCV's (x right, y down, z forward);
pixel (u, v) = (column, row) has its centre at integer coordinates, so the ray of pixel (u, v)
passes through K^-1 (u, v, 1). Depth is z in the camera frame, metres, 0 = no measurement.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# OpenCV camera -> OpenGL eye coordinates (x right, y up, z backwards): a rotation by pi about x.
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class PinholeCamera:
    """Rectified pinhole camera.

    K : (3, 3) float64 intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels)
    width, height : image size in pixels
    """

    K: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        K = np.asarray(self.K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not np.allclose(K[2], [0, 0, 1]):
            raise ValueError(f"K must be a finite 3x3 matrix with last row [0, 0, 1], got {K.tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        K.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    fx = property(lambda self: float(self.K[0, 0]))
    fy = property(lambda self: float(self.K[1, 1]))
    cx = property(lambda self: float(self.K[0, 2]))
    cy = property(lambda self: float(self.K[1, 2]))

    @classmethod
    def from_dict(cls, d: dict) -> "PinholeCamera":
        """From ``{'width', 'height', 'K'}`` as in trial.yaml's ``camera`` block."""
        return cls(K=np.asarray(d["K"], dtype=float), width=int(d["width"]), height=int(d["height"]))

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "K": self.K.tolist()}

    def resized(self, width: int, height: int) -> "PinholeCamera":
        """The same camera at another resolution ((B) eq. 4.23-4.25, pixel centres at integers).

        With s = width / W: fx' = s fx and cx' = s (cx + 0.5) - 0.5 (likewise for y), because pixel
        u' covers [u' - 0.5, u' + 0.5] and maps to [(u' + 0.5)/s - 1, ...] of the original.
        """
        sx, sy = width / self.width, height / self.height
        K = np.array([
            [sx * self.fx, 0.0, sx * (self.cx + 0.5) - 0.5],
            [0.0, sy * self.fy, sy * (self.cy + 0.5) - 0.5],
            [0.0, 0.0, 1.0],
        ])
        return PinholeCamera(K, width, height)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "PinholeCamera":
        """The camera of the sub-image starting at column x0, row y0: cx' = cx - x0, cy' = cy - y0."""
        K = self.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        return PinholeCamera(K, width, height)

    def project(self, p_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) and depths (N,) of points (N, 3) in the camera frame."""
        p = np.asarray(p_camera, dtype=float)
        z = p[:, 2]
        uv = np.column_stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy])
        return uv, z

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) rays K^-1 (u, v, 1) of every pixel (z = 1)."""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(float)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)

    def backproject(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (M, 3) in the camera frame of the valid pixels of ``depth`` (H, W) metres, and
        their pixel coordinates (M, 2) as (u, v). Invalid = 0 or non-finite."""
        depth = np.asarray(depth, dtype=float)
        valid = np.isfinite(depth) & (depth > 0)
        v, u = np.nonzero(valid)
        z = depth[v, u]
        points = np.column_stack([(u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z])
        return points, np.column_stack([u, v])

    def opengl_projection(self, near: float, far: float) -> np.ndarray:
        """(4, 4) OpenGL projection of OpenGL eye coordinates (``CV_TO_GL @ p_camera``).

        Maps pixel centres to x_ndc = 2 (u + 0.5) / W - 1 and y_ndc = 1 - 2 (v + 0.5) / H (GL's
        bottom row is the image's last row), depth to [-1, 1] between ``near`` and ``far``.
        """
        W, H = self.width, self.height
        return np.array([
            [2 * self.fx / W, 0.0, (W - 2 * self.cx - 1) / W, 0.0],
            [0.0, 2 * self.fy / H, (2 * self.cy + 1 - H) / H, 0.0],
            [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
            [0.0, 0.0, -1.0, 0.0],
        ])


def opencv_to_opengl_view(T_camera_x: np.ndarray) -> np.ndarray:
    """OpenGL view matrix of a pose in the OpenCV camera frame: CV_TO_GL @ T_camera_x."""
    return CV_TO_GL @ np.asarray(T_camera_x, dtype=float)
