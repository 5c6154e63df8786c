"""The D415's infrared dot projector and its left imager: the infrared image of the depth camera.

The D415's projector (between the two imagers) casts a fixed pseudo-random pattern of dots to give
texture to blank surfaces for the stereo matcher. The left imager has no IR-cut filter: it sees the
scene lit by the room (grey, see :mod:`app.sim.appearance`) plus, when the emitter is on, the dots.
A dot's irradiance on a surface at distance d from the emitter falls off as 1/d^2; because the
emitter sits beside the imager (baseline ``p_emitter_camera``), the dots shift along x with depth
(parallax), as on the real camera.

Model: the pattern is an image of Gaussian dots in the emitter's tangent-angle coordinates
(a, b) = (x/z, y/z) of the ray from the emitter to the surface point; each pixel's point
p = depth K^-1 (u, v, 1) is looked up in it (bilinear, ``cv2.remap``). Occlusion of dots by a
nearer surface (the emitter's shadow) is not modelled: with a 27 mm baseline it is a thin band at
occluding edges, where the depth is invalid anyway.
"""
from __future__ import annotations

import numpy as np

from app.geometry.camera import PinholeCamera

D415_EMITTER = np.array([0.0275, 0.0, 0.0])   # m, emitter in the left imager's (depth) optical frame


class DotProjector:
    """A fixed random dot pattern (one per seed), cast from ``p_emitter_camera``.

    n_dots : dots over the field (a in [-a_max, a_max], b in [-b_max, b_max])
    power : irradiance of a dot's centre at 1 m, in the units of the lamp's (lamp ~1 at 1 m)
    """

    def __init__(self, rng: np.random.Generator, p_emitter_camera: np.ndarray = D415_EMITTER, n_dots: int = 16000,
                 a_max: float = 0.75, b_max: float = 0.58, texel: float = 0.0008, dot_sigma_texels: float = 1.6,
                 power: float = 1.0):
        import cv2

        self.p_emitter = np.asarray(p_emitter_camera, float)
        self.a_max, self.b_max, self.texel, self.power = a_max, b_max, texel, power
        w, h = int(2 * a_max / texel), int(2 * b_max / texel)
        pattern = np.zeros((h, w), np.float32)
        cols = rng.integers(0, w, n_dots)
        rows = rng.integers(0, h, n_dots)
        pattern[rows, cols] = rng.uniform(0.6, 1.0, n_dots)   # dots of uneven brightness, as the DOE's
        pattern = cv2.GaussianBlur(pattern, (0, 0), dot_sigma_texels)
        self.pattern = pattern / pattern.max()

    def irradiance(self, camera: PinholeCamera, depth: np.ndarray) -> np.ndarray:
        """(H, W) dot irradiance on the visible surface (0 where depth is 0 or outside the pattern)."""
        import cv2

        q = camera.pixel_rays() * depth[..., None] - self.p_emitter
        z = np.where(q[..., 2] > 1e-6, q[..., 2], np.nan)
        map_x = ((q[..., 0] / z + self.a_max) / self.texel).astype(np.float32)
        map_y = ((q[..., 1] / z + self.b_max) / self.texel).astype(np.float32)
        dots = cv2.remap(self.pattern, np.nan_to_num(map_x, nan=-10.0), np.nan_to_num(map_y, nan=-10.0),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        d2 = np.sum(q ** 2, axis=-1)
        out = self.power * dots / np.maximum(d2, 1e-4)
        return np.where(depth > 0, out, 0.0)
