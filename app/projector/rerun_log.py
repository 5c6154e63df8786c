"""The projector in rerun: its frustum (pinhole) under the camera, and the image it shows.

Entities (the entity tree is the frame tree, STYLE.md §13; ``PROJECTOR`` comes from
app/viz/rerun_log.py, a child of the depth camera ``world/camera``):

- ``world/camera/projector``        Transform3D = T_camera_projector (static: the rig is rigid)
- ``world/camera/projector/image``  Pinhole of K_p at the logged size, RDF (static) -> the frustum
                                    in the 3D view; and each frame's projector image (JPEG-compressed,
                                    ``DISPLAY_WIDTH`` columns, so a long session stays small)

Usage::

    from app.projector.rerun_log import log_projector_static, log_projector_image
    log_projector_static(rec, projector)          # once
    rec.set_time(...); log_projector_image(rec, image)   # each frame

``rec`` is a ``rerun.RecordingStream`` (``RerunLog.rec``) or None for the process default.
"""
from __future__ import annotations

import numpy as np

from app.projector.model import ProjectorModel
from app.viz.rerun_log import PROJECTOR, transform

PROJECTOR_IMAGE = f"{PROJECTOR}/image"
DISPLAY_WIDTH = 320
JPEG_QUALITY = 85


def _display_size(projector: ProjectorModel) -> tuple[int, int]:
    w = min(DISPLAY_WIDTH, projector.width)
    return w, int(round(projector.height * w / projector.width))


def log_projector_static(rec, projector: ProjectorModel, image_plane_distance: float = 0.42) -> None:
    """T_camera_projector and the projector's pinhole (its frustum reaches ``image_plane_distance`` metres)."""
    import rerun as rr

    w, h = _display_size(projector)
    small = projector.camera.resized(w, h)
    log = rec.log if rec is not None else rr.log
    log(PROJECTOR, transform(projector.T_camera_projector), static=True)
    log(PROJECTOR_IMAGE, rr.Pinhole(image_from_camera=small.K, resolution=[w, h], camera_xyz=rr.ViewCoordinates.RDF,
                                    image_plane_distance=image_plane_distance), static=True)


def log_projector_image(rec, image: np.ndarray) -> None:
    """The projector image of the current frame (resized to DISPLAY_WIDTH, JPEG)."""
    import cv2
    import rerun as rr

    h, w = image.shape[:2]
    if w > DISPLAY_WIDTH:
        # INTER_AREA keeps one-pixel lines visible (max-pool would be stricter; area is enough at 4x)
        small = cv2.resize(image, (DISPLAY_WIDTH, int(round(h * DISPLAY_WIDTH / w))), interpolation=cv2.INTER_AREA)
        small = np.clip(small.astype(np.float32) * 2.0, 0, 255).astype(np.uint8) if w >= 2 * DISPLAY_WIDTH else small
    else:
        small = image
    entity = rr.Image(np.ascontiguousarray(small), color_model="RGB").compress(jpeg_quality=JPEG_QUALITY)
    (rec.log if rec is not None else rr.log)(PROJECTOR_IMAGE, entity)
