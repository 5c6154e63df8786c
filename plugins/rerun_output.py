"""Rerun logging of a live session (``outputs: [{plugin: rerun, params: {path: session.rrd}}]``).

Logs, per estimate (:class:`app.pipeline.sinks.RerunSink`, shared with replay): the flange and camera
poses, every ``depth_every``-th depth (and infrared / colour) image, the bone at the estimate
(cleared when the status is not ok: what the projector would show), the particles, the status, the
frame-to-estimate latency (``latency_ms``) and every scalar of the tracker's result (spreads, ESS,
inliers, the refinement's fitness and template error...); events go to a text log.
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
from app.outputs import wrote
from app.pipeline.sinks import RerunSink


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
    """The session's rerun output: :class:`app.pipeline.sinks.RerunSink` (the same logging as replay's)
    on a file or a live viewer, plus the session's events as a text log."""

    kind, name = "output", "rerun"

    def __init__(self, path: str | None = None, spawn: bool = False, depth_every: int = 3):
        self.path, self.spawn, self.depth_every = path, bool(spawn), max(int(depth_every), 1)
        self.log = None
        self.sink: RerunSink | None = None

    def open(self, context: dict) -> None:
        from app.viz.rerun_log import RerunLog

        import rerun as rr

        if self.path and not self.spawn:
            self.path = str(fresh_path(Path(self.path)))
            wrote(self.path)
        self.log = RerunLog.spawn() if (self.spawn or not self.path) else RerunLog.to_file(self.path)
        # the session's recording is the process's default: plugins that log extra entities
        # (the marker tracker's image and angles) find it with rr.get_data_recording()
        rr.set_global_data_recording(self.log.rec)
        mesh = context.get("mesh")
        if mesh is not None:
            self.log.log_static_scene(context["camera"], np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                      with_groundtruth=False)
        self.log.log_image_streams(context.get("image_streams"))
        self.sink = RerunSink(self.log, context.get("T_flange_camera"), self.depth_every, bone_when=("ok",))

    def on_frame(self, frame: DepthFrame) -> None:
        pass

    def on_joints(self, samples: JointSamples) -> None:
        pass

    def on_estimate(self, est: Estimate) -> None:
        self.sink.on_estimate(est)

    def on_event(self, event: SessionEvent) -> None:
        if self.log is not None:
            self.log.log_text("events", f"{event.source} {event.kind}: {event.message}")

    def close(self) -> dict:
        if self.log is not None:
            self.log.close()
        return {"path": self.path}
