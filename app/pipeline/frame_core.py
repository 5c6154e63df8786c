"""The per-frame core shared by replay and the live session: frame + camera pose -> tracker -> estimate -> sinks.

Import as ``from app.pipeline.frame_core import FrameCore``. The callers differ only in where the
frames come from: :func:`app.pipeline.replay.replay` feeds every frame of a recorded trial in order
on its own thread (deterministic: no threads, no drops), :class:`app.session.loop.LiveLoop` the
newest frame from the bus. Per frame (:meth:`FrameCore.process`):

1. the tracker (:class:`app.interfaces.Tracker`) processes the frame at its camera pose;
2. the status is capped at ``status_floor`` (the live loop's rule for a frame without a camera pose);
3. the :class:`app.interfaces.Estimate` is built: pose, status, latency (``now() - stamp`` when the
   core has a clock), and diagnostics for the sinks (``frame``, ``result``, ``particles``, the
   tracker's spreads and ESS ratio, ``T_base_bone_true`` when the caller knows it, and
   ``T_base_bone_seen``: the true bone as the calibrated camera sees it, which the projector's
   template error is scored against (:func:`app.sim.truth.bone_seen`; the truth when not given));
4. every sink (:mod:`app.pipeline.sinks`, or a session output plugin) gets it, in order.
"""
from __future__ import annotations

import logging
from typing import Callable, Sequence

import numpy as np

from app.errors import OsteonavError
from app.interfaces import DepthFrame, Estimate, Tracker
from app.filter.status import Reason
from app.metrics import STATUS_CODE

log = logging.getLogger(__name__)


class FrameCore:
    """One tracker and its sinks (module docstring).

    tracker : Tracker, or None (a session without one: every estimate is lost, 'not tracking')
    sinks : the sinks, called in this order (a :class:`app.pipeline.sinks.GroundTruthScoring`
        first when others should log its errors)
    now : the clock the latency is measured on (the session's host clock); None = no latency (replay)
    """

    def __init__(self, tracker: Tracker | None, sinks: Sequence, now: Callable[[], float] | None = None):
        self.tracker = tracker
        self.sinks = list(sinks)
        self.failures: dict[str, str] = {}   # sink name: why closing it failed (close())
        self.now = now
        self.t_estimate: float | None = None   # host time the last estimate was made (None without a clock)

    def process(self, frame: DepthFrame, T_base_camera: np.ndarray | None, reasons: Sequence[str] = (),
                status_floor: str | None = None, T_base_bone_true: np.ndarray | None = None,
                T_base_bone_seen: np.ndarray | None = None) -> Estimate:
        """Track one frame and hand the estimate to every sink (module docstring)."""
        est = self.estimate(frame, T_base_camera, reasons, status_floor, T_base_bone_true, T_base_bone_seen)
        self.emit(est)
        return est

    def estimate(self, frame: DepthFrame, T_base_camera: np.ndarray | None, reasons: Sequence[str] = (),
                 status_floor: str | None = None, T_base_bone_true: np.ndarray | None = None,
                 T_base_bone_seen: np.ndarray | None = None) -> Estimate:
        """Steps 1-3 of the module docstring, without the sinks."""
        if self.tracker is None:
            self.t_estimate = None
            return Estimate(frame.stamp, frame.frame_id, None, "lost", T_base_camera, self._latency(frame),
                            (Reason("not_tracking", "not tracking"),))
        result = self.tracker.process(frame, T_base_camera)
        status = str(result.status)
        if status_floor is not None:
            status = max(status, status_floor, key=STATUS_CODE.get)
        self.t_estimate = self.now() if self.now is not None else None
        latency = self.t_estimate - frame.stamp if self.t_estimate is not None else None
        reasons = tuple(reasons) + tuple(getattr(result, "reasons", ()) if status != "ok" else ())
        diagnostics = {"ess_ratio": getattr(result, "ess_ratio", None), "state": getattr(result, "state", ""),
                       "position_spread": getattr(result, "position_spread", None),
                       "rotation_spread": getattr(result, "rotation_spread", None),
                       "frame": frame, "result": result, "particles": self.tracker.particle_positions(),
                       "T_base_bone_true": T_base_bone_true,
                       "T_base_bone_seen": T_base_bone_true if T_base_bone_seen is None else T_base_bone_seen}
        return Estimate(frame.stamp, frame.frame_id, np.asarray(result.T_base_bone, float), status, T_base_camera,
                        latency, tuple(reasons), diagnostics)

    def emit(self, est: Estimate) -> None:
        """Hand an estimate (a frame's, or the live loop's lost tick) to every sink, in order."""
        for sink in self.sinks:
            sink.on_estimate(est)

    def _latency(self, frame: DepthFrame) -> float | None:
        return self.now() - frame.stamp if self.now is not None else None

    def close(self) -> dict:
        """Close the sinks (last first) and release the tracker; {sink class name (#2, #3... for a
        repeated class): its report, or {'error': message} when closing it failed}."""
        reports = {}
        try:
            for sink in reversed(self.sinks):
                name = type(sink).__name__
                name = name if name not in reports else f"{name}#{sum(k.startswith(name) for k in reports) + 1}"
                try:
                    reports[name] = sink.close()
                except (OsteonavError, OSError) as exc:   # a full disk: one line, the others still close
                    log.error("closing the output %s failed: %s", name, exc)
                    reports[name] = {"error": str(exc)}
                    self.failures[name] = str(exc)
                except Exception as exc:    # one failing output must not lose the others' files
                    log.exception("closing an output failed")
                    reports[name] = {"error": str(exc)}
                    self.failures[name] = str(exc)
        finally:
            if self.tracker is not None:
                self.tracker.release()
        return reports
