"""The renderer's edge: conversions between numpy conventions and OpenGL's.

Kept in one module (STYLE.md §10): the transpose for GLSL's column-major ``mat4`` and the
bottom-left origin of GL images. The OpenCV -> OpenGL camera flip happens in the vertex shader
(``depth.vert.glsl``), and the projection comes from :meth:`PinholeCamera.opengl_projection`.
"""
from __future__ import annotations

import numpy as np


def mat4_to_glsl(T: np.ndarray) -> bytes:
    """Bytes of one or more row-major numpy 4x4 matrices as GLSL column-major ``mat4`` (float32).

    Parameters
    ----------
    T : (..., 4, 4) float array
    """
    T = np.asarray(T, dtype=np.float32)
    return np.ascontiguousarray(np.swapaxes(T, -1, -2)).tobytes()


def gl_rows_to_image(rows: np.ndarray) -> np.ndarray:
    """Flip GL's bottom-up rows into image rows (row 0 at the top); works on (..., H, W)."""
    return np.ascontiguousarray(rows[..., ::-1, :])


def tile_grid(n: int, width: int, height: int) -> tuple[int, int]:
    """Tiles per row and rows for ``n`` tiles of ``width`` x ``height``, close to a square texture."""
    cols = max(1, int(np.ceil(np.sqrt(n * height / width))))
    rows = int(np.ceil(n / cols))
    return cols, rows
