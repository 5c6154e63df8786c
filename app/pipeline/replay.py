"""``osteonav replay``: the application loop over a recorded trial.

For each frame: the joints interpolated at the frame's stamp give ``T_base_camera`` (FK and the
trial's hand-eye); the depth image is reduced to the filter's resolution; the particle filter
(started by ``init.method``: with ``auto``, the default, at the trial's ``initial_pose``, else
from its ``point_prior`` by the detector, app/tracking/detector.py, the summary's ``start`` block
giving its work; with ``point`` by the one-point initialiser on the first frame, the summary's
``init`` block giving that run) steps; the estimate goes to the sinks. Every frame goes, in order and on the calling thread (no
threads, no drops: deterministic), through the per-frame core the live session uses
(:class:`app.pipeline.frame_core.FrameCore`) and its sinks (:mod:`app.pipeline.sinks`: ground-truth
scoring, which ``osteonav bench`` reads through :attr:`ReplayResult.errors`, the trajectory, rerun,
the projector, the files). Writes, in ``out``:

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
frames where the template was shown; app/projector/accuracy.py). The true pose is taken as the
trial's calibrated camera sees it when the trial records the true camera (a simulated calibration
error: the projector draws with the calibrated camera pose; app/sim/truth.py).

The plan is built from that configuration whether or not the projector is an output: the tracker's
status bounds the predicted error of the plan's points (:func:`known_plan`), so the estimates and
statuses never depend on the outputs (``projector``, ``projector_images``, ``rrd``, ``out_dir``).
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
from app.interfaces import DepthFrame
from app.outputs import OutputError, write_failure, wrote
from app.pipeline.engine_tracker import EngineTracker
from app.pipeline.frame_core import FrameCore
from app.pipeline.sinks import EstimateFiles, GroundTruthScoring, ProjectorEstimates, RerunSink, Trajectory
from app.pipeline.tracker import DepthTracker, start_method, start_tracker, tracker_report, use_plan
from app.tracking.reasons import reason_shares

log = logging.getLogger(__name__)


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

    ``make_tracker(mesh, camera) -> engine`` replaces the particle filter by another tracking engine
    with ``start``, ``process(depth_m, stamp, T_base_camera)``, ``particle_positions``,
    ``mean_timings_ms``, ``release`` and ``gl_description`` (wrapped in
    :class:`app.pipeline.engine_tracker.EngineTracker`, the :class:`app.interfaces.Tracker` contract),
    e.g. the ICP baseline (app/baselines/icp.py); ``config`` then only names the run in the summary.
    """
    from app.trial.reader import open_trial

    config = config or load_config(None)
    reader = open_trial(trial_dir)
    method = "pose" if make_tracker is not None else \
        start_method(config.init_method, reader.meta.initial_pose, reader.meta.point_prior)
    _check_start(reader, Path(trial_dir), method)
    mesh = reader.load_mesh()
    engine = DepthTracker(config, mesh, reader.meta.camera) if make_tracker is None else make_tracker(mesh, reader.meta.camera)
    tracker = EngineTracker(engine)
    start_tracker(tracker, reader.meta.initial_pose, reader.meta.point_prior)   # by init.method; the recovery's point
    out = Path(out_dir) if out_dir else None
    plan, plan_error = known_plan(projector_config, mesh)
    use_plan(engine, plan)   # the status's template points: the plan's whatever the outputs (issue 34)
    sinks = ReplaySinks.open(reader, tracker, mesh, out, rrd, projector and out is not None,
                             ProjectorOptions(projector_config, projector_every, projector_images), plan, plan_error)
    core = FrameCore(tracker, sinks.all)
    try:
        elapsed = _run(core, reader, max_frames, realtime, progress)
    finally:
        reports = core.close()
    summary = _summary(reader, config, engine, sinks.trajectory, sinks.scoring,
                       elapsed, np.asarray(mesh.vertices))
    if sinks.projector_skipped is not None:
        summary["projector"] = {"plan": None, "skipped": sinks.projector_skipped}
    if "ProjectorEstimates" in reports:
        summary["projector"] = reports["ProjectorEstimates"]
    failures = dict(core.failures)
    if out is not None:
        wrote(out / "summary.json")
        try:
            (out / "summary.json").write_text(json.dumps(summary, indent=2))
        except OSError as exc:
            failures["summary.json"] = write_failure(exc, "cannot write it")
    if failures:
        raise OutputError(f"{out}: the outputs are incomplete: " + "; ".join(f"{k}: {v}" for k, v in failures.items()))
    t = sinks.trajectory
    return ReplayResult(summary, np.array(t.stamps), np.array(t.poses), t.statuses, sinks.scoring.errors())


def _run(core: FrameCore, reader, max_frames: int | None, realtime: bool, progress) -> float:
    """Every frame in order through the core (paced at the recorded stamps with ``realtime``); seconds taken."""
    T_base_camera, pose_valid = reader.camera_poses()
    truth = reader.groundtruth
    seen = _bone_seen(reader, T_base_camera, truth)
    n_total = len(reader.stamps) if max_frames is None else min(max_frames, len(reader.stamps))
    t_start = time.perf_counter()
    stamp0 = None
    for frame in reader.iter_frames():
        i = frame.index
        if i >= n_total:
            break
        if realtime:
            stamp0 = frame.stamp if stamp0 is None else stamp0
            delay = (frame.stamp - stamp0) - (time.perf_counter() - t_start)
            if delay > 0:
                time.sleep(delay)
        depth_frame = DepthFrame(frame.frame_id, frame.stamp, frame.depth_m, frame.stamp, frame.infrared, frame.color)
        core.process(depth_frame, T_base_camera[i] if pose_valid[i] else None,
                     T_base_bone_true=truth[i] if truth is not None else None,
                     T_base_bone_seen=seen[i] if seen is not None and pose_valid[i] else None)
        if progress:
            progress(i + 1, n_total)
    return time.perf_counter() - t_start


def _bone_seen(reader, T_base_camera: np.ndarray, truth: np.ndarray | None) -> np.ndarray | None:
    """The truth as the trial's camera sees it, for the projector's template error (app/sim/truth.py,
    eq. S1); None without ground truth or without a true camera apart from the trial's own."""
    from app.sim.truth import FROM_TRIAL, bone_seen, true_camera_poses

    if truth is None:
        return None
    T_true, source = true_camera_poses(reader)
    return None if source == FROM_TRIAL else bone_seen(T_base_camera, T_true, truth)


def known_plan(projector_config: str | Path | None, mesh):
    """(plan, None) for the projector configuration (None: configs/projector.yaml) on this mesh, the
    configured plan or one derived on the mesh's ridge; (None, reason) when no plan fits.

    The tracker's status bounds the predicted error of the plan's points (``use_plan``), so the plan is
    built whether or not the projector is an output: the estimates never depend on the outputs."""
    from app.projector.config import DEFAULT_CONFIG, build_plan, load_projector_config

    cfg = load_projector_config(projector_config or DEFAULT_CONFIG)
    try:
        return build_plan(cfg, np.asarray(mesh.vertices), np.asarray(mesh.faces), derive=True), None
    except MeshError as exc:
        return None, str(exc)


@dataclass
class ProjectorOptions:
    config: str | Path | None = None
    every: int = 3
    images: bool = False


@dataclass
class ReplaySinks:
    """Replay's sinks, in the core's order: scoring (with ground truth), trajectory, rerun, projector, files."""

    trajectory: Trajectory
    scoring: GroundTruthScoring
    all: list
    projector_skipped: str | None = None

    @classmethod
    def open(cls, reader, tracker: EngineTracker, mesh, out: Path | None, rrd: bool, projector: bool,
             options: ProjectorOptions, plan=None, plan_error: str | None = None) -> "ReplaySinks":
        sinks = cls(Trajectory(), GroundTruthScoring(np.asarray(mesh.vertices)), [])
        sinks.all = [sinks.scoring, sinks.trajectory]
        if out is None:
            return sinks
        out.mkdir(parents=True, exist_ok=True)
        rerun = None
        if rrd:
            from app.viz.rerun_log import RerunLog

            wrote(out / "log.rrd")
            log_ = RerunLog.to_file(out / "log.rrd")
            log_.log_static_scene(reader.meta.camera, np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                  with_groundtruth=reader.groundtruth is not None)
            log_.log_image_streams(reader.meta.streams)
            log_.log_text("backend", tracker.description)
            rerun = RerunSink(log_, reader.meta.T_flange_camera, depth_every=3, bone_when=("ok", "uncertain"))
            sinks.all.append(rerun)
        if projector and plan is None:
            log.warning("projector skipped: no plan fits this trial's mesh (%s)", plan_error)
            sinks.projector_skipped = plan_error
        elif projector:
            sinks._open_projector(mesh, out, rerun, options, plan)
        sinks.all.append(EstimateFiles(out))
        return sinks

    def _open_projector(self, mesh, out: Path, rerun: RerunSink | None, options: ProjectorOptions, plan) -> None:
        from app.projector.sink import ProjectorSink

        projector = ProjectorSink.from_config(options.config, np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                              rec=rerun.log.rec if rerun is not None else None,
                                              png_dir=out / "projector" if options.images else None,
                                              error_every=2, plan=plan)
        self.all.append(ProjectorEstimates(projector, every=options.every, age_s=0.0))


def _check_start(reader, trial_dir: Path, method: str) -> None:
    """The trial holds what the chosen start needs (:func:`app.pipeline.tracker.start_method`: 'pose' ->
    initial_pose, 'point' -> point_prior; 'detect', init.method auto without a pose, needs neither)."""
    from app.errors import TrialFormatError

    if method == "point" and reader.meta.point_prior is None:
        raise TrialFormatError(trial_dir / "trial.yaml", "init.method 'point' needs 'point_prior' (a point on the bone, "
                               "base frame); none given: add it, or use init.method 'auto' (the default)")
    if method == "pose" and reader.meta.initial_pose is None:
        raise TrialFormatError(trial_dir / "trial.yaml", "init.method 'pose' needs 'initial_pose' to start the filter "
                               "(none given); or use init.method 'auto' (the default), which starts from "
                               "'point_prior' or searches the image")


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


def _summary(reader, config, tracker, trajectory, scoring: GroundTruthScoring, elapsed, points) -> dict:
    stamps, statuses = trajectory.stamps, trajectory.statuses
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
        **reason_shares(trajectory.reasons, trajectory.states),
        "timings_ms": tracker.mean_timings_ms(),
        **tracker_report(tracker),     # re-initialisations (count, stamps), template points: plan | mesh_vertices
    }
    init = getattr(tracker, "init_result", None)
    if init is not None:
        summary["init"] = _init_summary(init, reader, points)
    start = getattr(tracker, "start_report", None)          # a start by the detector (init.method auto, no pose)
    if start is not None:
        summary["start"] = start
    summary.update(scoring.summary())
    return summary
