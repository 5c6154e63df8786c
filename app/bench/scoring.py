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


def after_rest(T_gt: np.ndarray, t: np.ndarray, add_mm: np.ndarray, delay_s: float = REST_DELAY_S) -> dict | None:
    """The error once a moved bone has come to rest: ``rest_s`` (time of the last frame whose
    ground truth differs from the previous one), and the max / median ADD over the frames from
    ``rest_s + delay_s`` on. None when the bone never moves (or is still moving at the end)."""
    moving = ~static_pairs(T_gt, np.asarray(t), settle_s=0.0)
    moving[0] = False
    if not moving.any():
        return None
    rest_s = float(t[np.nonzero(moving)[0][-1]])
    late = np.asarray(t) >= rest_s + delay_s
    if not late.any():
        return None
    return {"rest_s": rest_s, "delay_s": delay_s, "max_add_mm": float(np.max(add_mm[late])),
            "median_add_mm": float(np.median(add_mm[late])), "frames": int(late.sum())}


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
