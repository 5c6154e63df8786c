"""Per-run scores that app/metrics.py does not hold: jitter over static ground truth, VSD per frame."""
from __future__ import annotations

from pathlib import Path

import numpy as np

VSD_RESOLUTION = (160, 120)
JITTER_SETTLE_S = 0.5
STATIC_TRANSLATION_M = 1e-6
STATIC_ROTATION_RAD = 1e-5


def static_pairs(T_gt: np.ndarray, stamps: np.ndarray, settle_s: float = JITTER_SETTLE_S) -> np.ndarray:
    """(N,) bool: frame k and k-1 have equal ground-truth poses and k is past the settling time."""
    from app.geometry import se3

    T_gt = np.asarray(T_gt)
    mask = np.zeros(len(T_gt), dtype=bool)
    if len(T_gt) < 2:
        return mask
    moved_t = np.linalg.norm(T_gt[1:, :3, 3] - T_gt[:-1, :3, 3], axis=1)
    moved_r = np.asarray(se3.rotation_angle(T_gt[1:], T_gt[:-1]))
    mask[1:] = (moved_t < STATIC_TRANSLATION_M) & (moved_r < STATIC_ROTATION_RAD)
    mask &= np.asarray(stamps) - stamps[0] >= settle_s
    return mask


REST_DELAY_S = 0.3   # issue 12: back within 1 mm ADD 0.3 s after the bone comes to rest


def _last_motion(T_gt: np.ndarray, t: np.ndarray) -> int | None:
    """Index of the last frame whose ground truth differs from the previous one; None when it never moves."""
    moving = ~static_pairs(T_gt, np.asarray(t), settle_s=0.0)
    moving[0] = False
    return int(np.nonzero(moving)[0][-1]) if moving.any() else None


def after_rest(T_gt: np.ndarray, t: np.ndarray, add_mm: np.ndarray, delay_s: float = REST_DELAY_S) -> dict | None:
    """The error once a moved bone has come to rest: ``rest_s`` (time of the last frame whose
    ground truth differs from the previous one), and the max / median ADD over the frames from
    ``rest_s + delay_s`` on. None when the bone never moves (or is still moving at the end)."""
    rest = _last_motion(T_gt, t)
    if rest is None:
        return None
    rest_s = float(t[rest])
    late = np.asarray(t) >= rest_s + delay_s
    if not late.any():
        return None
    return {"rest_s": rest_s, "delay_s": delay_s, "max_add_mm": float(np.max(add_mm[late])),
            "median_add_mm": float(np.median(add_mm[late])), "frames": int(late.sum())}


REFOUND_ADD_MM = 2.0       # issue 12: a lost track found again = ADD < 2 mm ...
VISIBLE_SHARE = 0.2        # ... within 2 s of the bone being visible (this share of its vertices in view) and still


def in_view_share(T_base_camera: np.ndarray, T_base_bone: np.ndarray, points_bone: np.ndarray, camera) -> np.ndarray:
    """(N,) the share of the mesh's points (bone frame) that project into the image in front of the
    camera at the ground truth (occluders not counted: a hand over the bone leaves it in view); 0 on
    frames without a camera pose."""
    out = np.zeros(len(T_base_bone))
    for i, (T_bc, T_bb) in enumerate(zip(T_base_camera, T_base_bone)):
        if not np.all(np.isfinite(T_bc)):
            continue
        T_camera_bone = np.linalg.inv(T_bc) @ T_bb
        uv, z = camera.project(points_bone @ T_camera_bone[:3, :3].T + T_camera_bone[:3, 3])
        inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < camera.width - 0.5) & \
                 (uv[:, 1] >= -0.5) & (uv[:, 1] < camera.height - 0.5)
        out[i] = float(np.mean(inside))
    return out


def refound(T_gt: np.ndarray, t: np.ndarray, add_mm: np.ndarray, in_view: np.ndarray,
            threshold_mm: float = REFOUND_ADD_MM, visible_share: float = VISIBLE_SHARE) -> dict | None:
    """Issue 12's "lost track found again": from the first frame at or after the bone's last motion
    (``rest_s``, as :func:`after_rest`) on which it is in view (``in_view`` >= ``visible_share``;
    ``visible_s``) to the first frame from which ADD stays below ``threshold_mm`` to the end
    (``refound_s``: 0 when it never left; None when the last frame is off or the bone is never in view
    after rest). None when the bone never moves (or is still moving at the end)."""
    t = np.asarray(t, float)
    rest = _last_motion(T_gt, t)
    if rest is None or rest == len(t) - 1:
        return None
    seen = np.nonzero(np.asarray(in_view)[rest:] >= visible_share)[0]
    out = {"rest_s": float(t[rest]), "visible_s": None, "refound_s": None, "threshold_mm": threshold_mm}
    if len(seen) == 0:
        return out
    k_vis = rest + int(seen[0])
    out["visible_s"] = float(t[k_vis])
    off = np.nonzero(~(np.asarray(add_mm)[k_vis:] < threshold_mm))[0]
    if len(off) and k_vis + int(off[-1]) == len(t) - 1:
        return out
    k_found = k_vis + (int(off[-1]) + 1 if len(off) else 0)
    out["refound_s"] = float(t[k_found] - t[k_vis])
    return out


def jitter(T_est: np.ndarray, pairs: np.ndarray) -> dict:
    """RMS frame-to-frame change of the estimate over ``pairs`` (frames k with k-1): mm and deg."""
    from app.geometry import se3

    idx = np.nonzero(pairs)[0]
    idx = idx[idx >= 1]
    if len(idx) == 0:
        return {"translation_mm": float("nan"), "rotation_deg": float("nan"), "pairs": 0}
    dt = np.linalg.norm(T_est[idx, :3, 3] - T_est[idx - 1, :3, 3], axis=1)
    dr = np.asarray(se3.rotation_angle(T_est[idx], T_est[idx - 1]))
    return {"translation_mm": float(1e3 * np.sqrt(np.mean(dt ** 2))),
            "rotation_deg": float(np.rad2deg(np.sqrt(np.mean(dr ** 2)))), "pairs": int(len(idx))}


def vsd_series(trial_dir: str | Path, T_est: np.ndarray, n: int, resolution=VSD_RESOLUTION) -> np.ndarray:
    """e_VSD of the first ``n`` frames: the trial's mesh rendered at the estimate and the truth."""
    from app import metrics
    from app.depth_image import downsample_nearest
    from app.geometry import se3
    from app.render.context import shared_context
    from app.render.scene import SceneRenderer
    from app.trial.reader import open_trial

    reader = open_trial(trial_dir)
    camera = reader.meta.camera.resized(*resolution)
    mesh = reader.load_mesh()
    T_base_camera, valid = reader.camera_poses()
    renderer = SceneRenderer(shared_context(), camera)
    renderer.add_mesh("bone", np.asarray(mesh.vertices), np.asarray(mesh.faces), 1)
    out = np.full(n, np.nan)
    try:
        for i in range(n):
            if not valid[i]:
                continue
            T_camera_base = se3.inverse(T_base_camera[i])
            d_est, _ = renderer.render({"bone": T_camera_base @ T_est[i]})
            d_gt, _ = renderer.render({"bone": T_camera_base @ reader.groundtruth[i]})
            measured = downsample_nearest(reader.read_depth(i), *resolution)
            out[i] = metrics.vsd(d_est, d_gt, measured, K=camera.K)
    finally:
        renderer.release()
    return out
