"""``osteonav replay``: the application loop over a recorded trial.

For each frame: the joints interpolated at the frame's stamp give ``T_base_camera`` (FK and the
trial's hand-eye); the depth image is reduced to the filter's resolution; the particle filter
(started at the trial's ``initial_pose``, or with ``init.method: point`` by the one-point
initialiser from its ``point_prior`` on the first frame; the summary's ``init`` block gives that
run) steps; the estimate goes to the sinks. Writes, in ``out``:

- ``estimate.txt``: TUM, the bone in the robot base frame, one row per processed frame;
- ``status.csv``: ``stamp,status`` per processed frame (RECORDING_FORMAT.md);
- ``summary.json``: frames, processing rate and, with ground truth, ADD / translation / rotation
  errors (median, p95, max), the lost fraction and the dangerous frames (status ok, error > 5 mm);
- ``log.rrd``: camera and depth, the mesh at the estimate and the ground truth, particles, plots,
  and the projector: its frustum and the image it would show (the template when the status is
  ok, the warning pattern otherwise; app/projector/view.py);
- ``projector/NNNNNN.png``: the projector images, with ``projector_images=True``.

The projector (``projector=True``, configuration ``configs/projector.yaml`` or
``projector_config``) is rendered every ``projector_every``-th frame at the tracked pose; with
ground truth, the summary's ``projector`` block gives the template error: how far the lit outline,
traced back onto the bone at its true pose, lands from the plan (mean / p95 / max mm over the
frames where the template was shown; app/projector/accuracy.py).
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app import metrics
from app.config import TrackerConfig, load_config
from app.errors import MeshError
from app.pipeline.tracker import DepthTracker, tracker_report, use_plan

log = logging.getLogger(__name__)

LOST_ADD_M = 1e-3 * metrics.LOST_ADD_MM            # app/metrics.py: defined once
DANGEROUS_ADD_M = 1e-3 * metrics.DANGEROUS_ADD_MM


@dataclass
class ReplayResult:
    summary: dict
    stamps: np.ndarray
    T_base_bone: np.ndarray
    statuses: list[str]
    errors: dict = field(default_factory=dict)


def replay(trial_dir: str | Path, out_dir: str | Path | None, config: TrackerConfig | None = None,
           realtime: bool = False, rrd: bool = True, progress=None, max_frames: int | None = None,
           make_tracker=None, projector: bool = True, projector_config: str | Path | None = None,
           projector_every: int = 3, projector_images: bool = False) -> ReplayResult:
    """Run the tracker over a trial; write the outputs listed in the module docstring to ``out_dir``.

    ``make_tracker(mesh, camera) -> tracker`` replaces the particle filter by another tracker with
    the same interface (``start``, ``process``, ``particle_positions``, ``mean_timings_ms``,
    ``release``, ``mesh_vertices``/``mesh_faces``/``gl_description``/``T_flange_camera``), e.g. the
    ICP baseline (app/baselines/icp.py); ``config`` then only names the run in the summary.
    """
    from app.trial.reader import open_trial
    from app.trial.tum import write_status_csv, write_tum

    config = config or load_config(None)
    reader = open_trial(trial_dir)
    from_point = make_tracker is None and config.init_method == "point"
    _check_start(reader, Path(trial_dir), from_point)
    mesh = reader.load_mesh()
    if make_tracker is None:
        tracker = DepthTracker(config, mesh, reader.meta.camera)
    else:
        tracker = make_tracker(mesh, reader.meta.camera)
    if from_point:
        tracker.start_from_point(reader.meta.point_prior)
    else:
        tracker.start(reader.meta.initial_pose)
    getattr(tracker, "set_point_prior", lambda p: None)(reader.meta.point_prior)   # the recovery's point
    T_base_camera, pose_valid = reader.camera_poses()
    out = Path(out_dir) if out_dir else None
    sink = None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        if rrd:
            from app.viz.rerun_log import RerunLog

            sink = RerunLog.to_file(out / "log.rrd")
            sink.log_static_scene(reader.meta.camera, tracker.mesh_vertices, tracker.mesh_faces,
                                  with_groundtruth=reader.groundtruth is not None)
            sink.log_text("backend", tracker.gl_description)
    points = np.asarray(mesh.vertices)
    projector_sink, projector_skipped = None, None
    if projector and out is not None:
        from app.projector.sink import ProjectorSink

        try:   # a plan that does not fit this trial's mesh is replaced by one derived from it (never a failed replay)
            projector_sink = ProjectorSink.from_config(projector_config, np.asarray(mesh.vertices),
                                                       np.asarray(mesh.faces), rec=sink.rec if sink is not None else None,
                                                       png_dir=out / "projector" if projector_images else None,
                                                       error_every=2, derive_plan=True)
        except MeshError as exc:
            log.warning("projector skipped: no plan fits this trial's mesh (%s)", exc)
            projector_skipped = str(exc)
    use_plan(tracker, projector_sink.plan if projector_sink is not None else None)   # the status's template points
    stamps, estimates, statuses, add_mm, trans_mm, rot_deg = [], [], [], [], [], []
    t_start = time.perf_counter()
    wall0, stamp0 = time.perf_counter(), None
    n_total = len(reader.stamps) if max_frames is None else min(max_frames, len(reader.stamps))
    for frame in reader.iter_frames():
        i = frame.index
        if i >= n_total:
            break
        if realtime:
            stamp0 = frame.stamp if stamp0 is None else stamp0
            delay = (frame.stamp - stamp0) - (time.perf_counter() - wall0)
            if delay > 0:
                time.sleep(delay)
        result = tracker.process(frame.depth_m, frame.stamp, T_base_camera[i] if pose_valid[i] else None)
        stamps.append(frame.stamp)
        estimates.append(result.T_base_bone)
        statuses.append(result.status)
        if reader.groundtruth is not None:
            T_gt = reader.groundtruth[i]
            add_mm.append(1e3 * metrics.add(result.T_base_bone, T_gt, points))
            trans_mm.append(1e3 * metrics.translation_error(result.T_base_bone, T_gt))
            rot_deg.append(np.rad2deg(metrics.rotation_error(result.T_base_bone, T_gt)))
        if sink is not None:
            _log_frame(sink, frame, T_base_camera[i] if pose_valid[i] else None, result, tracker,
                       reader.groundtruth[i] if reader.groundtruth is not None else None,
                       add_mm[-1] if add_mm else None, rot_deg[-1] if rot_deg else None)
        if projector_sink is not None and i % max(1, projector_every) == 0:
            projector_sink.step(frame.frame_id, T_base_camera[i] if pose_valid[i] else None, result.T_base_bone,
                                result.status, age_s=0.0,
                                T_base_bone_true=reader.groundtruth[i] if reader.groundtruth is not None else None)
        if progress:
            progress(i + 1, n_total)
    elapsed = time.perf_counter() - t_start
    T_est = np.array(estimates)
    summary = _summary(reader, config, tracker, stamps, statuses, add_mm, trans_mm, rot_deg, elapsed, points)
    if projector_skipped is not None:
        summary["projector"] = {"plan": None, "skipped": projector_skipped}
    if projector_sink is not None:
        summary["projector"] = projector_sink.summary()
        projector_sink.release()
    if out is not None:
        write_tum(out / "estimate.txt", np.array(stamps), T_est)
        write_status_csv(out / "status.csv", np.array(stamps), statuses)
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if sink is not None:
        sink.close()
    tracker.release()
    return ReplayResult(summary, np.array(stamps), T_est, statuses,
                        {"add_mm": np.array(add_mm), "trans_mm": np.array(trans_mm), "rot_deg": np.array(rot_deg)})


def _log_frame(sink, frame, T_base_camera, result, tracker, T_gt, add_mm, rot_deg) -> None:
    sink.set_frame(frame.frame_id, frame.stamp)
    T_base_flange = T_base_camera @ np.linalg.inv(tracker.T_flange_camera) if T_base_camera is not None and tracker.T_flange_camera is not None else None
    sink.log_camera(T_base_flange, T_base_camera, frame.depth_m if frame.index % 3 == 0 else None)
    sink.log_bone("estimate", result.T_base_bone if result.status != "lost" else None)
    if T_gt is not None:
        sink.log_bone("groundtruth", T_gt)
    sink.log_particles(tracker.particle_positions())
    sink.log_scalar("ess_ratio", result.ess_ratio)
    sink.log_scalar("log_likelihood_max", result.log_likelihood_max)
    sink.log_scalar("spread/position_mm", 1e3 * result.position_spread)
    sink.log_scalar("spread/rotation_deg", np.rad2deg(result.rotation_spread))
    sink.log_scalar("status", metrics.STATUS_CODE.get(result.status, 2))
    if add_mm is not None:
        sink.log_scalar("error/add_mm", add_mm)
        sink.log_scalar("error/rotation_deg", rot_deg)


def _check_start(reader, trial_dir: Path, from_point: bool) -> None:
    """The trial holds what the chosen start needs (init.method: 'pose' -> initial_pose, 'point' -> point_prior)."""
    from app.errors import TrialFormatError

    if from_point and reader.meta.point_prior is None:
        raise TrialFormatError(trial_dir / "trial.yaml", "init.method 'point' needs 'point_prior' (a point on the bone, "
                               "base frame); none given: add it, or use init.method 'pose' with initial_pose")
    if not from_point and reader.meta.initial_pose is None:
        raise TrialFormatError(trial_dir / "trial.yaml", "replay needs 'initial_pose' to start the filter (none given); "
                               "or start from 'point_prior' with init.method 'point' in the --config file")


def _init_summary(init, reader, points: np.ndarray) -> dict:
    """The one-point initialiser's run: time, tempering steps, spread, and its error when ground truth exists."""
    out = {"method": "point", "seconds": init.seconds, "tempering_steps": len(init.phis) - 1,
           "reached_target": bool(init.reached_target), "symmetry_turned": bool(init.symmetry_turned),
           "evaluations": int(init.evaluations),
           "position_spread_mm": 1e3 * init.estimate.position_spread,
           "rotation_spread_deg": float(np.degrees(init.estimate.rotation_spread))}
    if reader.groundtruth is not None:
        T_gt = reader.groundtruth[0]
        out.update(add_mm=1e3 * metrics.add(init.estimate.T_base_bone, T_gt, points),
                   rotation_deg=float(np.degrees(metrics.rotation_error(init.estimate.T_base_bone, T_gt))))
    return out


def _summary(reader, config, tracker, stamps, statuses, add_mm, trans_mm, rot_deg, elapsed, points) -> dict:
    n = len(stamps)
    summary = {
        "trial": str(reader.path),
        "frames": n,
        "seconds_of_data": float(stamps[-1] - stamps[0]) if n > 1 else 0.0,
        "processing_rate_hz": n / elapsed if elapsed > 0 else float("nan"),
        "particles": config.particles,
        "resolution": list(config.resolution),
        "sampling": config.sampling,
        "gl": tracker.gl_description,
        "backend": getattr(tracker, "backend_name", None),   # the likelihood backend that ran (render.backend)
        "status_fraction": {s: statuses.count(s) / n if n else 0.0 for s in ("ok", "uncertain", "lost")},
        "timings_ms": tracker.mean_timings_ms(),
        **tracker_report(tracker),     # re-initialisations (count, stamps), template points: plan | mesh_vertices
    }
    init = getattr(tracker, "init_result", None)
    if init is not None:
        summary["init"] = _init_summary(init, reader, points)
    if add_mm:
        add = np.array(add_mm)
        ok = np.array([s == "ok" for s in statuses])
        summary.update({
            "add_mm": metrics.summarise(add),
            "translation_mm": metrics.summarise(trans_mm),
            "rotation_deg": metrics.summarise(rot_deg),
            "lost_fraction": float(np.mean(add > 1e3 * LOST_ADD_M)),
            "dangerous_frames": int(np.sum(ok & (add > 1e3 * DANGEROUS_ADD_M))),
        })
    return summary
