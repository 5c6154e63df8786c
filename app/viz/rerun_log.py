"""Logging osteonav sessions and trials to rerun: entity paths, the blueprint, and typed log calls.

The entity tree is the frame tree (STYLE.md §13): everything under ``world/`` is in the robot base
frame; each child's ``Transform3D`` is ``T_parent_child`` as it is (rerun's default relation). The
mesh, intrinsics and view coordinates (RDF, OpenCV's camera axes) are logged once as static.
Timelines ``stamp`` (seconds, the data's clock) and ``frame`` (the camera's frame counter).

rerun's SDK sends from a background thread, so logging never blocks the loop; a sink that cannot
keep up (for example a viewer that is gone) loses data, not frames of the tracker.

Usage::

    log = RerunLog.to_file("out/log.rrd")            # or RerunLog.spawn()
    log.log_static_scene(camera, mesh_vertices, mesh_faces)
    log.set_frame(frame_id, stamp)
    log.log_camera(T_base_camera, depth_m)
    log.log_bone("estimate", T_base_bone)
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from app.geometry import quaternion as quat
from app.geometry.camera import PinholeCamera

log = logging.getLogger(__name__)

WORLD = "world"
FLANGE = "world/robot/flange"
FLANGE_PATH = "world/robot/flange_path"
CAMERA = "world/camera"
CAMERA_IMAGE = "world/camera/image"
PROJECTOR_IMAGE = "world/camera/projector/image"   # logged by app/projector/rerun_log.py
DEPTH = "world/camera/image/depth"
INFRARED = "world/camera/image/infrared"          # the left imager: the depth camera's own pinhole
COLOR = "world/camera/color"                      # the colour camera: T_depth_color below the depth camera
COLOR_IMAGE = "world/camera/color/image"
BONE_ESTIMATE = "world/bone/estimate"
BONE_GROUNDTRUTH = "world/bone/groundtruth"
PARTICLES = "world/particles"
PROJECTOR = "world/camera/projector"
PLOTS = "plots"

COLORS = {"estimate": (60, 180, 255), "groundtruth": (255, 220, 120), "particles": (255, 90, 90)}
DISPLAY_WIDTH = 320   # depth images are logged at this width (a 640x480 float stream would be ~1 GB/min)


def blueprint():
    """The default layout: the 3D scene, the depth image and the plots at once."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="Scene (robot base frame)", origin=WORLD),
            rrb.Vertical(
                rrb.Tabs(rrb.Spatial2DView(name="Depth camera", origin=CAMERA_IMAGE),
                         rrb.Spatial2DView(name="Colour camera", origin=COLOR_IMAGE)),
                rrb.Spatial2DView(name="Projector", origin=PROJECTOR_IMAGE),
                rrb.TimeSeriesView(name="Tracking", origin=PLOTS),
                row_shares=[2, 2, 2],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def transform(T: np.ndarray):
    """rerun Transform3D of a 4x4 pose T_parent_child (quaternion passed as xyzw at this boundary)."""
    import rerun as rr

    q = quat.from_matrix(T[:3, :3])
    return rr.Transform3D(translation=T[:3, 3], quaternion=rr.Quaternion(xyzw=quat.to_xyzw(q)))


class RerunLog:
    """One rerun recording (a file or a live viewer) with osteonav's entities."""

    def __init__(self, recording, file=None):
        self.rec = recording
        self.file = file

    @classmethod
    def to_file(cls, path: str | Path, application_id: str = "osteonav") -> "RerunLog":
        """A recording written to ``path`` by :class:`app.viz.rrd_file.RrdFile`: a failed write
        (a full disk) is an OutputError from :meth:`close`, never a hang."""
        import rerun as rr

        from app.viz.rrd_file import RrdFile

        rec = rr.RecordingStream(application_id)
        return cls(rec, RrdFile(rec, path, blueprint()))

    @classmethod
    def spawn(cls, application_id: str = "osteonav") -> "RerunLog":
        import rerun as rr

        rec = rr.RecordingStream(application_id)
        rec.spawn(default_blueprint=blueprint())
        return cls(rec)

    def set_frame(self, frame_id: int, stamp: float) -> None:
        self.rec.set_time("frame", sequence=int(frame_id))
        self.rec.set_time("stamp", duration=float(stamp))

    def log_static_scene(self, camera: PinholeCamera, vertices: np.ndarray, faces: np.ndarray,
                         with_groundtruth: bool = True) -> None:
        """Intrinsics (at the display width), view coordinates and the bone meshes, once."""
        import rerun as rr

        display = display_camera(camera)
        self.rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log(CAMERA_IMAGE, rr.Pinhole(image_from_camera=display.K, resolution=[display.width, display.height],
                                              camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.1), static=True)
        normals = _vertex_normals(vertices, faces)
        for name, entity in (("estimate", BONE_ESTIMATE), ("groundtruth", BONE_GROUNDTRUTH)):
            if name == "groundtruth" and not with_groundtruth:
                continue
            self.rec.log(f"{entity}/mesh", rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces,
                                                     vertex_normals=normals, albedo_factor=COLORS[name]), static=True)

    def log_camera(self, T_base_flange: np.ndarray | None, T_base_camera: np.ndarray | None,
                   depth_m: np.ndarray | None) -> None:
        import rerun as rr

        if T_base_flange is not None:
            self.rec.log(FLANGE, transform(T_base_flange))
        if T_base_camera is not None:
            self.rec.log(CAMERA, transform(T_base_camera))
        if depth_m is not None:
            small = downsample_for_display(depth_m)
            self.rec.log(DEPTH, rr.DepthImage(np.round(small * 1000.0).astype(np.uint16), meter=1000.0))

    def log_image_streams(self, streams) -> None:
        """The colour camera's pose in the depth camera (T_depth_color) and its pinhole, once (static).

        streams : :class:`app.image_streams.ImageStreams` or None. The infrared image needs nothing:
        it is logged under the depth camera's own pinhole.
        """
        import rerun as rr

        if streams is None or streams.color is None:
            return
        display = display_camera(streams.color.camera)
        self.rec.log(COLOR, transform(streams.color.T_depth_color), static=True)
        self.rec.log(COLOR_IMAGE, rr.Pinhole(image_from_camera=display.K, resolution=[display.width, display.height],
                                             camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.1), static=True)

    def log_images(self, infrared: np.ndarray | None = None, color: np.ndarray | None = None) -> None:
        """The frame's infrared (H, W) uint8 and colour (Hc, Wc, 3) uint8 RGB, at the display width, JPEG-compressed."""
        import rerun as rr

        if infrared is not None:
            self.rec.log(INFRARED, rr.Image(image_for_display(infrared), color_model="L").compress(jpeg_quality=85))
        if color is not None:
            self.rec.log(COLOR_IMAGE, rr.Image(image_for_display(color), color_model="RGB").compress(jpeg_quality=85))

    def log_flange_path(self, p_base_flange: np.ndarray) -> None:
        import rerun as rr

        self.rec.log(FLANGE_PATH, rr.LineStrips3D([p_base_flange], radii=0.0008), static=True)

    def log_bone(self, which: str, T_base_bone: np.ndarray | None) -> None:
        """The bone mesh at the estimate or the ground truth (``which`` = 'estimate' | 'groundtruth')."""
        import rerun as rr

        entity = BONE_ESTIMATE if which == "estimate" else BONE_GROUNDTRUTH
        if T_base_bone is None:
            self.rec.log(entity, rr.Clear(recursive=False))
        else:
            self.rec.log(entity, transform(T_base_bone))

    def log_particles(self, p_base: np.ndarray, weights: np.ndarray | None = None) -> None:
        import rerun as rr

        self.rec.log(PARTICLES, rr.Points3D(p_base, radii=0.0006, colors=COLORS["particles"]))

    def log_scalar(self, name: str, value: float) -> None:
        import rerun as rr

        if value is not None and np.isfinite(value):
            self.rec.log(f"{PLOTS}/{name}", rr.Scalars(float(value)))

    def log_text(self, name: str, text: str) -> None:
        import rerun as rr

        self.rec.log(f"{PLOTS}/{name}", rr.TextLog(text))

    def close(self) -> None:
        """Flush and disconnect; with a file, raises OutputError when writing it failed."""
        if self.file is not None:
            self.file.close()              # flushes and disconnects
        else:
            self.rec.flush()
            self.rec.disconnect()


def display_camera(camera: PinholeCamera) -> PinholeCamera:
    """The camera model of the depth images as logged (resized to ``DISPLAY_WIDTH``)."""
    width = min(DISPLAY_WIDTH, camera.width)
    height = int(round(camera.height * width / camera.width))
    return camera.resized(width, height)


def image_for_display(image: np.ndarray) -> np.ndarray:
    """An 8-bit infrared or colour image averaged down (area) to ``DISPLAY_WIDTH`` columns."""
    import cv2

    h, w = image.shape[:2]
    if w <= DISPLAY_WIDTH:
        return image
    return cv2.resize(image, (DISPLAY_WIDTH, int(round(h * DISPLAY_WIDTH / w))), interpolation=cv2.INTER_AREA)


def downsample_for_display(depth_m: np.ndarray) -> np.ndarray:
    """Nearest-neighbour downsample of a depth image to ``DISPLAY_WIDTH`` columns."""
    h, w = depth_m.shape
    if w <= DISPLAY_WIDTH:
        return depth_m
    from app.depth_image import downsample_nearest

    return downsample_nearest(depth_m, DISPLAY_WIDTH, int(round(h * DISPLAY_WIDTH / w)))


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)
