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


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """Rectified pinhole camera (immutable; K is stored read-only).

    K : (3, 3) float64 intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels)
    width, height : image size in pixels

    Two cameras are equal when their sizes are equal and their K are identical.
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
        if any(float(v) != int(v) for v in (self.width, self.height)) or int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive integers, got {self.width}x{self.height}")
        K.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PinholeCamera):
            return NotImplemented
        return (self.width, self.height) == (other.width, other.height) and np.array_equal(self.K, other.K)

    def __hash__(self) -> int:
        return hash((self.width, self.height, self.K.tobytes()))

    fx = property(lambda self: float(self.K[0, 0]))
    fy = property(lambda self: float(self.K[1, 1]))
    cx = property(lambda self: float(self.K[0, 2]))
    cy = property(lambda self: float(self.K[1, 2]))

    @classmethod
    def from_dict(cls, d: dict) -> "PinholeCamera":
        """From ``{'width', 'height', 'K'}`` as in trial.yaml's ``camera`` block.

        Raises ValueError naming a missing key, or for an invalid K or size.
        """
        if not isinstance(d, dict):
            raise ValueError(f"camera must be a mapping with width, height and K, got {d!r}")
        missing = [k for k in ("width", "height", "K") if k not in d]
        if missing:
            raise ValueError(f"camera lacks {', '.join(missing)} (needs width, height and K (3x3))")
        return cls(K=np.asarray(d["K"], dtype=float), width=d["width"], height=d["height"])

    def to_dict(self) -> dict:
        """``{'width', 'height', 'K'}`` with K as nested lists (YAML-ready); inverse of from_dict."""
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
        """Pixel coordinates and depths of points in the camera frame (OpenCV: u = fx x / z + cx).

        Parameters
        ----------
        p_camera : (N, 3) float64, metres, camera frame

        Returns
        -------
        uv : (N, 2) float64 (column, row), pixel centres at integers; inf/NaN where z = 0
        z : (N,) float64 depth, metres; z <= 0 means the point is behind the camera (its uv is
            meaningless): callers mask with ``z > 0``.
        """
        p = np.asarray(p_camera, dtype=float)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.column_stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy])
        return uv, z

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) rays K^-1 (u, v, 1) of every pixel (z = 1)."""
        v, u = np.mgrid[0:self.height, 0:self.width].astype(float)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)

    def backproject(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Back-project the valid pixels of a depth image: p = z K^-1 (u, v, 1).

        Parameters
        ----------
        depth : (H, W) float, metres (z in the camera frame); 0 or non-finite = no measurement

        Returns
        -------
        p_camera : (M, 3) float64, metres, camera frame, one row per valid pixel in row-major order
        uv : (M, 2) int64, the (column, row) of each point's pixel, so ``depth[uv[:, 1], uv[:, 0]]``
            is its z.
        """
        depth = np.asarray(depth)
        if depth.shape != (self.height, self.width):
            raise ValueError(f"depth image is {depth.shape}, the camera is (H, W) = ({self.height}, {self.width})")
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

        Derivation: with p_gl = (x, -y, -z) for p_camera = (x, y, z), w_clip = z and
        x_ndc = 2 fx x / (W z) - (W - 2 cx - 1) / W = (2 (u + 0.5) - W) / W with u = fx x / z + cx;
        likewise y_ndc = -2 fy y / (H z) - (2 cy + 1 - H) / H = 1 - 2 (v + 0.5) / H. The depth rows
        are glFrustum's. Checked against cv2.projectPoints in tests/test_camera.py.

        Parameters
        ----------
        near, far : clip distances along the optical axis, metres, 0 < near < far

        Returns
        -------
        (4, 4) float64, row-major (transpose it for GLSL's column-major ``mat4`` upload).
        """
        if not 0 < near < far:
            raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
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
