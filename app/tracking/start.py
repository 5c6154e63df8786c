"""A start without a pose: the detector's attempts until it finds the bone, and their work.

Import as ``from app.tracking.start import StartByDetection``. Used by
:meth:`app.pipeline.tracker.DepthTracker.start_by_detection` (``init.method: auto`` with no coarse
pose; issue 33). On each usable frame while the start is pending, at most every DETECT_RETRY_S
(the recovery's SEARCH_RETRY_S: a detector that found nothing on one frame is asked again a third of
a second later, not on every frame), the detector (app/tracking/detector.py) looks for the bone
from the point prior, or over the whole image without one. The work (attempts, likelihood
evaluations, refinements, CPU and wall seconds, the stamp it was found at) is counted for the
summaries: work, never a timer, decides anything.
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np

from app.filter.recovery import SEARCH_RETRY_S

log = logging.getLogger(__name__)
DETECT_RETRY_S = SEARCH_RETRY_S


class StartByDetection:
    """The pending start of the module docstring.

    Parameters
    ----------
    detector : a :class:`app.tracking.detector.Detector`
    point : (3,) the point prior (base frame, m), or None (the whole image)
    """

    def __init__(self, detector, point: np.ndarray | None):
        self.detector, self.point = detector, point
        self.pending = True
        self.detection = None
        self._next_stamp = -math.inf
        self.work = {"attempts": 0, "evaluations": 0, "refinements": 0, "cpu_s": 0.0, "wall_s": 0.0}
        self.found_stamp: float | None = None

    def attempt(self, depth_small: np.ndarray, depth_m: np.ndarray, T_base_camera: np.ndarray,
                stamp: float) -> np.ndarray | None:
        """One attempt on this usable frame when one is due: the found T_base_bone, or None (nothing
        found, or the retry not due yet)."""
        if not self.pending or stamp < self._next_stamp:
            return None
        wall0, cpu0 = time.perf_counter(), time.process_time()
        found = self.detector.detect(depth_small, depth_m, T_base_camera, self.point)
        work = self.work
        work["attempts"] += 1
        work["cpu_s"] += time.process_time() - cpu0
        work["wall_s"] += time.perf_counter() - wall0
        evaluations, refinements = self.detector.last_work
        work["evaluations"] += int(evaluations)
        work["refinements"] += int(refinements)
        if found is None:
            self._next_stamp = stamp + DETECT_RETRY_S
            log.info("start at %.3f s: the detector found nothing confirmed; again in %.2f s", stamp, DETECT_RETRY_S)
            return None
        self.pending, self.detection, self.found_stamp = False, found, float(stamp)
        log.info("start at %.3f s: the detector found the bone (%s, sharp share %.2f, fit %.2f)", stamp,
                 "from the point" if self.point is not None else "whole image", found.score, found.fitness)
        return found.T_base_bone

    def report(self) -> dict:
        """For the summaries: the method ('point' | 'whole_image'), whether and when it was found, its
        verification score and the work of every attempt."""
        d = self.detection
        return {"method": "detect_point" if self.point is not None else "detect_whole_image",
                "strategy": getattr(self.detector, "strategy", ""), "found": d is not None,
                "found_stamp": self.found_stamp, "score": None if d is None else float(d.score),
                "fitness": None if d is None else float(d.fitness), **self.work}
