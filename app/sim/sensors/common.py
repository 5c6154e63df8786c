"""What every simulated depth sensor shares: the scenario's errors, depth discontinuities, quantisation.

:class:`SceneErrors` are the scenario's errors (``app.sim.scenarios.Scenario``), which every sensor
model applies in the same way, so that a scenario means the same thing whatever the sensor:
- a relative depth scale error and a smooth bias field across the image (:func:`scale_and_bias`);
- random single invalid pixels and invalid blobs on wet, specular bone (:func:`dropouts`).

:func:`depth_edges` finds the pixels next to a depth discontinuity; :func:`quantise_depth` rounds to
the trial's 16-bit depth unit (RECORDING_FORMAT.md: ``depth_mm = PNG value * depth_scale``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

PNG_MAX = 65535   # largest 16-bit depth value


@dataclass(frozen=True)
class SceneErrors:
    """The scenario's depth errors, applied by every sensor model (names as in ``Scenario``)."""

    invalid_probability: float = 0.01   # random single invalid pixels
    scale_error: float = 0.0            # relative (0.005 = depth 0.5 % too far)
    bias: float = 0.0                   # m, amplitude of the smooth bias field
    specular_fraction: float = 0.0      # fraction of the bone's pixels lost to specular blobs


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


def scale_and_bias(depth: np.ndarray, errors: SceneErrors) -> np.ndarray:
    """float64 depth with the scenario's scale error and smooth bias field (empty pixels get them too)."""
    z = depth.astype(np.float64) * (1.0 + errors.scale_error)
    if errors.bias:
        h, w = depth.shape
        v, u = np.mgrid[0:h, 0:w]
        z = z + errors.bias * (0.6 * np.cos(np.pi * u / w) + 0.4 * np.sin(np.pi * v / h))
    return z


def dropouts(shape: tuple[int, int], errors: SceneErrors, rng: np.random.Generator,
             bone_mask: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: random invalid pixels, then specular blobs on ``bone_mask`` (in that order of draws)."""
    invalid = rng.random(shape) < errors.invalid_probability
    if errors.specular_fraction > 0 and bone_mask is not None and bone_mask.any():
        field = smooth_field(shape, rng, scale_px=4.0)
        threshold = np.quantile(field[bone_mask], 1.0 - errors.specular_fraction)
        invalid |= bone_mask & (field > threshold)
    return invalid


def quantise_depth(z: np.ndarray, depth_scale_mm: float) -> np.ndarray:
    """``z`` (m) rounded to the 16-bit unit ``depth_scale_mm``; beyond 65535 units it is invalid (0)."""
    units = np.rint(z * (1000.0 / depth_scale_mm))
    return np.where(units <= PNG_MAX, units * (depth_scale_mm * 1e-3), 0.0)
