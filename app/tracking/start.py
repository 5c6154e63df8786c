"""A start without a pose: the detector's attempts until it finds the bone, and their work.

Import as ``from app.tracking.start import StartByDetection, PointedPixel``. Used by
:meth:`app.pipeline.tracker.DepthTracker.start_by_detection` (``init.method: auto`` with no coarse
pose; issue 33). On each usable frame while the start is pending, at most every ``retry_s``
(``status.settle_s``: a detector that found nothing on one frame is asked again a third of
a second later, not on every frame), the detector (app/tracking/detector.py) looks for the bone
from the point prior, or over the whole image without one. The work (attempts, likelihood
evaluations, refinements, CPU and wall seconds, the stamp it was found at) is counted for the
summaries: work, never a timer, decides anything.

The point may also be given live, by a *point source* (:class:`PointSource`): it locates the point
on a frame (base frame, m) or says why it cannot yet; the first point located is kept for every
attempt (and for the recovery). :class:`PointedPixel` is the session's ``bone.pointed_pixel``: a pixel
(u, v) of the full-resolution depth image, back-projected through the depth camera's intrinsics at
the median valid depth of a POINTED_WINDOW_PX square around it, and carried into the base frame by
the frame's T_base_camera: ``p_base = T_base_camera (z K^-1 (u, v, 1))``. A frame where the window
holds too little valid depth locates nothing (the start waits, 'initialising', and tries the next
frame: no retry delay, nothing was searched).
"""
from __future__ import annotations

import logging
import math
import time
from typing import Protocol

import numpy as np

from app.filter.recovery import RecoveryConfig


log = logging.getLogger(__name__)
POINTED_WINDOW_PX = 5     # the pointed pixel's depth: the median over this square (odd) around it
POINTED_MIN_VALID = 0.5   # ... of at least this share of valid pixels: fewer is an edge, a hole or a flying pixel


class PointSource(Protocol):
    """Where the pointed point is on this frame (module docstring): ``locate`` returns the point (3,)
    in the base frame (m) and '' , or None and the reason it cannot locate it on this frame;
    ``description`` names the source for the logs and the summaries."""

    description: str

    def locate(self, depth_m: np.ndarray, T_base_camera: np.ndarray) -> tuple[np.ndarray | None, str]: ...


class PointedPixel:
    """A pixel pointed at in the full-resolution depth image (the session's ``bone.pointed_pixel``).

    Parameters
    ----------
    pixel : (u, v), column and row of the depth image, pixel centres at integers (OpenCV's convention,
        :meth:`app.geometry.camera.PinholeCamera.project`); inside the image
    camera : the depth camera's full-resolution PinholeCamera (the frames' size)
    window_px : the odd side of the square whose median valid depth is the pixel's depth
    """

    def __init__(self, pixel, camera, window_px: int = POINTED_WINDOW_PX):
        u, v = (float(c) for c in pixel)
        if not (0 <= u <= camera.width - 1 and 0 <= v <= camera.height - 1):
            raise ValueError(f"the pointed pixel ({u:g}, {v:g}) lies outside the {camera.width}x{camera.height} "
                             f"depth image: 0 <= u <= {camera.width - 1}, 0 <= v <= {camera.height - 1}")
        if window_px < 1 or window_px % 2 == 0:
            raise ValueError(f"the pointed pixel's window is an odd number of pixels >= 1, got {window_px}")
        self.pixel, self.camera, self.window_px = (u, v), camera, int(window_px)
        self.description = f"pointed pixel ({u:g}, {v:g})"

    def locate(self, depth_m: np.ndarray, T_base_camera: np.ndarray) -> tuple[np.ndarray | None, str]:
        """The pixel's point in the base frame (3,) and '', or None and why (too little valid depth)."""
        u, v = self.pixel
        h = self.window_px // 2
        col, row = int(round(u)), int(round(v))
        window = np.asarray(depth_m[max(row - h, 0):row + h + 1, max(col - h, 0):col + h + 1], dtype=float)
        valid = window[np.isfinite(window) & (window > 0)]
        if len(valid) < POINTED_MIN_VALID * window.size:
            return None, (f"the {self.description} has no depth on this frame ({len(valid)} of {window.size} pixels "
                          f"valid in its {self.window_px}x{self.window_px} window): point at the bone's surface")
        z = float(np.median(valid))
        K = self.camera.K
        p_camera = z * np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
        T = np.asarray(T_base_camera, dtype=float)
        return T[:3, :3] @ p_camera + T[:3, 3], ""


class StartByDetection:
    """The pending start of the module docstring.

    Parameters
    ----------
    detector : a :class:`app.tracking.detector.Detector`
    point : (3,) the point prior (base frame, m), or None (the whole image, or the source's point)
    source : a :class:`PointSource` that locates the point live (with ``point`` None), or None
    """

    def __init__(self, detector, point: np.ndarray | None, source: PointSource | None = None,
                 retry_s: float = RecoveryConfig.search_retry_s):
        if point is not None and source is not None:
            raise ValueError("a start takes a point or a point source, not both")
        self.detector, self.point, self.source = detector, point, source
        self.retry_s = float(retry_s)   # s between two attempts that found nothing (status.settle_s)
        self.waiting = ""           # why the source located no point on the last frame ('' once it has)
        self.located_stamp: float | None = None
        self.pending = True
        self.worker = None          # app/tracking/search_worker.py's SearchWorker in a live session, else inline
        self.detection = None
        self._next_stamp = -math.inf
        self.work = {"attempts": 0, "evaluations": 0, "refinements": 0, "cpu_s": 0.0, "wall_s": 0.0}
        self.found_stamp: float | None = None

    def attempt(self, depth_small: np.ndarray, depth_m: np.ndarray, T_base_camera: np.ndarray,
                stamp: float) -> np.ndarray | None:
        """One attempt on this usable frame when one is due: the found T_base_bone, or None (nothing
        found, or the retry not due yet)."""
        if not self.pending or not self._located(depth_m, T_base_camera, stamp):
            return None
        if self.worker is not None and (self.worker.in_flight or self.worker.safe()):
            return self._on_worker(depth_small, depth_m, T_base_camera, stamp)
        if stamp < self._next_stamp:
            return None
        wall0, cpu0 = time.perf_counter(), time.process_time()
        found = self.detector.detect(depth_small, depth_m, T_base_camera, self.point)
        return self._attempted(found, self.detector.last_work, time.process_time() - cpu0,
                               time.perf_counter() - wall0, stamp)

    def _on_worker(self, depth_small, depth_m, T_base_camera, stamp: float) -> np.ndarray | None:
        """The attempt on the search worker (app/tracking/search_worker.py, a live session): taken on the
        first frame after it finished (its frame's result; the camera's motion since is in the base
        frame's pose), else handed over when due; None meanwhile (the frames go on, 'initialising')."""
        from app.tracking.search_worker import DetectJob

        worker = self.worker
        if worker.in_flight:
            if not worker.ready():
                return None
            job, outcome = worker.take()
            found, spent = outcome.result if outcome is not None else (None, (0, 0))
            return self._attempted(found, spent, 0.0 if outcome is None else outcome.cpu_s,
                                   0.0 if outcome is None else outcome.wall_s, stamp)
        if stamp >= self._next_stamp:
            worker.submit(DetectJob(depth_small.copy(), depth_m.copy(), np.array(T_base_camera, float),
                                    None if self.point is None else self.point.copy(), float(stamp),
                                    getattr(self.detector, "start", None)))
        return None

    def _attempted(self, found, spent: tuple, cpu_s: float, wall_s: float, stamp: float) -> np.ndarray | None:
        """Count an attempt's work; the found T_base_bone, or None (retried ``retry_s`` later)."""
        work = self.work
        work["attempts"] += 1
        work["cpu_s"] += cpu_s
        work["wall_s"] += wall_s
        evaluations, refinements = spent
        work["evaluations"] += int(evaluations)
        work["refinements"] += int(refinements)
        if found is None:
            self._next_stamp = stamp + self.retry_s
            log.info("start at %.3f s: the detector found nothing confirmed; again in %.2f s", stamp, self.retry_s)
            return None
        self.pending, self.detection, self.found_stamp = False, found, float(stamp)
        log.info("start at %.3f s: the detector found the bone (%s, sharp share %.2f, fit %.2f)", stamp,
                 "from the point" if self.point is not None else "whole image", found.score, found.fitness)
        return found.T_base_bone

    def _located(self, depth_m: np.ndarray, T_base_camera: np.ndarray, stamp: float) -> bool:
        """Whether the start has its point (or needs none): the source's first point, located on this
        frame when not yet (module docstring)."""
        if self.source is None or self.point is not None:
            return True
        point, why = self.source.locate(depth_m, T_base_camera)
        if point is None:
            if why != self.waiting:
                log.info("start at %.3f s: %s", stamp, why)
            self.waiting = why
            return False
        self.point, self.waiting, self.located_stamp = np.asarray(point, float).reshape(3), "", float(stamp)
        log.info("start at %.3f s: the %s is at %s m in the base frame", stamp, self.source.description,
                 np.round(self.point, 4).tolist())
        return True

    def report(self) -> dict:
        """For the summaries: the method ('detect_point' | 'detect_whole_image' | 'detect_pointed'), the
        point source, the point it located (or why it has not, ``waiting``), whether and when it was
        found, its verification score and the work of every attempt."""
        d = self.detection
        method = "detect_pointed" if self.source is not None else \
            "detect_point" if self.point is not None else "detect_whole_image"
        pointed = {} if self.source is None else {
            "source": self.source.description, "located_stamp": self.located_stamp, "waiting": self.waiting,
            "point": None if self.point is None else [float(c) for c in self.point]}
        return {"method": method, **pointed,
                "strategy": getattr(self.detector, "strategy", ""), "found": d is not None,
                "found_stamp": self.found_stamp, "score": None if d is None else float(d.score),
                "fitness": None if d is None else float(d.fitness), **self.work}
