"""What the projector shows each frame: the template when the track is ok and fresh, else a warning.

Safety rules (DESIGN.md "The projector template"; issue 7):

- the template is drawn only when the tracker's status is ``ok`` **and** the estimate is fresh:
  its age (now minus the stamp of the frame it was computed from) is at most ``max_age_s``, and
  the pose is a finite 4x4;
- otherwise the template disappears and the **warning pattern** is shown: a red border with red
  corner wedges and a red text line naming the reason ("TRACKING LOST", "TRACKING UNCERTAIN",
  "ESTIMATE STALE", ...). It is red and sits at the image border, where no template can be, so it
  cannot be mistaken for an outline; it lights almost nothing of the patient;
- nothing is cached between frames: each call decides again, so an old template is never shown.

:func:`gate` is the rule alone (no GL, used by tests and by the window's watchdog);
:class:`ProjectorView` applies it around a :class:`~app.projector.render.ProjectorRenderer`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from app.geometry import se3

log = logging.getLogger(__name__)

MAX_AGE_S = 0.2
"""Oldest estimate the template may follow (s): at the surgeon's 25 cm/s a 0.2 s old pose is
already 5 cm off, but the tracker's motion gate has made such a pose uncertain; for a still bone
0.2 s is six camera frames, enough to ride over one dropped frame and short enough to blank on a
stalled pipeline."""
WARNING_COLOR = (255, 0, 0)


@dataclass(frozen=True)
class GateDecision:
    """show : draw the template; reason : why not (empty when shown)."""

    show: bool
    reason: str = ""


def gate(status: str | None, T_projector_bone: np.ndarray | None, age_s: float | None = 0.0,
         max_age_s: float = MAX_AGE_S) -> GateDecision:
    """Whether the template may be shown.

    Parameters
    ----------
    status : the tracker's status, 'ok' | 'uncertain' | 'lost' (anything else counts as not ok)
    T_projector_bone : (4, 4) pose used to draw, or None
    age_s : seconds between now and the stamp of the estimate's frame; None = unknown (not shown)
    max_age_s : oldest estimate allowed
    """
    status = str(status) if status is not None else "none"
    if status != "ok":
        return GateDecision(False, f"TRACKING {status.upper()}")
    if T_projector_bone is None or not se3.is_rigid(np.asarray(T_projector_bone, dtype=float), atol=1e-4):
        return GateDecision(False, "NO VALID POSE")
    if age_s is None or not np.isfinite(age_s) or age_s > max_age_s:
        return GateDecision(False, "ESTIMATE STALE")
    if age_s < -max_age_s:
        return GateDecision(False, "ESTIMATE FROM THE FUTURE (CLOCKS?)")
    return GateDecision(True)


def warning_pattern(width: int, height: int, reason: str = "TRACKING LOST") -> np.ndarray:
    """(H, W, 3) uint8: red border, red corner wedges and the reason in red at the top, black inside."""
    import cv2

    img = np.zeros((height, width, 3), dtype=np.uint8)
    b = max(2, int(round(0.015 * min(width, height))))
    c = WARNING_COLOR
    img[:b], img[-b:], img[:, :b], img[:, -b:] = c, c, c, c
    k = max(8, int(round(0.12 * min(width, height))))
    for (x, y, dx, dy) in ((0, 0, 1, 1), (width - 1, 0, -1, 1), (0, height - 1, 1, -1), (width - 1, height - 1, -1, -1)):
        pts = np.array([[x, y], [x + dx * k, y], [x, y + dy * k]], dtype=np.int32)
        cv2.fillConvexPoly(img, pts, c)
    scale = max(0.4, min(width, height) / 500.0)
    thick = max(1, int(round(2 * scale)))
    (tw, th), _ = cv2.getTextSize(reason, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    cv2.putText(img, reason, ((width - tw) // 2, b + k // 2 + th), cv2.FONT_HERSHEY_SIMPLEX, scale, c, thick,
                cv2.LINE_AA)
    return img


class ProjectorView:
    """The projector image of each frame, behind the safety gate.

    Parameters
    ----------
    renderer : ProjectorRenderer (owns the GL resources; released by ``release()``)
    max_age_s : oldest estimate that may drive the template (see MAX_AGE_S)
    """

    def __init__(self, renderer, max_age_s: float = MAX_AGE_S):
        self.renderer = renderer
        self.projector = renderer.projector
        self.max_age_s = float(max_age_s)
        self._warnings: dict[str, np.ndarray] = {}
        self.last_decision = GateDecision(False, "NOT STARTED")

    @classmethod
    def create(cls, projector, vertices, faces, plan, ctx=None, line_width: float | None = None,
               color=None, max_age_s: float = MAX_AGE_S) -> "ProjectorView":
        """A view with its own renderer on ``ctx`` (default: this thread's shared context)."""
        from app.projector.render import DEFAULT_COLOR, LINE_WIDTH_M, ProjectorRenderer
        from app.render.context import shared_context

        renderer = ProjectorRenderer(ctx or shared_context(), projector, vertices, faces, plan,
                                     line_width=line_width or LINE_WIDTH_M, color=color or DEFAULT_COLOR)
        return cls(renderer, max_age_s)

    def warning(self, reason: str) -> np.ndarray:
        """The warning pattern for ``reason`` (cached per reason; a copy is returned)."""
        if reason not in self._warnings:
            self._warnings[reason] = warning_pattern(self.projector.width, self.projector.height, reason)
        return self._warnings[reason].copy()

    def render(self, T_projector_bone: np.ndarray | None, status: str | None, age_s: float | None = 0.0) -> np.ndarray:
        """(H, W, 3) uint8 projector image: the template if :func:`gate` allows it, else the warning.

        Parameters
        ----------
        T_projector_bone : (4, 4) pose of the bone in the projector frame (None when there is none)
        status : tracker status string ('ok' | 'uncertain' | 'lost')
        age_s : now minus the estimate's frame stamp, seconds (0 in replay, where frames are processed in order)
        """
        decision = gate(status, T_projector_bone, age_s, self.max_age_s)
        if decision != self.last_decision:
            log.info("projector: %s", "template shown" if decision.show else f"template hidden ({decision.reason})")
        self.last_decision = decision
        if not decision.show:
            return self.warning(decision.reason)
        return self.renderer.render(np.asarray(T_projector_bone, dtype=float))

    def render_base(self, T_base_camera: np.ndarray | None, T_base_bone: np.ndarray | None, status: str | None,
                    age_s: float | None = 0.0) -> np.ndarray:
        """:meth:`render` from poses in the robot base frame (T_projector_bone from the rig calibration)."""
        T = (None if T_base_bone is None or T_base_camera is None
             else self.projector.T_projector_bone(T_base_camera, T_base_bone))
        return self.render(T, status, age_s)

    def release(self) -> None:
        self.renderer.release()
