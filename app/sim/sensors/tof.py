"""``tof``: a continuous-wave time-of-flight camera: amplitude-dependent noise, mixed pixels, multipath bias.

Each pixel measures the phase of its own returned light, so the noise is independent per pixel
(no matching window), but it depends on how much light comes back, and a pixel whose footprint
straddles a depth discontinuity returns a mixture of both surfaces.

1. **Amplitude.** The returned amplitude relative to a surface facing the camera at ``z_ref``:
   ``A = cos(theta) (z_ref / z)^2`` (a Lambertian surface of uniform reflectance lit by the camera's
   own illuminator; ``theta`` the angle between the surface normal, from the depth image's
   neighbours, and the viewing ray). Pixels with ``A < min_amplitude`` are invalid (the camera's
   confidence threshold: grazing surfaces, far range).
2. **Noise.** Shot-noise-limited phase noise: ``sigma_z = sigma_ref / sqrt(A) = sigma_ref (z / z_ref) /
   sqrt(cos theta)``, white and independent per pixel (lag-1 autocorrelation ~0).
3. **Mixed ("flying") pixels.** A pixel within ``mixed_px`` of a depth jump larger than ``edge_jump``
   sees the nearest surface of its neighbourhood (``z_fg``, the lowest depth within ``mixed_px``) over
   a random share ``c ~ U(0, 1)`` of its footprint and the farthest (``z_bg``) over the rest. The
   phases of the two returns add as phasors; for the small phase differences at these ranges the
   result is the amplitude-weighted mean ``z = (c A_fg z_fg + (1 - c) A_bg z_bg) / (c A_fg + (1 - c)
   A_bg)`` with ``A = (z_ref / z)^2`` (an empty background returns nothing). Its noise follows its
   mixed amplitude ``c A_fg + (1 - c) A_bg`` times the largest incidence cosine within ``mixed_px`` (the
   normals at the jump itself are meaningless; a steep surface without a jump stays as dim as it is).
4. **Multipath bias near edges.** Light that bounces off a neighbouring surface travels further: every
   valid pixel is biased away from the camera by ``multipath_bias_m exp(-r / multipath_px)``, ``r`` its
   distance in pixels to the nearest depth discontinuity (0.5 px for the pixels either side of it).
5. Depth outside ``[z_min, z_max]`` is invalid; depth is rounded to the 16-bit unit
   (``depth_unit_mm``, default the trial's ``depth_scale``); the scenario's
   :class:`~app.sim.sensors.common.SceneErrors` as for every model (scale error and bias first,
   dropouts last).

Parameter sources: the Azure Kinect DK's hardware specification bounds its random error to
``sigma <= 17 mm`` and its systematic error to ``< 11 mm + 0.1 % of distance`` over its whole
range (0.25-5.46 m); at the surgical range of 0.4-0.65 m and on a bright surface far better is
reached, and all values here are assumptions of that order, not datasheet values:
``sigma_ref = 1 mm`` at ``z_ref = 0.5 m``, ``min_amplitude = 0.05`` (about 87 deg incidence at 0.5 m),
``mixed_px = 1``, ``edge_jump = 6 mm`` (as the ``independent`` model), ``multipath_bias_m = 1 mm``,
``multipath_px = 4``, ``z_min = 0.25 m`` (the Azure Kinect's wide-field minimum).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage

from app.geometry.camera import PinholeCamera
from app.sim.sensors.common import SceneErrors, depth_edges, dropouts, quantise_depth, scale_and_bias


@dataclass(frozen=True)
class TofSensor:
    """Continuous-wave time of flight: amplitude-dependent noise, mixed pixels, multipath (module docstring)."""

    name: ClassVar[str] = "tof"
    sigma_ref_m: float = 0.001         # noise on a surface facing the camera at z_ref (assumption)
    z_ref_m: float = 0.5               # m
    min_amplitude: float = 0.05        # relative amplitude below which a pixel is invalid (assumption)
    mixed_px: int = 1                  # px either side of a discontinuity that mix both surfaces
    edge_jump: float = 0.006           # m, depth jump that makes a discontinuity
    multipath_bias_m: float = 0.001    # m, bias away from the camera at a discontinuity (assumption)
    multipath_px: float = 4.0          # px, its decay length (assumption)
    z_min: float = 0.25                # m
    z_max: float = 3.0                 # m
    depth_unit_mm: float | None = None # 16-bit depth unit; None = the trial's depth_scale

    def __post_init__(self):
        checks = {"sigma_ref_m": self.sigma_ref_m >= 0, "z_ref_m": self.z_ref_m > 0,
                  "min_amplitude": self.min_amplitude >= 0,
                  "mixed_px": int(self.mixed_px) == self.mixed_px and self.mixed_px >= 0,
                  "edge_jump": self.edge_jump > 0, "multipath_px": self.multipath_px > 0,
                  "z_min": 0 <= self.z_min < self.z_max,
                  "depth_unit_mm": self.depth_unit_mm is None or self.depth_unit_mm > 0}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"tof sensor: invalid {', '.join(f'{k}={getattr(self, k)!r}' for k in bad)} "
                             "(sigma_ref_m >= 0, z_ref_m > 0, min_amplitude >= 0, mixed_px integer >= 0, "
                             "edge_jump > 0, multipath_px > 0, 0 <= z_min < z_max)")

    def amplitude(self, z: np.ndarray, cos_theta: np.ndarray | float = 1.0) -> np.ndarray:
        """Returned amplitude relative to a facing surface at ``z_ref``: ``cos(theta) (z_ref / z)^2``."""
        z = np.asarray(z, dtype=float)
        return np.asarray(cos_theta) * (self.z_ref_m / np.where(z > 0, z, np.inf)) ** 2

    def sigma_z(self, z: np.ndarray, cos_theta: np.ndarray | float = 1.0) -> np.ndarray:
        """Noise (m): ``sigma_ref / sqrt(A)``."""
        return self.sigma_ref_m / np.sqrt(np.maximum(self.amplitude(z, cos_theta), 1e-12))

    def measure(self, depth: np.ndarray, rng: np.random.Generator, *, camera: PinholeCamera,
                depth_scale_mm: float, errors: SceneErrors = SceneErrors(),
                bone_mask: np.ndarray | None = None) -> np.ndarray:
        """Measured depth (H, W) float32 metres (0 = invalid) from the exact rendered depth (0 = empty)."""
        valid = depth > 0
        z = np.where(valid, scale_and_bias(depth, errors), 0.0)
        cos = incidence_cosine(z, camera)
        amp = self.amplitude(z, cos)
        edges = depth_edges(z, self.edge_jump)
        band = edges.copy()
        if self.mixed_px > 1:
            band = ndimage.binary_dilation(band, iterations=self.mixed_px - 1)
        band &= valid & (self.mixed_px > 0)
        coverage = rng.random(depth.shape)
        if band.any():
            z, amp = self._mix(z, amp, cos, band, coverage)
        if self.multipath_bias_m:
            # the pixels next to a jump lie half a pixel from it
            distance = ndimage.distance_transform_edt(~edges) + 0.5 if edges.any() else np.full(z.shape, np.inf)
            z = z + self.multipath_bias_m * np.exp(-distance / self.multipath_px)
        z = z + rng.standard_normal(z.shape) * self.sigma_ref_m / np.sqrt(np.maximum(amp, 1e-12))
        invalid = ~valid | (amp < self.min_amplitude) | (z < self.z_min) | (z > self.z_max)
        z = quantise_depth(np.where(invalid, 0.0, z), self.depth_unit_mm or depth_scale_mm)
        invalid |= (z <= 0) | dropouts(depth.shape, errors, rng, bone_mask)
        return np.where(invalid, 0.0, z).astype(np.float32)

    def _mix(self, z: np.ndarray, amp: np.ndarray, cos: np.ndarray, band: np.ndarray, coverage: np.ndarray):
        """Depth and amplitude of the mixed pixels in ``band`` (module docstring, 3)."""
        size = 2 * self.mixed_px + 1
        z_fg = ndimage.minimum_filter(np.where(z > 0, z, np.inf), size=size)
        z_bg = ndimage.maximum_filter(z, size=size)
        a_fg = self.amplitude(z_fg)
        a_bg = self.amplitude(z_bg)
        w_fg, w_bg = coverage * a_fg, (1.0 - coverage) * a_bg
        total = np.maximum(w_fg + w_bg, 1e-12)
        mixed = (w_fg * np.where(np.isfinite(z_fg), z_fg, 0.0) + w_bg * z_bg) / total
        facing = ndimage.maximum_filter(cos, size=size)   # a steep surface stays as dim as it is
        return np.where(band, mixed, z), np.where(band, (w_fg + w_bg) * facing, amp)


def incidence_cosine(depth: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """(H, W) |cos| of the angle between each pixel's surface normal (from its neighbours' 3D points,
    central differences) and its viewing ray; 0 where the depth or a neighbour is empty."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1)
    points = rays * depth[..., None]
    normal = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
    norm = np.linalg.norm(normal, axis=-1) * np.linalg.norm(points, axis=-1)
    cos = np.abs(np.sum(normal * points, axis=-1)) / np.where(norm > 0, norm, np.inf)
    empty = ndimage.binary_dilation(depth <= 0)
    return np.where(empty, 0.0, cos)
