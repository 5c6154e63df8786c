"""The projector in a live session (``outputs: [{plugin: projector, params: {...}}]``).

Each estimate is rendered by :class:`app.projector.sink.ProjectorSink`: the plan (from
``configs/projector.yaml`` or ``config``) at the estimated ``T_base_bone`` seen from the
projector, shown only when the status is ok and the estimate is fresh; otherwise the red warning
frame (app/projector/view.py). The estimate's age is its frame-to-estimate latency: a tick without
a frame (a stalled or lost camera) has no age and blanks the template, so a stale template is
never shown. Images go to a full-screen window (``window: true``, ``screen``; needs pyglet: ``pip
install -e .[projector]``), to PNG files (``png_dir``) and to the session's rerun recording when
one is active (``rerun: auto``, the default).

Parameters: ``config`` (projector YAML), ``window`` (bool), ``screen`` (int, -1 = last),
``png_dir``, ``every`` (render every n-th estimate; the window shows the latest), ``rerun``.
"""
from __future__ import annotations

import logging

import numpy as np

from app.errors import ConfigError
from app.interfaces import DepthFrame, Estimate, JointSamples, SessionEvent

log = logging.getLogger(__name__)


class ProjectorOutput:
    kind, name = "output", "projector"

    def __init__(self, config: str | None = None, window: bool = False, screen: int = -1,
                 png_dir: str | None = None, every: int = 1, rerun="auto"):
        if not isinstance(every, int) or every < 1:
            raise ConfigError("outputs.projector.params.every", f"expected an integer >= 1, got {every!r}")
        self.config, self.window_wanted, self.screen = config, bool(window), int(screen)
        self.png_dir, self.every, self.rerun = png_dir, every, rerun
        self.sink = None
        self.window = None
        self.shown = 0

    def open(self, context: dict) -> None:
        from app.pipeline.sinks import ProjectorEstimates
        from app.projector.sink import ProjectorSink

        mesh = context.get("mesh")
        if mesh is None:
            raise ConfigError("bone.mesh", "missing: the projector output needs the bone mesh (the plan lies on it)")
        rec = None
        if self.rerun == "auto" or self.rerun is True:
            import rerun as rr

            rec = rr.get_data_recording()     # the rerun output's recording, when it was opened first
        projector = ProjectorSink.from_config(self.config, np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                              rec=rec, png_dir=self.png_dir, error_every=10**9)
        self.sink = ProjectorEstimates(projector, every=self.every)
        if self.window_wanted:
            from app.projector.output import ProjectorWindow

            self.window = ProjectorWindow(screen=self.screen, max_age_s=projector.view.max_age_s)

    def on_frame(self, frame: DepthFrame) -> None:
        pass

    def on_joints(self, samples: JointSamples) -> None:
        pass

    def on_estimate(self, est: Estimate) -> None:
        self.sink.on_estimate(est)
        out = self.sink.last
        if out is None:
            return
        self.shown += int(out.shown)
        if self.window is not None:
            self.window.show(out.image)
            self.window.poll()

    def on_event(self, event: SessionEvent) -> None:
        pass

    def close(self) -> dict:
        summary = {"rendered": self.sink.projector.frames if self.sink else 0, "template_shown": self.shown}
        if self.window is not None:
            self.window.close()
        if self.sink is not None:
            self.sink.close()
        return summary
