"""What the surgeon sees in a bench run: the projected template's error on the real bone.

The product's promise is a template within about a millimetre of its plan on the bone, or no
template. The base-frame ADD measures the tracker; this measures the light on the bone. They differ
when the rig's calibration is off: the projector is rigid to the camera and draws with the camera
pose the tracker believes, so a hand-eye error moves the whole base frame and the template with it.

For each frame with status ok (the projector's gate shows the template only then; its staleness
limit is not modelled: a replay's estimate has no age), :func:`app.projector.accuracy.template_error`
traces the plan's outline through the projector (configs/projector.yaml's model; its plan, or one of
the configured shape derived on this mesh's ridge as a replay does) at the estimate (the points it
draws: not hidden, not at grazing incidence, as the renderer), and lands the
same rays on the bone at the true pose *as the measured camera sees it*
(:func:`app.sim.truth.bone_seen`, eq. S1; the true camera poses from :func:`app.sim.truth.true_camera_poses`).

Also ``add_camera_mm``: the ADD against that same seen pose on every frame, the tracker's error in
the camera frame (equal to the base-frame ADD when the calibration is exact).
"""
from __future__ import annotations

import numpy as np

from app import metrics

OUTLINE_OFF_MM = 2.0   # an ok frame whose outline lands farther than this somewhere is counted


def template_scores(reader, T_est: np.ndarray, statuses, n: int, every: int = 1) -> dict:
    """Scores of the first ``n`` frames of an open trial ``reader`` with estimates ``T_est`` (n, 4, 4).

    Returns ``{"camera_truth": source, "plan": name, "add_camera_mm": summary, "ok_frames_scored": k,
    "outline_mean_mm": summary over ok frames of the per-frame mean, "outline_max_mm": the largest
    displacement on any ok frame, "ok_frames_outline_over_2mm": count}`` (summaries as
    :func:`app.metrics.summarise`). ``every``: score every k-th ok frame (the ADD takes them all).
    """
    from app.projector.accuracy import plan_normals, template_error
    from app.sim.truth import bone_seen, true_camera_poses

    mesh = reader.load_mesh()
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    projector, plan = _projector_and_plan(vertices, faces)
    T_measured, valid = reader.camera_poses()
    T_true, source = true_camera_poses(reader)
    gt = np.asarray(reader.groundtruth[:n])
    with_pose = np.asarray(valid[:n]) & np.all(np.isfinite(T_true[:n]), axis=(1, 2))
    T_seen = np.full((n, 4, 4), np.nan)
    T_seen[with_pose] = bone_seen(T_measured[:n][with_pose], T_true[:n][with_pose], gt[with_pose])
    add_camera = np.full(n, np.nan)
    for i in np.nonzero(with_pose & np.all(np.isfinite(T_est[:n]), axis=(1, 2)))[0]:
        add_camera[i] = 1e3 * metrics.add(T_est[i], T_seen[i], vertices)
    ok = np.array([s == "ok" for s in statuses[:n]]) & with_pose
    means, maxes = [], []
    normals = plan_normals(plan, vertices, faces)
    for i in np.nonzero(ok)[0][::max(int(every), 1)]:
        e = template_error(plan, T_est[i], T_seen[i], T_measured[i], projector, vertices, faces, normals=normals)
        if e.n_points:
            means.append(e.mean_mm)
            maxes.append(e.max_mm)
    maxes = np.asarray(maxes, float)
    return {"camera_truth": source, "plan": plan.name, "add_camera_mm": metrics.summarise(add_camera),
            "ok_frames_scored": len(means), "outline_mean_mm": metrics.summarise(means),
            "outline_max_mm": float(maxes.max()) if len(maxes) else float("nan"),
            "ok_frames_outline_over_2mm": int(np.sum(maxes > OUTLINE_OFF_MM))}


def _projector_and_plan(vertices: np.ndarray, faces: np.ndarray):
    """configs/projector.yaml's projector and plan, derived on this mesh when it does not fit (no
    warning: the bench's table names the plan, ``derived ...`` when it was)."""
    from app.projector.config import DEFAULT_CONFIG, build_plan, load_projector_config

    cfg = load_projector_config(DEFAULT_CONFIG)
    return cfg.projector, build_plan(cfg, vertices, faces, derive=True, quiet=True)
