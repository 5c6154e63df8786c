"""What a camera's image streams are (infrared, colour): the constant description a trial or a session carries.

Import as ``from app.image_streams import ImageStreams, InfraredStream, ColorStream``.

RECORDING_FORMAT.md, version 1.1:

- **infrared** is the D415's left imager, which *is* the depth frame: same size, same K, no
  registration (the depth map is computed in the left imager's rectified frame). 8-bit grey.
  ``emitter`` says whether the IR dot projector was on (a ChArUco board is cleaner with it off).
- **colour** is kept in its own optical frame with its own pinhole ``camera``, its ``distortion``
  (OpenCV order k1, k2, p1, p2, k3) and ``T_depth_color`` (the colour optical frame in the depth
  optical frame: ``p_depth = T_depth_color @ p_color``); or, with ``aligned_to_depth``, registered
  to the depth image by the SDK's align (then it has the depth camera's size and K and no
  extrinsics). osteonav's own sources deliver it unaligned: aligning resamples the colour image
  through the noisy depth, which smears edges exactly where a board's corners are.

The per-frame pixels travel in :class:`app.interfaces.DepthFrame` (``infrared``, ``color``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.geometry.camera import PinholeCamera


@dataclass(frozen=True)
class InfraredStream:
    """The depth camera's own left imager (same size and K as depth); 8-bit grey per frame."""

    emitter: bool = True


@dataclass(frozen=True, eq=False)
class ColorStream:
    """The colour camera: its pinhole, distortion and pose in the depth optical frame (or aligned to depth).

    camera : PinholeCamera of the colour images (the depth camera's when ``aligned_to_depth``)
    distortion : (5,) k1, k2, p1, p2, k3 (OpenCV order); zeros when rectified or aligned
    T_depth_color : (4, 4) colour optical frame in the depth optical frame, metres (identity when aligned)
    aligned_to_depth : True when each colour image is registered to the depth image
    """

    camera: PinholeCamera
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))
    T_depth_color: np.ndarray = field(default_factory=lambda: np.eye(4))
    aligned_to_depth: bool = False

    def __post_init__(self):
        object.__setattr__(self, "distortion", np.asarray(self.distortion, dtype=float).reshape(5))
        object.__setattr__(self, "T_depth_color", np.asarray(self.T_depth_color, dtype=float).reshape(4, 4))


@dataclass(frozen=True)
class ImageStreams:
    """The image streams a camera delivers besides depth (None = not delivered)."""

    infrared: InfraredStream | None = None
    color: ColorStream | None = None

    @property
    def names(self) -> tuple[str, ...]:
        """('ir', 'color') for the streams present, in that order."""
        return tuple(n for n, s in (("ir", self.infrared), ("color", self.color)) if s is not None)

    def __bool__(self) -> bool:
        return self.infrared is not None or self.color is not None


def check_frame_images(streams: ImageStreams, depth_shape: tuple[int, int], infrared, color, where: str) -> None:
    """Raise ValueError unless ``infrared``/``color`` match ``streams`` (presence, dtype uint8, size)."""
    if streams.infrared is not None:
        if infrared is None:
            raise ValueError(f"{where}: the infrared stream is declared but the frame has no infrared image")
        ir = np.asarray(infrared)
        if ir.dtype != np.uint8 or ir.shape != tuple(depth_shape):
            raise ValueError(f"{where}: infrared must be uint8 of the depth image's shape {tuple(depth_shape)}, "
                             f"got {ir.dtype} {ir.shape}")
    if streams.color is not None:
        if color is None:
            raise ValueError(f"{where}: the colour stream is declared but the frame has no colour image")
        c = np.asarray(color)
        cam = streams.color.camera
        if c.dtype != np.uint8 or c.shape != (cam.height, cam.width, 3):
            raise ValueError(f"{where}: colour must be uint8 RGB of shape {(cam.height, cam.width, 3)}, "
                             f"got {c.dtype} {c.shape}")
