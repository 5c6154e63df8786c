"""Whether the bone is seen: the inputs of the recovery's "When" (app/filter/recovery.py).

Import as ``from app.filter.visibility import visible_share, point_visible`` (used by
app/pipeline/recovery_runner.py). ``visible_share``: the share of the model's expected silhouette at
a pose that is not hidden by an occluder (the hand has withdrawn); ``point_visible``: the pointed
point of the one-point initialiser is not behind a hand. Both use the likelihood's occluder rule (DESIGN.md: a
measurement more than ``occluder_margin`` in front of the model is an occluder).
"""
from __future__ import annotations

import numpy as np


def visible_share(refiner, depth: np.ndarray, T_camera_bone: np.ndarray) -> float:
    """The share of the model's expected silhouette at ``T_camera_bone`` (the refiner's z-buffer on its
    grid) whose measurement is valid and not an occluder (not more than ``occluder_margin`` in
    front of the model): 1 on a clear view, ~0.2 under an 80 % hand. NaN when that pose is out of
    the image (no hand can be judged there)."""
    zbuf, _ = refiner.model_depth(T_camera_bone)
    expected = int(np.isfinite(zbuf).sum())
    if expected == 0:
        return float("nan")
    y, _ = refiner.measurements(depth, T_camera_bone)
    return len(y) / expected


def point_visible(camera, depth: np.ndarray, point_camera: np.ndarray, margin: float) -> bool:
    """Whether a point (camera frame, m) projects into the image onto a valid depth that is not
    more than ``margin`` in front of it (the pointed point not hidden by a hand)."""
    if point_camera[2] <= 0:
        return False
    uv, z = camera.project(np.asarray(point_camera, float).reshape(1, 3))
    u, v = int(round(uv[0, 0])), int(round(uv[0, 1]))
    h, w = depth.shape
    if not (0 <= u < w and 0 <= v < h):
        return False
    r0, r1, c0, c1 = max(v - 2, 0), min(v + 3, h), max(u - 2, 0), min(u + 3, w)
    patch = depth[r0:r1, c0:c1]
    patch = patch[np.isfinite(patch) & (patch > 0)]
    return patch.size > 0 and float(np.median(patch)) >= float(z[0]) - margin
