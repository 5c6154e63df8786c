"""The output sinks of the per-frame core (:mod:`app.pipeline.frame_core`), shared by replay and the live loop.

A sink takes each :class:`app.interfaces.Estimate` (``on_estimate``, returning at once) and gives a
report when closed (``close() -> dict``); the session's output plugins are sinks too. The core
calls them in order: :class:`GroundTruthScoring` first where there is ground truth (it adds the
frame's errors to ``est.diagnostics["errors"]`` for the sinks after it), then the others.

- :class:`Trajectory`: stamps, poses and statuses in memory (replay's result);
- :class:`GroundTruthScoring`: ADD / translation / rotation errors per frame and their summary
  (the figures ``osteonav bench`` and the demo report; thresholds of :mod:`app.metrics`);
- :class:`EstimateFiles`: ``estimate.txt`` (TUM) and ``status.csv``, streamed row by row;
- :class:`RerunSink`: the camera, depth (and infrared / colour) images, the bone at the estimate
  and the ground truth, particles, and every scalar of the tracker result;
- :class:`ProjectorEstimates`: every ``every``-th estimate rendered by the gated projector
  (:class:`app.projector.sink.ProjectorSink`), scored against the ground truth when it exists.

Estimate diagnostics the sinks read: ``frame`` (the DepthFrame), ``result`` (the tracker's
:class:`app.interfaces.TrackerResult`), ``particles`` ((N, 3) base frame), ``T_base_bone_true``
(replay with ground truth), ``errors`` (set by GroundTruthScoring).
"""
from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from app import metrics
from app.filter.status import codes
from app.geometry import se3
from app.interfaces import Estimate, result_scalars
from app.trial import tum


class Sink(Protocol):
    """What the per-frame core hands estimates to (output plugins included)."""

    def on_estimate(self, est: Estimate) -> None: ...

    def close(self) -> dict: ...


class Trajectory:
    """The estimates' stamps, poses (None where there was none), statuses, lifecycle states and reason
    codes, in memory."""

    def __init__(self):
        self.stamps: list[float] = []
        self.poses: list[np.ndarray | None] = []
        self.statuses: list[str] = []
        self.states: list[str] = []
        self.reasons: list[tuple[str, ...]] = []

    def on_estimate(self, est: Estimate) -> None:
        self.stamps.append(est.stamp)
        self.poses.append(est.T_base_bone)
        self.statuses.append(est.status)
        self.states.append(est.diagnostics.get("state", ""))
        self.reasons.append(codes(est.reasons))

    def close(self) -> dict:
        return {"frames": len(self.stamps)}


class GroundTruthScoring:
    """Per-frame errors against ``est.diagnostics['T_base_bone_true']`` over the model points ``points``.

    ADD (mean point distance, :func:`app.metrics.add`), translation and rotation errors; the summary
    adds the lost fraction (ADD > ``metrics.LOST_ADD_MM``) and the dangerous frames (status ok and
    ADD > ``metrics.DANGEROUS_ADD_MM``).
    """

    def __init__(self, points: np.ndarray):
        self.points = np.asarray(points, dtype=float)
        self.add_mm: list[float] = []
        self.trans_mm: list[float] = []
        self.rot_deg: list[float] = []
        self.ok: list[bool] = []

    def on_estimate(self, est: Estimate) -> None:
        T_true = est.diagnostics.get("T_base_bone_true")
        if T_true is None or est.T_base_bone is None:
            return
        errors = {"add_mm": 1e3 * metrics.add(est.T_base_bone, T_true, self.points),
                  "translation_mm": 1e3 * metrics.translation_error(est.T_base_bone, T_true),
                  "rotation_deg": np.rad2deg(metrics.rotation_error(est.T_base_bone, T_true))}
        self.add_mm.append(errors["add_mm"])
        self.trans_mm.append(errors["translation_mm"])
        self.rot_deg.append(errors["rotation_deg"])
        self.ok.append(est.status == "ok")
        est.diagnostics["errors"] = errors

    def errors(self) -> dict[str, np.ndarray]:
        """Per-frame arrays: add_mm, trans_mm, rot_deg (bench reads these)."""
        return {"add_mm": np.array(self.add_mm), "trans_mm": np.array(self.trans_mm), "rot_deg": np.array(self.rot_deg)}

    def summary(self) -> dict:
        """add_mm / translation_mm / rotation_deg (median, p95, max...), lost_fraction, dangerous_frames; {} without truth."""
        if not self.add_mm:
            return {}
        add, ok = np.array(self.add_mm), np.array(self.ok)
        return {"add_mm": metrics.summarise(add), "translation_mm": metrics.summarise(self.trans_mm),
                "rotation_deg": metrics.summarise(self.rot_deg),
                "lost_fraction": float(np.mean(add > metrics.LOST_ADD_MM)),
                "dangerous_frames": int(np.sum(ok & (add > metrics.DANGEROUS_ADD_MM)))}

    def close(self) -> dict:
        return self.summary()


class EstimateFiles:
    """``estimate.txt`` (TUM) and ``status.csv`` in ``out``, one row per estimate, flushed row by row.
    ``status.csv`` has the format's ``stamp,status`` first, then the tracker's lifecycle ``state`` and
    its reason ``codes`` (``;``-separated; app/tracking/reasons.py): why the template is not shown.

    The rows are :mod:`app.trial.tum`'s (its header, :func:`~app.trial.tum.format_tum_row`, the status
    row of :func:`~app.trial.tum.write_status_csv`), so a killed session leaves every processed frame
    on disk. An estimate without a pose (a tick without frames) has a status row only.
    """

    def __init__(self, out: Path):
        from app.outputs import wrote

        wrote(Path(out) / "estimate.txt")
        wrote(Path(out) / "status.csv")
        self.tum = open(Path(out) / "estimate.txt", "w", buffering=1)
        self.tum.write(tum.TUM_HEADER + "\n")
        self.status = open(Path(out) / "status.csv", "w", buffering=1)
        self.status.write(tum.STATUS_HEADER_REASONS + "\n")

    def on_estimate(self, est: Estimate) -> None:
        if est.T_base_bone is not None:
            self.tum.write(tum.format_tum_row(est.stamp, est.T_base_bone))
        self.status.write(tum.format_status_row(est.stamp, est.status, est.diagnostics.get("state", ""),
                                                codes(est.reasons)))

    def close(self) -> dict:
        self.tum.close()
        self.status.close()
        return {"estimate": self.tum.name, "status": self.status.name}


# tracker-result fields logged under their own plot names and units; the others go to tracker/<field>
SCALAR_PLOTS = {"position_spread": ("spread/position_mm", 1e3), "rotation_spread": ("spread/rotation_deg", 180 / np.pi),
                "ess_ratio": ("ess_ratio", 1.0), "log_likelihood_max": ("log_likelihood_max", 1.0),
                "template_std": ("refine/template_std_mm", 1e3), "refine_fitness": ("refine/fitness", 1.0),
                "nearby": ("refine/nearby_gap_mm", 1e3)}
SKIPPED_SCALARS = ("ess", "dt")   # ess_ratio says it; dt is the stamps'


def _status_text(est: Estimate) -> str:
    """The frame's status line for the log: status, lifecycle state, and each reason's code and text."""
    state = est.diagnostics.get("state") or "-"
    reasons = "; ".join(f"{getattr(r, 'code', 'other')}: {r}" for r in est.reasons)
    return f"{est.status} ({state})" + (f": {reasons}" if reasons else "")


class RerunSink:
    """Per estimate to a :class:`app.viz.rerun_log.RerunLog` (module docstring).

    T_flange_camera : hand-eye, to draw the flange (None: not drawn); depth_every : the depth image
    (and infrared / colour) of every n-th estimate; bone_when : the statuses at which the bone is drawn
    at the estimate (the live session: ('ok',), what the projector would show; replay: ok and uncertain).
    """

    def __init__(self, log, T_flange_camera: np.ndarray | None = None, depth_every: int = 3,
                 bone_when: tuple[str, ...] = ("ok",)):
        self.log, self.T_flange_camera = log, T_flange_camera
        self.T_camera_flange = None if T_flange_camera is None else se3.inverse(np.asarray(T_flange_camera, float))
        self.depth_every, self.bone_when = max(int(depth_every), 1), tuple(bone_when)
        self._frame_id, self._n = 0, 0

    def on_estimate(self, est: Estimate) -> None:
        if est.frame_id is not None:
            self._frame_id = est.frame_id
        self.log.set_frame(self._frame_id, est.stamp)
        self._log_camera(est)
        d = est.diagnostics
        shown = est.T_base_bone is not None and est.status in self.bone_when
        self.log.log_bone("estimate", est.T_base_bone if shown else None)
        if d.get("T_base_bone_true") is not None:
            self.log.log_bone("groundtruth", d["T_base_bone_true"])
        if d.get("particles") is not None:
            self.log.log_particles(d["particles"])
        self.log.log_scalar("status", metrics.STATUS_CODE.get(est.status, 2))
        if est.status != "ok" or d.get("state"):
            self.log.log_text("status/reasons", _status_text(est))
        if est.latency_s is not None:
            self.log.log_scalar("latency_ms", 1e3 * est.latency_s)
        self._log_result(d.get("result"))
        for name, value in (d.get("errors") or {}).items():
            self.log.log_scalar(f"error/{name}", value)

    def _log_camera(self, est: Estimate) -> None:
        frame = est.diagnostics.get("frame")
        depth_now = frame is not None and self._n % self.depth_every == 0
        self._n += 1
        T_base_flange = None
        if est.T_base_camera is not None and self.T_camera_flange is not None:
            T_base_flange = est.T_base_camera @ self.T_camera_flange
        self.log.log_camera(T_base_flange, est.T_base_camera, frame.depth_m if depth_now else None)
        if depth_now:
            self.log.log_images(frame.infrared, frame.color)

    def _log_result(self, result) -> None:
        """Every numeric field of the tracker result (:func:`app.interfaces.result_scalars`); none without one."""
        if result is None:
            return
        scalars = result_scalars(result)
        scalars.setdefault("reinitialised", float(getattr(result, "reinitialised", False)))
        for name, value in scalars.items():
            if name in SKIPPED_SCALARS:
                continue
            plot, scale = SCALAR_PLOTS.get(name, (f"tracker/{name}", 1.0))
            self.log.log_scalar(plot, scale * value)

    def close(self) -> dict:
        self.log.close()
        return {}


class ProjectorEstimates:
    """Every ``every``-th estimate to a :class:`app.projector.sink.ProjectorSink` (gated on the status).

    age_s : the estimate's age handed to the gate: None = its latency (live); a number = that (replay: 0).
    ``last`` is the last :class:`app.projector.sink.ProjectorFrame` rendered (None when skipped).
    """

    def __init__(self, projector, every: int = 1, age_s: float | None = None):
        self.projector, self.every, self.age_s = projector, max(int(every), 1), age_s
        self._n = 0
        self.last = None

    @property
    def plan(self):
        """The projector's plan (its template points bound the tracker's status: app/pipeline/tracker.py)."""
        return self.projector.plan

    def on_estimate(self, est: Estimate) -> None:
        n = self._n
        self._n += 1
        self.last = None
        if n % self.every:
            return
        age = est.latency_s if self.age_s is None else self.age_s
        self.last = self.projector.step(est.frame_id if est.frame_id is not None else self._n, est.T_base_camera,
                                        est.T_base_bone, est.status, age_s=age,
                                        T_base_bone_true=est.diagnostics.get("T_base_bone_seen",
                                                                             est.diagnostics.get("T_base_bone_true")))

    def close(self) -> dict:
        summary = self.projector.summary()
        self.projector.release()
        return summary
