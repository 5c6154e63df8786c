"""Simulated camera images: the infrared (left imager) and colour images of a simulated frame.

An imager turns scene radiance (:mod:`app.sim.appearance`) into 8-bit pixels:
``v = clip(e * L * vignetting)``, with shot and read noise ``sigma^2 = g v + r^2``, then the
transfer curve (sRGB-like gamma 1/2.2 for colour, linear for infrared), rounded to uint8.
``e`` is the auto-exposure: ``e <- e (target / mean)^alpha`` after each frame (it lags a change of
light by a few frames, as real auto-exposure does; the first frame finds it settled); highlights
above 1 saturate.
Vignetting is ``cos^4`` of the angle off the optical axis.

:class:`ImageSimulator` holds the colour camera (its own K and ``T_depth_color``, the D415's RGB
module about 15 mm beside the left imager; rectified, no distortion), the dot projector and both
imagers' exposure states for one trial.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.image_streams import ColorStream, ImageStreams, InfraredStream
from app.sim.appearance import OperatingField
from app.sim.ir import DotProjector

# the D415's RGB module at 640x480 (its own K) and its pose in the left imager's (depth) optical frame
D415_COLOR_640x480 = PinholeCamera(np.array([[616.4, 0.0, 322.1], [0.0, 616.7, 238.6], [0.0, 0.0, 1.0]]), 640, 480)
D415_T_DEPTH_COLOR = se3.from_rotvec_trans(np.array([0.0021, -0.0034, 0.0012]), np.array([0.0147, 0.0001, 0.0003]))
STREAM_NAMES = ("depth", "ir", "color")


def parse_streams(text: str) -> tuple[str, ...]:
    """``'depth,ir,color'`` -> ('depth', 'ir', 'color'); depth is required; ValueError naming the fix."""
    names = tuple(dict.fromkeys(s.strip().lower() for s in str(text).split(",") if s.strip()))
    unknown = [n for n in names if n not in STREAM_NAMES]
    if unknown or "depth" not in names:
        raise ValueError(f"streams {text!r}: expected a comma-separated subset of {','.join(STREAM_NAMES)} that "
                         f"includes depth (e.g. depth,ir,color){'; unknown: ' + ', '.join(unknown) if unknown else ''}")
    return names


@dataclass
class Imager:
    """An 8-bit imager with auto-exposure (see the module docstring)."""

    gamma: float = 1.0
    target: float = 0.35      # mean linear level auto-exposure aims for
    alpha: float = 0.35       # auto-exposure step (1 = instant)
    gain_noise: float = 0.0004
    read_noise: float = 0.003
    exposure: float | None = None   # None: settled on the first frame (the camera ran before the recording)
    blur_px: float = 0.0

    def capture(self, radiance: np.ndarray, camera: PinholeCamera, rng: np.random.Generator) -> np.ndarray:
        """uint8 image of ``radiance`` ((H, W) or (H, W, 3) linear); updates the exposure afterwards."""
        import cv2

        rays = camera.pixel_rays()
        cos4 = (1.0 / np.sum(rays ** 2, axis=-1)) ** 2       # cos^4 of the off-axis angle
        v = radiance * (cos4[..., None] if radiance.ndim == 3 else cos4)
        if self.exposure is None:
            self.exposure = self.target / max(float(np.mean(np.clip(v, 0.0, None))), 1e-6)
        v = self.exposure * v
        if self.blur_px > 0:
            v = cv2.GaussianBlur(v.astype(np.float32), (0, 0), self.blur_px)
        v = np.clip(v, 0.0, None)
        v = v + rng.standard_normal(v.shape) * np.sqrt(self.gain_noise * v + self.read_noise ** 2)
        v = np.clip(v, 0.0, 1.0)
        mean = float(np.mean(v))
        if mean > 1e-4:
            self.exposure *= (self.target / mean) ** self.alpha
        return np.round(255.0 * v ** (1.0 / self.gamma)).astype(np.uint8)


@dataclass
class ImageSimulator:
    """The infrared and/or colour images of each simulated frame (one per trial; stateful exposure)."""

    scene: OperatingField
    depth_camera: PinholeCamera
    rng: np.random.Generator
    emitter: bool = True
    with_ir: bool = True
    with_color: bool = True
    color_camera: PinholeCamera = D415_COLOR_640x480
    T_depth_color: np.ndarray = field(default_factory=lambda: D415_T_DEPTH_COLOR.copy())
    ir_imager: Imager = field(default_factory=lambda: Imager(gamma=1.0, target=0.22))
    color_imager: Imager = field(default_factory=lambda: Imager(gamma=2.2, target=0.25, blur_px=0.6))

    def __post_init__(self):
        self.projector = DotProjector(self.rng) if self.with_ir else None

    @property
    def streams(self) -> ImageStreams:
        return ImageStreams(InfraredStream(self.emitter) if self.with_ir else None,
                            ColorStream(self.color_camera, np.zeros(5), self.T_depth_color) if self.with_color else None)

    def infrared(self, depth: np.ndarray, labels: np.ndarray, T_camera_object: dict, T_camera_base: np.ndarray,
                 t: float) -> np.ndarray:
        """(H, W) uint8 left-imager image from the exact rendered depth and labels of the depth camera."""
        rows = self.scene.material_image(depth, labels, self.depth_camera, T_camera_object)
        _, nir = self.scene.radiance(self.depth_camera, depth, labels, T_camera_object, T_camera_base, t, rows=rows)
        if self.emitter:
            nir = nir + rows[..., 3] * self.projector.irradiance(self.depth_camera, depth)
        return self.ir_imager.capture(nir, self.depth_camera, self.rng)

    def color(self, render, poses: dict[str, np.ndarray], label_of: dict[str, int], T_camera_base: np.ndarray,
              t: float) -> np.ndarray:
        """(Hc, Wc, 3) uint8 RGB seen by the colour camera.

        render : ``render(T_color_object by name) -> (depth, labels)`` in the colour camera
        poses : T_camera_object (depth camera frame) by object name; label_of : each name's label
        """
        T_color_depth = se3.inverse(self.T_depth_color)
        T_color_object = {name: T_color_depth @ T for name, T in poses.items()}
        depth, labels = render(T_color_object)
        by_label = {label_of[name]: T for name, T in T_color_object.items()}
        rgb, _ = self.scene.radiance(self.color_camera, depth, labels, by_label, T_color_depth @ T_camera_base, t)
        return self.color_imager.capture(rgb, self.color_camera, self.rng)
