"""Log a hand-eye calibration to rerun: the board, and the camera frustum at every capture.

Entity tree (the frame tree, everything in the robot base frame, all static):

    world                          the robot base frame (ViewCoordinates RIGHT_HAND_Z_UP)
    world/board                    Transform3D T_base_board; its outline (LineStrips3D) and corners
    world/captures/000003/flange   Transform3D T_base_flange of capture 3
    world/captures/000003/flange/camera          Transform3D T_flange_camera (the result)
    world/captures/000003/flange/camera/image    Pinhole (K, RDF) + the capture's image
                                                 + detected corners (Points2D)

Each capture also has a ``capture`` sequence timeline entry, with its residuals as scalars
under ``residuals/...``. Transforms are logged as rerun's default relation (parent from child),
i.e. ``T_parent_child`` as it is.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _transform(rr, T: np.ndarray):
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


def log_hand_eye(path: "str | Path", result, K: np.ndarray, width: int, height: int,
                 board_spec: str) -> None:
    """Write ``result`` (``calibration.handeye.HandEyeResult``) to an .rrd file at ``path``."""
    import rerun as rr

    from calibration.board import parse_board_spec

    from app.viz.rrd_file import RrdFile

    rec = rr.RecordingStream("osteonav-calibration")
    rrd = RrdFile(rec, path)
    spec = parse_board_spec(board_spec)
    w, h = spec.size
    chosen = result.chosen
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("world/board", _transform(rr, chosen.T_base_board), static=True)
    outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0], [0, 0, 0]], dtype=np.float64)
    rec.log("world/board/outline", rr.LineStrips3D([outline], colors=[[255, 200, 0]]), static=True)
    sx, sy = spec.squares_x, spec.squares_y
    gx, gy = np.meshgrid(np.arange(1, sx), np.arange(1, sy))
    corners = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) * spec.square_length
    rec.log("world/board/corners", rr.Points3D(corners, radii=0.002), static=True)
    if result.robot_world:
        rec.log("world/board_robot_world", _transform(rr, result.robot_world["T_base_board"]), static=True)
        rec.log("world/board_robot_world/outline",
                rr.LineStrips3D([outline], colors=[[0, 200, 255]]), static=True)
    for k, o in enumerate(result.observations):
        base = f"world/captures/{o.capture:06d}"
        rec.log(f"{base}/flange", _transform(rr, o.T_base_flange), static=True)
        rec.log(f"{base}/flange/camera", _transform(rr, chosen.T_flange_camera), static=True)
        rec.log(f"{base}/flange/camera/image",
                rr.Pinhole(image_from_camera=K, resolution=[width, height],
                           camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.05),
                static=True)
        if o.image is not None:
            rec.log(f"{base}/flange/camera/image", rr.Image(o.image), static=True)
        if o.detection is not None:
            rec.log(f"{base}/flange/camera/image/corners",
                    rr.Points2D(o.detection.corners_px, radii=2.0, colors=[[0, 255, 0]]), static=True)
        rec.set_time("capture", sequence=int(o.capture))
        rec.log("residuals/rotation_deg", rr.Scalars(float(chosen.rotation_deg[k])))
        rec.log("residuals/translation_mm", rr.Scalars(float(chosen.translation_mm[k])))
        if np.isfinite(chosen.reprojection_px[k]):
            rec.log("residuals/reprojection_px", rr.Scalars(float(chosen.reprojection_px[k])))
    rrd.close()      # flushes, disconnects; OutputError when the file could not be written (a full disk)
