"""Gray-code structured light: the patterns a projector shows and their decoding in camera images.

OpenCV's ``cv2.structured_light.GrayCodePattern`` is part of opencv-contrib; the
``opencv-python-headless`` wheel osteonav depends on (4.14) does not include the
``structured_light`` module, so the encoding and decoding are implemented here in numpy, following
the same scheme (and the same image order as OpenCV's ``generate`` + white/black images):

- column index x in [0, W) is written with ``n_x = ceil(log2 W)`` bits of its reflected binary
  Gray code g(x) = x XOR (x >> 1), most significant bit first; rows likewise with ``n_y`` bits;
- each bit is shown as a pattern and its inverse (a pixel lit where the bit is 1, then where it is
  0), so decoding compares two captures of the same scene pixel and needs no global threshold;
- image 0 is all white and image 1 all black (the direct/ambient check and the board detection).

Order of :func:`patterns` (``2 + 2 (n_x + n_y)`` images)::

    white, black, col bit 0 (MSB), its inverse, ..., col bit n_x-1, inverse, row bit 0, inverse, ...

Decoding (:func:`decode`): a camera pixel is valid when white - black >= ``min_direct`` (the
projector lights it) and every pattern/inverse pair differs by at least ``min_contrast`` grey
levels; its bits give g, and x = g XOR (g >> 1) XOR (g >> 2) ... (Gray to binary).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def bit_count(n: int) -> int:
    """Bits needed to number ``n`` columns (or rows): ceil(log2 n), at least 1."""
    return max(1, int(np.ceil(np.log2(max(int(n), 2)))))


def gray_encode(i: np.ndarray) -> np.ndarray:
    """Reflected binary Gray code of non-negative integers."""
    i = np.asarray(i, dtype=np.int64)
    return i ^ (i >> 1)


def gray_decode(g: np.ndarray) -> np.ndarray:
    """Inverse of :func:`gray_encode`: b = g XOR (g >> 1) XOR (g >> 2) XOR ..."""
    b = np.asarray(g, dtype=np.int64).copy()
    shift = b >> 1
    while np.any(shift):
        b ^= shift
        shift >>= 1
    return b


def pattern_count(width: int, height: int) -> int:
    return 2 + 2 * (bit_count(width) + bit_count(height))


def patterns(width: int, height: int) -> np.ndarray:
    """(P, height, width) uint8 projector images in the order of the module docstring (0 or 255)."""
    nx, ny = bit_count(width), bit_count(height)
    gx, gy = gray_encode(np.arange(width)), gray_encode(np.arange(height))
    out = [np.full((height, width), 255, np.uint8), np.zeros((height, width), np.uint8)]
    for bit in range(nx):
        row = (((gx >> (nx - 1 - bit)) & 1) * 255).astype(np.uint8)
        img = np.broadcast_to(row[None, :], (height, width))
        out += [img.copy(), 255 - img]
    for bit in range(ny):
        col = (((gy >> (ny - 1 - bit)) & 1) * 255).astype(np.uint8)
        img = np.broadcast_to(col[:, None], (height, width))
        out += [img.copy(), 255 - img]
    return np.stack(out)


@dataclass
class Decoded:
    """Projector pixel seen by each camera pixel.

    col, row : (H, W) int64 projector column and row (meaningful where valid)
    valid : (H, W) bool
    """

    col: np.ndarray
    row: np.ndarray
    valid: np.ndarray


def decode(captures: np.ndarray, projector_width: int, projector_height: int, min_contrast: float = 8.0,
           min_direct: float = 30.0) -> Decoded:
    """Decode camera captures of :func:`patterns` (same order) into projector coordinates.

    Parameters
    ----------
    captures : (P, H, W) uint8 or float grey camera images, P = pattern_count(projector size)
    min_contrast : grey levels a pattern and its inverse must differ by at each bit
    min_direct : grey levels white must exceed black by (pixels the projector does not reach fail)
    """
    captures = np.asarray(captures, dtype=np.float32)
    nx, ny = bit_count(projector_width), bit_count(projector_height)
    expected = 2 + 2 * (nx + ny)
    if captures.ndim != 3 or captures.shape[0] != expected:
        raise ValueError(f"expected {expected} captures (H, W) for a {projector_width}x{projector_height} projector, "
                         f"got an array of shape {captures.shape}")
    valid = captures[0] - captures[1] >= min_direct

    def word(first: int, n: int) -> np.ndarray:
        nonlocal valid
        g = np.zeros(captures.shape[1:], dtype=np.int64)
        for bit in range(n):
            diff = captures[first + 2 * bit] - captures[first + 2 * bit + 1]
            valid &= np.abs(diff) >= min_contrast
            g = (g << 1) | (diff > 0)
        return gray_decode(g)

    col = word(2, nx)
    row = word(2 + 2 * nx, ny)
    valid &= (col < projector_width) & (row < projector_height)
    return Decoded(col, row, valid)
