"""Rerun logging of a live session (``outputs: [{plugin: rerun, params: {path: session.rrd}}]``).

Logs, per estimate: the flange and camera poses, every ``depth_every``-th depth image, the bone at
the estimate (cleared when the status is not ok: what the projector would show), the status,
the frame-to-estimate latency (``latency_ms``) and the filter's spreads; events go to a text log.
Without ``path`` (or with ``spawn: true``) it opens a live viewer. Rerun's SDK queues and sends
from its own thread, so these calls return at once. A run never overwrites an earlier session's
log: when ``path`` exists, this run writes ``<stem>-<YYYYmmdd-HHMMSS><suffix>`` beside it (the
summary's ``outputs.RerunOutput.path`` names the file written).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from app.interfaces import DepthFrame, Estimate, JointSamples, SessionEvent
from app.metrics import STATUS_CODE



def fresh_path(path: Path) -> Path:
    """``path`` if free, else ``<stem>-<local time YYYYmmdd-HHMMSS>[-n]<suffix>`` beside it."""
    if not path.exists():
        return path
    stamp = time.strftime("%Y%m%d-%H%M%S")
    candidate = path.with_name(f"{path.stem}-{stamp}{path.suffix}")
    n = 1
    while candidate.exists():
        candidate = path.with_name(f"{path.stem}-{stamp}-{n}{path.suffix}")
        n += 1
    return candidate


class RerunOutput:
    kind, name = "output", "rerun"

    def __init__(self, path: str | None = None, spawn: bool = False, depth_every: int = 3):
        self.path, self.spawn, self.depth_every = path, bool(spawn), max(int(depth_every), 1)
        self.log = None
        self.T_flange_camera = None
        self._frame_id = 0
        self._n = 0

    def open(self, context: dict) -> None:
        from app.viz.rerun_log import RerunLog

        import rerun as rr

        if self.path and not self.spawn:
            self.path = str(fresh_path(Path(self.path)))
        self.log = RerunLog.spawn() if (self.spawn or not self.path) else RerunLog.to_file(self.path)
        # the session's recording is the process's default: plugins that log extra entities
        # (the marker tracker's image and angles) find it with rr.get_data_recording()
        rr.set_global_data_recording(self.log.rec)
        self.T_flange_camera = context.get("T_flange_camera")
        mesh = context.get("mesh")
        if mesh is not None:
            self.log.log_static_scene(context["camera"], np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                      with_groundtruth=False)
        self.log.log_image_streams(context.get("image_streams"))

    def on_frame(self, frame: DepthFrame) -> None:
        pass

    def on_joints(self, samples: JointSamples) -> None:
        pass

    def on_estimate(self, est: Estimate) -> None:
        if est.frame_id is not None:
            self._frame_id = est.frame_id
        self.log.set_frame(self._frame_id, est.stamp)
        frame = est.diagnostics.get("frame")
        depth = frame.depth_m if frame is not None and self._n % self.depth_every == 0 else None
        self._n += 1
        T_base_flange = None
        if est.T_base_camera is not None and self.T_flange_camera is not None:
            T_base_flange = est.T_base_camera @ np.linalg.inv(self.T_flange_camera)
        self.log.log_camera(T_base_flange, est.T_base_camera, depth)
        if depth is not None:
            self.log.log_images(frame.infrared, frame.color)
        self.log.log_bone("estimate", est.T_base_bone if est.show_template else None)
        self.log.log_scalar("status", STATUS_CODE.get(est.status, 2))
        if est.latency_s is not None:
            self.log.log_scalar("latency_ms", 1e3 * est.latency_s)
        for key in ("ess_ratio",):
            if est.diagnostics.get(key) is not None:
                self.log.log_scalar(key, est.diagnostics[key])
        if est.diagnostics.get("position_spread") is not None:
            self.log.log_scalar("spread/position_mm", 1e3 * est.diagnostics["position_spread"])

    def on_event(self, event: SessionEvent) -> None:
        if self.log is not None:
            self.log.log_text("events", f"{event.source} {event.kind}: {event.message}")

    def close(self) -> dict:
        if self.log is not None:
            self.log.close()
        return {"path": self.path}
