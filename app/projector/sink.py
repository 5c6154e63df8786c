"""One object for the replay and demo loops: render the gated template, log it, write it, score it.

Usage (what the lead wires into app/pipeline/replay.py and the demo)::

    from app.projector.sink import ProjectorSink
    sink = ProjectorSink.from_config("configs/projector.yaml", bone_vertices, bone_faces,
                                     rec=rerun_log.rec,            # or None: no rerun logging
                                     png_dir=out / "projector")    # or None: no PNG files
    for each frame:
        rerun_log.set_frame(frame_id, stamp)                       # the sink logs at the current time
        out = sink.step(frame_id, T_base_camera, T_base_bone_est, status, age_s=0.0,
                        T_base_bone_true=truth_or_None)
        # out.image (H, W, 3) uint8; out.shown (bool); out.reason; out.error (TemplateError or None)
    summary["projector"] = sink.summary()   # frames shown, template error mean/p95/max over shown frames
    sink.release()

The template error is computed only on frames where the template is shown and the truth is known
(a hidden template cannot mislead); it costs ~30 ms per frame (numpy ray casting), so
``error_every`` (default 1) can thin it out on long replays.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.projector.accuracy import TemplateError, plan_normals, template_error
from app.projector.view import ProjectorView

log = logging.getLogger(__name__)


@dataclass
class ProjectorFrame:
    image: np.ndarray
    shown: bool
    reason: str
    error: TemplateError | None


class ProjectorSink:
    """Gated projector rendering + rerun + PNG + template error, per frame."""

    def __init__(self, view: ProjectorView, vertices: np.ndarray, faces: np.ndarray, rec=None,
                 png_dir: "str | Path | None" = None, error_every: int = 1):
        from app.projector.output import PngWriter

        self.view = view
        self.plan = view.renderer.plan
        self.projector = view.projector
        self.vertices, self.faces = np.asarray(vertices, dtype=float), np.asarray(faces)
        self._normals = None   # the surface normals at the scored outline points (once, on first use)
        self.rec = rec
        self.png = PngWriter(png_dir) if png_dir is not None else None
        self.error_every = max(1, int(error_every))
        self.frames = 0
        self.shown = 0
        self.errors: list[TemplateError] = []
        if rec is not None:
            from app.projector.rerun_log import log_projector_static

            log_projector_static(rec, self.projector)

    @classmethod
    def from_config(cls, config_path: "str | Path | None", vertices: np.ndarray, faces: np.ndarray, rec=None,
                    png_dir=None, ctx=None, error_every: int = 1, derive_plan: bool = False,
                    plan=None) -> "ProjectorSink":
        """Build from configs/projector.yaml (None: that default file); ``derive_plan``: see ``build_plan``;
        ``plan``: one already built from the same file (not built again)."""
        from app.projector.config import DEFAULT_CONFIG, build_plan, load_projector_config

        cfg = load_projector_config(config_path or DEFAULT_CONFIG)
        plan = plan if plan is not None else build_plan(cfg, vertices, faces, derive=derive_plan)
        view = ProjectorView.create(cfg.projector, vertices, faces, plan, ctx=ctx, line_width=cfg.line_width_m,
                                    color=cfg.color, max_age_s=cfg.max_age_s)
        return cls(view, vertices, faces, rec, png_dir, error_every)

    def step(self, frame_id: int, T_base_camera: np.ndarray | None, T_base_bone: np.ndarray | None,
             status: str | None, age_s: float | None = 0.0, T_base_bone_true: np.ndarray | None = None
             ) -> ProjectorFrame:
        """Render (gated), log to rerun at the recording's current time, write the PNG, score the template."""
        image = self.view.render_base(T_base_camera, T_base_bone, status, age_s)
        decision = self.view.last_decision
        error = None
        if decision.show and T_base_bone_true is not None and self.frames % self.error_every == 0:
            if self._normals is None:
                self._normals = plan_normals(self.plan, self.vertices, self.faces)
            error = template_error(self.plan, T_base_bone, T_base_bone_true, T_base_camera, self.projector,
                                   self.vertices, self.faces, normals=self._normals)
            if error.n_points:
                self.errors.append(error)
        self.frames += 1
        self.shown += int(decision.show)
        if self.rec is not None:
            from app.projector.rerun_log import log_projector_image

            log_projector_image(self.rec, image)
            if error is not None and np.isfinite(error.mean_mm):
                import rerun as rr

                self.rec.log("plots/projector_template_error_mm", rr.Scalars(error.mean_mm))
        if self.png is not None:
            self.png.write(frame_id, image)
        return ProjectorFrame(image, decision.show, decision.reason, error)

    def summary(self) -> dict:
        """Frames, frames with the template shown, and the template error (mm) over the scored frames."""
        out = {"plan": self.plan.name, "frames": self.frames, "template_shown": self.shown,
               "scored_frames": len(self.errors)}
        if self.errors:
            means = np.array([e.mean_mm for e in self.errors])
            maxes = np.array([e.max_mm for e in self.errors])
            out.update(template_error_mean_mm=float(means.mean()), template_error_p95_mm=float(np.percentile(means, 95)),
                       template_error_max_mm=float(maxes.max()))
        return out

    def release(self) -> None:
        self.view.release()
