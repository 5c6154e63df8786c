"""How far the projected template lands from the plan: lit pixels traced back, and pose errors in mm.

Two measures, both in the bone frame at the TRUE pose, ray casting in numpy
(:func:`app.projector.geometry.ray_mesh_first_hit`, independent of the GL renderer):

- :func:`lit_pixel_errors` (the renderer's accuracy): every lit pixel (u, v) of a projector image
  is traced back along its ray ``K_p^-1 (u, v, 1)`` from the projector's centre to its first hit
  on the bone mesh at the true pose; its error is the distance from that hit to the plan's outline
  polylines. With the true pose used for rendering this is at most half the line width plus the
  pixel footprint (about 0.5 + 0.3 mm for 1 mm lines at 0.42 m, 1280 px).
- :func:`template_error` (what a tracking error costs the surgeon): each outline point p is drawn
  by the projector pixel that sees it at the *estimated* pose; that pixel's ray lands on the bone
  at the *true* pose at q. The displacement |q - p| (mm) is reported per point, with its mean,
  95th percentile and maximum, over the outline points the projector draws at the estimate: hidden
  ones are not drawn, nor are those the surface shows the projector at grazing incidence (beyond
  :data:`app.projector.geometry.MAX_INCIDENCE_DEG`, the renderer's rule), where a 0.1 mm pose error
  moves the line by millimetres. A ray that misses the bone counts as ``miss``; its displacement is
  the distance from p to the ray (a lower bound).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.geometry import se3
from app.projector.geometry import (MAX_INCIDENCE_DEG, distance_to_segments, facing, ray_mesh_first_hit,
                                    surface_normals_at)
from app.projector.model import ProjectorModel
from app.projector.plan import Plan

VISIBILITY_TOLERANCE_M = 0.0015
MAX_TEMPLATE_POINTS = 200


def trace_pixels(uv: np.ndarray, projector: ProjectorModel, T_projector_bone: np.ndarray, vertices: np.ndarray,
                 faces: np.ndarray) -> np.ndarray:
    """Points where the rays of projector pixels ``uv`` (N, 2) first hit the bone; (N, 3) bone frame, NaN = miss."""
    K = projector.K
    d_proj = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))])
    T_bone_projector = se3.inverse(np.asarray(T_projector_bone, dtype=float))
    origin = T_bone_projector[:3, 3]
    d_bone = d_proj @ T_bone_projector[:3, :3].T
    t, _ = ray_mesh_first_hit(origin, d_bone, vertices, faces)
    out = origin + t[:, None] * d_bone
    out[~np.isfinite(t)] = np.nan
    return out


def lit_pixel_errors(image: np.ndarray, plan: Plan, projector: ProjectorModel, T_projector_bone_true: np.ndarray,
                     vertices: np.ndarray, faces: np.ndarray, threshold: int = 32) -> np.ndarray:
    """Distance (metres) from each lit pixel's landing point on the bone to the plan outline.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 projector image; a pixel is lit when any channel > ``threshold``
    T_projector_bone_true : (4, 4) the true pose of the bone in the projector frame

    Returns
    -------
    (L,) float64 metres, one per lit pixel in row-major order; inf where the ray misses the bone
    """
    lit = (image.max(axis=2) if image.ndim == 3 else image) > threshold
    v, u = np.nonzero(lit)
    hits = trace_pixels(np.column_stack([u, v]).astype(float), projector, T_projector_bone_true, vertices, faces)
    a, b = plan.segments()
    err = np.full(len(hits), np.inf)
    ok = np.all(np.isfinite(hits), axis=1)
    if ok.any():
        err[ok] = distance_to_segments(hits[ok], a, b)
    return err


@dataclass(frozen=True)
class TemplateError:
    """Displacement of the projected outline on the bone (millimetres).

    mean_mm, p95_mm, max_mm over the drawn points; n_points drawn, n_missed (rays past the bone),
    n_hidden (outline points hidden from the projector at the estimate, not drawn), n_grazing (seen at
    grazing incidence at the estimate, not drawn).
    """

    mean_mm: float
    p95_mm: float
    max_mm: float
    n_points: int
    n_missed: int
    n_hidden: int
    n_grazing: int = 0


def _subsample(points: np.ndarray, n: int) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.linspace(0, len(points) - 1, n).round().astype(int)]


def template_error(plan: Plan, T_base_bone_est: np.ndarray, T_base_bone_true: np.ndarray, T_base_camera: np.ndarray,
                   projector: ProjectorModel, vertices: np.ndarray, faces: np.ndarray,
                   max_points: int = MAX_TEMPLATE_POINTS, normals: np.ndarray | None = None,
                   max_incidence_deg: float = MAX_INCIDENCE_DEG) -> TemplateError:
    """Projected-template error of an estimated bone pose against the true one (module docstring).

    Parameters
    ----------
    plan : outline on the bone (bone frame)
    T_base_bone_est, T_base_bone_true : (4, 4) estimated and true bone poses, base frame
    T_base_camera : (4, 4) camera pose in the base (robot FK and hand-eye; the same for both)
    projector : K_p, resolution and T_camera_projector
    vertices, faces : the bone mesh (bone frame), as the surface the light lands on
    max_points : outline points used (evenly subsampled), for speed
    normals : (N, 3) the surface normals at those points (:func:`plan_normals`; computed when None)
    max_incidence_deg : points seen more obliquely than this at the estimate are not drawn
    """
    p = _subsample(plan.points(), max_points)
    if normals is None:
        normals = surface_normals_at(p, vertices, faces)
    T_pb_est = projector.T_projector_bone(T_base_camera, T_base_bone_est)
    T_pb_true = projector.T_projector_bone(T_base_camera, T_base_bone_true)
    # which outline points the projector sees at the estimate (and inside its image)
    p_proj = se3.transform_points(T_pb_est, p)
    uv, z = projector.camera.project(p_proj)
    inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < projector.width - 0.5) & \
             (uv[:, 1] >= -0.5) & (uv[:, 1] < projector.height - 0.5)
    T_bp_est = se3.inverse(T_pb_est)
    o_est = T_bp_est[:3, 3]
    t, _ = ray_mesh_first_hit(o_est, p - o_est, vertices, faces)
    visible = inside & (t >= 1.0 - VISIBILITY_TOLERANCE_M / np.linalg.norm(p - o_est, axis=1))
    n_hidden = int(np.count_nonzero(~visible))
    grazing = visible & (facing(normals, p, o_est) < np.cos(np.radians(max_incidence_deg)))
    visible &= ~grazing
    n_grazing = int(np.count_nonzero(grazing))
    if not visible.any():
        return TemplateError(np.nan, np.nan, np.nan, 0, 0, n_hidden, n_grazing)
    # the same projector rays, in the bone frame at the true pose
    d_proj = p_proj[visible]
    T_bp_true = se3.inverse(T_pb_true)
    o_true = T_bp_true[:3, 3]
    d_true = d_proj @ T_bp_true[:3, :3].T
    t, _ = ray_mesh_first_hit(o_true, d_true, vertices, faces)
    target = p[visible]
    hit = np.isfinite(t)
    err = np.empty(len(target))
    err[hit] = np.linalg.norm(o_true + t[hit, None] * d_true[hit] - target[hit], axis=1)
    if (~hit).any():  # distance from the planned point to the ray that missed the bone
        dm = d_true[~hit] / np.linalg.norm(d_true[~hit], axis=1, keepdims=True)
        w = target[~hit] - o_true
        err[~hit] = np.linalg.norm(w - np.sum(w * dm, axis=1, keepdims=True) * dm, axis=1)
    mm = 1000.0 * err
    return TemplateError(float(mm.mean()), float(np.percentile(mm, 95)), float(mm.max()), int(len(mm)),
                         int(np.count_nonzero(~hit)), n_hidden, n_grazing)


def plan_normals(plan: Plan, vertices: np.ndarray, faces: np.ndarray, max_points: int = MAX_TEMPLATE_POINTS) -> np.ndarray:
    """The surface normals at the outline points :func:`template_error` uses (compute once per plan and mesh)."""
    return surface_normals_at(_subsample(plan.points(), max_points), vertices, faces)


def template_error_mm(plan: Plan, T_base_bone_est: np.ndarray, T_base_bone_true: np.ndarray, T_base_camera: np.ndarray,
                      projector: ProjectorModel, vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean displacement (mm) of the projected outline on the bone; NaN when no outline point is drawn."""
    return template_error(plan, T_base_bone_est, T_base_bone_true, T_base_camera, projector, vertices, faces).mean_mm
