"""A stereo depth sensor's errors applied to a rendered (exact) depth image.

Intel RealSense D4xx-like (DESIGN.md, "What the operating room does to the tracker"):
- noise sigma(z) = k z^2 + sigma_base (stereo error grows quadratically with depth);
- invalid pixels along depth discontinuities (the matcher fails at occluding edges) and at random;
- invalid blobs on wet, specular bone (optional), out-of-range pixels (closer than ``z_min``);
- a relative scale error and a smooth bias across the image (optional);
- quantisation to the recording's depth unit happens when the PNG is written.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class SensorModel:
    k: float = 0.0015              # 1/m: sigma(z) = k z^2 + sigma_base
    sigma_base: float = 0.0003     # m
    z_min: float = 0.28            # m, minimum range (D415 ~0.3 m at 640x480)
    z_max: float = 3.0             # m
    edge_jump: float = 0.006       # m, neighbour depth jump that invalidates a pixel
    edge_dilation: int = 1         # px
    invalid_probability: float = 0.01
    scale_error: float = 0.0       # relative
    bias: float = 0.0              # m, amplitude of the smooth bias field
    specular_fraction: float = 0.0 # fraction of bone pixels lost to specular blobs

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Per-pixel noise standard deviation (m) at depth ``z`` (m)."""
        return self.k * z * z + self.sigma_base


def depth_edges(depth: np.ndarray, jump: float) -> np.ndarray:
    """(H, W) bool: pixels next to a depth discontinuity larger than ``jump`` (or to empty pixels)."""
    edges = np.zeros(depth.shape, dtype=bool)
    dx = np.abs(np.diff(depth, axis=1)) > jump
    dy = np.abs(np.diff(depth, axis=0)) > jump
    edges[:, 1:] |= dx
    edges[:, :-1] |= dx
    edges[1:, :] |= dy
    edges[:-1, :] |= dy
    return edges


def smooth_field(shape: tuple[int, int], rng: np.random.Generator, scale_px: float = 40.0) -> np.ndarray:
    """A smooth random field in [-1, 1] (low-pass filtered noise)."""
    field = ndimage.gaussian_filter(rng.standard_normal(shape), scale_px)
    return field / max(np.abs(field).max(), 1e-12)


def apply_sensor(depth: np.ndarray, model: SensorModel, rng: np.random.Generator,
                 bone_mask: np.ndarray | None = None) -> np.ndarray:
    """Measured depth (H, W) float32 metres (0 = invalid) from the exact rendered depth (0 = empty)."""
    valid = depth > 0
    z = depth.astype(np.float64) * (1.0 + model.scale_error)
    if model.bias:
        h, w = depth.shape
        v, u = np.mgrid[0:h, 0:w]
        z = z + model.bias * (0.6 * np.cos(np.pi * u / w) + 0.4 * np.sin(np.pi * v / h))
    z = z + rng.standard_normal(z.shape) * model.sigma(z)
    invalid = ~valid | (z < model.z_min) | (z > model.z_max)
    edges = depth_edges(np.where(valid, depth, 0.0), model.edge_jump)
    if model.edge_dilation:
        edges = ndimage.binary_dilation(edges, iterations=model.edge_dilation)
    invalid |= edges
    invalid |= rng.random(z.shape) < model.invalid_probability
    if model.specular_fraction > 0 and bone_mask is not None and bone_mask.any():
        field = smooth_field(depth.shape, rng, scale_px=4.0)
        threshold = np.quantile(field[bone_mask], 1.0 - model.specular_fraction)
        invalid |= bone_mask & (field > threshold)
    return np.where(invalid, 0.0, z).astype(np.float32)
