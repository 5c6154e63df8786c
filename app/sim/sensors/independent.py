"""``independent``: white per-pixel depth noise whose spread grows with depth squared (the default).

The simulator's original model (formerly ``app.sim.sensor``), kept bit for bit for the same seed:

- measured depth ``z_m = z + sigma(z) n`` with ``n ~ N(0, 1)`` independent per pixel and
  ``sigma(z) = k z^2 + sigma_base``, ``k = 0.0015 /m``, ``sigma_base = 0.3 mm`` (0.56 mm at 0.42 m,
  0.93 mm at 0.65 m). The quadratic term is the shape of a stereo camera's depth error; the values
  are assumptions of the order of a RealSense D415's measured precision at these ranges, not
  datasheet values;
- invalid: outside ``[z_min, z_max]`` (D415 minimum range ~0.3 m at 640x480; assumption 0.28 m),
  next to a depth jump larger than ``edge_jump`` (6 mm), dilated by ``edge_dilation`` px (the
  matcher fails at occluding edges), plus the scenario's :class:`~app.sim.sensors.common.SceneErrors`;
- no quantisation here: the trial writer rounds to ``depth_scale`` when it writes the PNG.

Its noise has no spatial correlation (lag-1 autocorrelation ~0), unlike a real stereo camera's
(:mod:`app.sim.sensors.stereo`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage

from app.geometry.camera import PinholeCamera
from app.sim.sensors.common import SceneErrors, depth_edges, dropouts, scale_and_bias


@dataclass(frozen=True)
class IndependentSensor:
    """Independent per-pixel noise sigma(z) = k z^2 + sigma_base (module docstring)."""

    name: ClassVar[str] = "independent"
    k: float = 0.0015              # 1/m: sigma(z) = k z^2 + sigma_base
    sigma_base: float = 0.0003     # m
    z_min: float = 0.28            # m, minimum range (D415 ~0.3 m at 640x480)
    z_max: float = 3.0             # m
    edge_jump: float = 0.006       # m, neighbour depth jump that invalidates a pixel
    edge_dilation: int = 1         # px

    def __post_init__(self):
        checks = {"k": self.k >= 0, "sigma_base": self.sigma_base >= 0, "z_min": 0 <= self.z_min < self.z_max,
                  "edge_jump": self.edge_jump > 0,
                  "edge_dilation": int(self.edge_dilation) == self.edge_dilation and self.edge_dilation >= 0}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"independent sensor: invalid {', '.join(f'{k}={getattr(self, k)!r}' for k in bad)} "
                             "(k >= 0, sigma_base >= 0, 0 <= z_min < z_max, edge_jump > 0, edge_dilation integer >= 0)")

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Per-pixel noise standard deviation (m) at depth ``z`` (m)."""
        return self.k * z * z + self.sigma_base

    def measure(self, depth: np.ndarray, rng: np.random.Generator, *, camera: PinholeCamera | None = None,
                depth_scale_mm: float | None = None, errors: SceneErrors = SceneErrors(),
                bone_mask: np.ndarray | None = None) -> np.ndarray:
        """Measured depth (H, W) float32 metres (0 = invalid) from the exact rendered depth (0 = empty).

        ``camera`` and ``depth_scale_mm`` are not used (the noise is per pixel; the writer quantises).
        """
        valid = depth > 0
        z = scale_and_bias(depth, errors)
        z = z + rng.standard_normal(z.shape) * self.sigma(z)
        invalid = ~valid | (z < self.z_min) | (z > self.z_max)
        edges = depth_edges(np.where(valid, depth, 0.0), self.edge_jump)
        if self.edge_dilation:
            edges = ndimage.binary_dilation(edges, iterations=self.edge_dilation)
        invalid |= edges
        invalid |= dropouts(z.shape, errors, rng, bone_mask)
        return np.where(invalid, 0.0, z).astype(np.float32)
