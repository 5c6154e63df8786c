"""``stereo``: an active stereo camera like the Intel RealSense D415, with its errors in disparity.

Depth is the left imager's; the right imager sits ``b`` to its right (+x, rectified pair). For a
pixel at column ``u`` with depth ``z`` the disparity is ``d = f b / z`` pixels (``f`` = fx).

1. **Noise in disparity, correlated over the matching window.** White noise ``w ~ N(0, 1)`` per
   pixel is averaged over a ``window_px`` x ``window_px`` box (periodic borders) and multiplied by
   ``window_px``, so each pixel's noise ``n`` still has unit variance but neighbours share most of
   their window: the correlation at a lag of ``L`` px along a row is ``(window_px - L) / window_px``
   (6/7 = 0.86 at lag 1 for the 7 px window). Measured disparity ``d_m = d + sigma_d n``. To first
   order the depth error is ``sigma_z = z^2 sigma_d / (f b)``: 0.42 mm at 0.42 m and 1.0 mm at
   0.65 m for f = 612 px, b = 55 mm, sigma_d = 0.08 px.
2. **Stereo shadows.** A surface point the right imager cannot see has no match: along a row,
   pixel ``u`` is hidden when some pixel to its right maps at or left of it in the right image,
   ``u - d(u) > min_{u' > u} (u' - d(u'))`` (the ordering constraint broken by a nearer surface),
   and pixels whose match falls off the right image (``u - d < 0``, the band on the image's left
   edge) are invalid. The shadow therefore lies on the left side of a foreground object and is
   ``d_fg - d_bg`` pixels wide.
3. **Invalid and flying edges.** Pixels within ``edge_band_px`` of a disparity jump larger than
   ``edge_jump_px`` (between 4-neighbours, true disparity) are invalid with probability
   ``edge_invalid_fraction``; the others fly: their disparity is a random mix ``d_lo + a (d_hi -
   d_lo)``, ``a ~ U(0, 1)``, of the lowest and highest true disparity within ``edge_band_px``
   (the matching window straddles both surfaces), plus the same correlated noise.
4. **Quantisation.** Disparity is rounded to ``1 / subpixel_levels`` px (0: not rounded); a
   disparity outside ``(0, max_disparity_px]`` is invalid (the matcher's search range: minimum
   range ``f b / 126`` = 0.27 m); depth ``f b / d_m`` outside ``[z_min, z_max]`` is invalid; depth is
   rounded to the 16-bit unit (``depth_unit_mm``, default the trial's ``depth_scale``); depths over
   65535 units are invalid.
5. The scenario's :class:`~app.sim.sensors.common.SceneErrors` (scale error and bias on the depth
   before it becomes disparity; random and specular dropouts last), as for every model.

Parameter sources:
- ``baseline_m = 0.055``: D415 baseline 55 mm (Intel RealSense D400 Series datasheet);
- ``sigma_d_px = 0.08``: the D415's typical RMS subpixel error, ~0.08 px on a well-textured target
  (Grunnet-Jepsen et al., "Tuning depth cameras for best performance", Intel white paper:
  depth RMS error = z^2 subpixel / (f b));
- ``max_disparity_px = 126``: the D4 matcher's disparity search range (same white paper,
  MinZ = f b / 126);
- ``f`` from the trial's camera (fx; 612 px for the D415 at 640x480);
- assumptions (not from a datasheet): ``window_px = 7`` (the correlation length of the noise),
  ``subpixel_levels = 32`` (1/32 px disparity resolution), ``edge_jump_px = 1``, ``edge_band_px =
  2``, ``edge_invalid_fraction = 0.6``, ``z_min = 0.28`` m as in the ``independent`` model;
- not modelled: texture (the emitter's dot pattern is taken to texture every surface alike, so
  ``sigma_d`` does not depend on the surface), the emitter's own shadow, and the matcher's
  left-right check beyond the shadows above.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage

from app.geometry.camera import PinholeCamera
from app.sim.sensors.common import SceneErrors, depth_edges, dropouts, quantise_depth, scale_and_bias


@dataclass(frozen=True)
class StereoSensor:
    """Active stereo (D415-like): correlated disparity noise, shadows, edges, quantisation (module docstring)."""

    name: ClassVar[str] = "stereo"
    baseline_m: float = 0.055          # D415 datasheet
    sigma_d_px: float = 0.08           # RMS subpixel error (Intel tuning white paper)
    window_px: int = 7                 # matching window: the noise's correlation (assumption)
    subpixel_levels: int = 32          # disparity rounded to 1/32 px; 0 = not rounded (assumption)
    max_disparity_px: float = 126.0    # search range (Intel tuning white paper)
    edge_jump_px: float = 1.0          # disparity jump that makes an edge (assumption)
    edge_band_px: int = 2              # px either side of an edge that are invalid or fly (assumption)
    edge_invalid_fraction: float = 0.6 # share of the edge band that is invalid; the rest flies (assumption)
    z_min: float = 0.28                # m
    z_max: float = 3.0                 # m
    depth_unit_mm: float | None = None # 16-bit depth unit; None = the trial's depth_scale

    def __post_init__(self):
        checks = {"baseline_m": self.baseline_m > 0, "sigma_d_px": self.sigma_d_px >= 0,
                  "window_px": int(self.window_px) == self.window_px and self.window_px >= 1,
                  "subpixel_levels": int(self.subpixel_levels) == self.subpixel_levels and self.subpixel_levels >= 0,
                  "max_disparity_px": self.max_disparity_px > 0, "edge_jump_px": self.edge_jump_px > 0,
                  "edge_band_px": int(self.edge_band_px) == self.edge_band_px and self.edge_band_px >= 0,
                  "edge_invalid_fraction": 0 <= self.edge_invalid_fraction <= 1,
                  "z_min": 0 <= self.z_min < self.z_max,
                  "depth_unit_mm": self.depth_unit_mm is None or self.depth_unit_mm > 0}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"stereo sensor: invalid {', '.join(f'{k}={getattr(self, k)!r}' for k in bad)} "
                             "(baseline_m > 0, sigma_d_px >= 0, window_px integer >= 1, subpixel_levels integer >= 0, "
                             "edge_band_px integer >= 0, 0 <= edge_invalid_fraction <= 1, 0 <= z_min < z_max)")

    def sigma_z(self, z: np.ndarray, f_px: float) -> np.ndarray:
        """First-order depth noise (m) at depth ``z`` (m) for focal length ``f_px``: ``z^2 sigma_d / (f b)``,
        with the disparity rounding's variance (1 / levels)^2 / 12 added to ``sigma_d^2``."""
        q = 1.0 / self.subpixel_levels if self.subpixel_levels else 0.0
        sigma_d = np.sqrt(self.sigma_d_px ** 2 + q * q / 12.0)
        return np.asarray(z, dtype=float) ** 2 * sigma_d / (f_px * self.baseline_m)

    def measure(self, depth: np.ndarray, rng: np.random.Generator, *, camera: PinholeCamera,
                depth_scale_mm: float, errors: SceneErrors = SceneErrors(),
                bone_mask: np.ndarray | None = None) -> np.ndarray:
        """Measured depth (H, W) float32 metres (0 = invalid) from the exact rendered depth (0 = empty)."""
        fb = camera.fx * self.baseline_m
        valid = depth > 0
        d_true = np.where(valid, fb / np.where(valid, depth, 1.0), 0.0)
        invalid = ~valid | right_image_hidden(d_true)
        band = depth_edges(d_true, self.edge_jump_px)
        if self.edge_band_px > 1:
            band = ndimage.binary_dilation(band, iterations=self.edge_band_px - 1)
        band &= valid
        z = scale_and_bias(depth, errors)
        d = np.where(valid, fb / np.where(valid, z, 1.0), 0.0)
        noise = self.sigma_d_px * correlated_noise(depth.shape, self.window_px, rng)
        edge_draw = rng.random(depth.shape)
        mix = rng.random(depth.shape)
        invalid |= band & (edge_draw < self.edge_invalid_fraction)
        flying = band & ~invalid
        if flying.any():
            size = 2 * self.edge_band_px + 1
            d_hi = ndimage.maximum_filter(d, size=size)
            d_lo = ndimage.minimum_filter(d, size=size)
            d = np.where(flying, d_lo + mix * (d_hi - d_lo), d)
        d = d + noise
        if self.subpixel_levels:
            d = np.rint(d * self.subpixel_levels) / self.subpixel_levels
        invalid |= (d <= 0) | (d > self.max_disparity_px)
        z = fb / np.where(invalid, 1.0, d)
        invalid |= (z < self.z_min) | (z > self.z_max)
        z = quantise_depth(z, self.depth_unit_mm or depth_scale_mm)
        invalid |= (z <= 0) | dropouts(depth.shape, errors, rng, bone_mask)
        return np.where(invalid, 0.0, z).astype(np.float32)


def correlated_noise(shape: tuple[int, int], window_px: int, rng: np.random.Generator) -> np.ndarray:
    """(H, W) noise of unit variance per pixel, correlated over a ``window_px`` box: white N(0, 1)
    averaged over the box (periodic borders, so every pixel averages window_px^2 samples) times window_px.
    Neighbours ``L`` px apart along a row or column correlate by ``(window_px - L) / window_px``."""
    white = rng.standard_normal(shape)
    if window_px <= 1:
        return white
    return ndimage.uniform_filter(white, size=int(window_px), mode="wrap") * float(window_px)


def right_image_hidden(disparity: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of the left (reference) image that the right imager, offset along +x, cannot see.

    ``disparity`` (px, 0 = empty). A pixel's match lies at column ``u - d`` of the right image; it is
    hidden when a pixel to its right maps at or left of that column (a nearer surface covers it), or
    when ``u - d < 0`` (outside the right image). Empty pixels hide nothing.
    """
    h, w = disparity.shape
    u = np.arange(w, dtype=float)
    right_col = u[None, :] - disparity
    # min over u' > u of right_col[u']: a running minimum from the right, shifted by one column
    running = np.minimum.accumulate(right_col[:, ::-1], axis=1)[:, ::-1]
    min_right = np.full((h, w), np.inf)
    min_right[:, :-1] = running[:, 1:]
    hidden = (right_col >= min_right) & (disparity > 0)
    return hidden | ((right_col < 0) & (disparity > 0))
