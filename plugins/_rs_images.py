"""The RealSense plugin's image streams: what to enable, how to describe them, how to pair them with depth.

- :func:`parse_stream_names`: the session's ``streams: depth,ir,color`` (depth required).
- :func:`describe_streams`: :class:`app.image_streams.ImageStreams` of a started pipeline: the
  infrared stream (index 1, the left imager: the depth frame itself) with the emitter state, and
  the colour stream's own intrinsics, distortion and ``T_depth_color`` (the inverse of the SDK's
  depth -> colour extrinsics, whose rotation is column-major: ``p_color = R p_depth + t``).
- :class:`FramePairer`: a pipeline's syncer hands over a frameset whenever any stream delivers,
  holding the others' latest frames, so one depth frame arrives in several sets and an image may
  come a set later. The pairer keeps the latest frame of each image stream and emits each depth
  frame once, when every enabled image stream has caught up with its timestamp, with the image
  whose timestamp is within half a frame period (else None: the recorder counts such frames).
"""
from __future__ import annotations

import logging

import numpy as np

from app.errors import ConfigError
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.image_streams import ColorStream, ImageStreams, InfraredStream

log = logging.getLogger(__name__)

NAMES = ("depth", "ir", "color")


def parse_stream_names(text: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(s.strip().lower() for s in str(text).split(",") if s.strip()))
    if "depth" not in names or any(n not in NAMES for n in names):
        raise ConfigError("camera.params.streams", f"expected a comma-separated subset of {','.join(NAMES)} that "
                                                   f"includes depth (e.g. depth,ir,color), got {text!r}")
    return names


def describe_streams(rs, profile, names: tuple[str, ...], emitter: bool | None) -> ImageStreams:
    """The image streams of the started ``profile`` (see the module docstring)."""
    infrared = color = None
    if "ir" in names:
        if emitter is None:
            sensor = profile.get_device().first_depth_sensor()
            emitter = bool(sensor.get_option(rs.option.emitter_enabled)) if sensor.supports(rs.option.emitter_enabled) else True
        infrared = InfraredStream(emitter=bool(emitter))
    if "color" in names:
        cprof = profile.get_stream(rs.stream.color).as_video_stream_profile()
        intr = cprof.get_intrinsics()
        K = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])
        ext = profile.get_stream(rs.stream.depth).get_extrinsics_to(cprof)
        T_color_depth = se3.make_pose(np.array(ext.rotation).reshape(3, 3).T, np.array(ext.translation))
        distortion = np.array(list(intr.coeffs)[:5], float)
        if intr.model not in (rs.distortion.brown_conrady, rs.distortion.inverse_brown_conrady, rs.distortion.none):
            log.warning("RealSense colour distortion model %s is stored as OpenCV's k1, k2, p1, p2, k3", intr.model)
        color = ColorStream(PinholeCamera(K, intr.width, intr.height), distortion, se3.inverse(T_color_depth))
    return ImageStreams(infrared, color)


class FramePairer:
    """Pair each depth frame with the infrared / colour frames of the same instant (module docstring).

    ``add(depth, infrared, color)`` takes a frameset's frames as ``(timestamp_ms, number, array)`` or
    None and returns the completed ``(depth, infrared_array | None, color_array | None)`` tuples.
    """

    def __init__(self, streams: ImageStreams, fps: float):
        self.wanted = streams.names
        self.tol_ms = 500.0 / fps
        self.latest: dict[str, tuple] = {}
        self.pending = None
        self._last_depth = None

    def add(self, depth, infrared=None, color=None) -> list:
        out = []
        for name, frame in (("ir", infrared), ("color", color)):
            if frame is not None and name in self.wanted:
                self.latest[name] = frame
        if depth is not None and (depth[0], depth[1]) != self._last_depth:
            self._last_depth = (depth[0], depth[1])
            if self.pending is not None:
                out.append(self._emit())   # a newer depth frame came first: pair the old one with what is here
            self.pending = depth
        if self.pending is not None and all(n in self.latest and self.latest[n][0] >= self.pending[0] - self.tol_ms
                                            for n in self.wanted):
            out.append(self._emit())
        return out

    def flush(self) -> list:
        return [self._emit()] if self.pending is not None else []

    def _emit(self):
        depth, self.pending = self.pending, None
        images = []
        for name in ("ir", "color"):
            frame = self.latest.get(name)
            ok = name in self.wanted and frame is not None and abs(frame[0] - depth[0]) <= self.tol_ms
            images.append(frame[2] if ok else None)
        return depth, images[0], images[1]
