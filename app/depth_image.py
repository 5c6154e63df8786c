"""Depth-image operations shared by the tracker and its sinks (plain numpy).

The filter works at a low resolution (80x60 to 160x120, (A), (B)); the measured image is reduced by
nearest neighbour ((B) A.2.6), never averaged, so invalid pixels (0) and depth edges are not blended
into depths that exist nowhere. The sampled source pixel of target pixel u' is
round((u' + 0.5) / s - 0.5) with s = w'/w, the pixel-centre convention of
:meth:`PinholeCamera.resized`, so the reduced image and the resized K agree.
"""
from __future__ import annotations

import numpy as np


def nearest_indices(n_source: int, n_target: int) -> np.ndarray:
    """Source indices (n_target,) sampled for each target pixel centre."""
    scale = n_target / n_source
    idx = np.round((np.arange(n_target) + 0.5) / scale - 0.5).astype(int)
    return np.clip(idx, 0, n_source - 1)


def downsample_nearest(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width) nearest-neighbour reduction of a (H, W) depth image; non-finite -> 0."""
    rows = nearest_indices(depth.shape[0], height)
    cols = nearest_indices(depth.shape[1], width)
    out = depth[np.ix_(rows, cols)].astype(np.float32, copy=True)
    out[~np.isfinite(out)] = 0.0
    return out
