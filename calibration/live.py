"""Live hand-eye capture: a session's camera images and robot joints turned into a capture folder.

``osteonav calibrate capture --config SESSION.yaml --out DIR`` runs the session's camera and robot
plugins (e.g. ``realsense`` with ``streams: depth,ir`` and ``ur``), detects the ChArUco board in
every image (infrared by default: the depth camera's own K; or colour) and writes a capture
(``calibration.captures`` folder format) when

- **automatically**: the robot has rested ``rest_s`` (0.5 s) at the frame's stamp, judged from the
  joint samples themselves (every sample in [stamp - rest_s, stamp] within ``rest_tol_rad`` of
  their mean, and samples spanning the whole window: never wall time), the board is seen, its
  corners moved less than ``still_px`` since the previous frame (the image agrees that nothing
  moves, which also guards against a camera/robot clock offset) and the robot moved since the
  last capture (one capture per rest);
- **on a key press** (Enter on the terminal): the next frame with the board seen.

The joint angles written are the mean of the rest window (encoder noise averaged). After every
capture the flange rotations are checked for AX = XB conditioning
(:func:`calibration.handeye.check_conditioning`) and the warnings are printed until they clear.
Detection results go to rerun (the image and the corners found) when a recording is given.
"""
from __future__ import annotations

import collections
import logging
import threading
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class JointHistory:
    """The last ``keep_s`` seconds of joint samples (stamps on the host clock)."""

    keep_s: float = 5.0
    _blocks: collections.deque = field(default_factory=collections.deque)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, stamps: np.ndarray, q: np.ndarray) -> None:
        with self._lock:
            self._blocks.append((np.asarray(stamps, float), np.asarray(q, float)))
            last = self._blocks[-1][0][-1]
            while len(self._blocks) > 1 and self._blocks[0][0][-1] < last - self.keep_s:
                self._blocks.popleft()

    def window(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """Samples with t0 <= stamp <= t1, and the last sample before t0 (to judge coverage)."""
        with self._lock:
            if not self._blocks:
                return np.zeros(0), np.zeros((0, 6))
            stamps = np.concatenate([b[0] for b in self._blocks])
            q = np.concatenate([b[1] for b in self._blocks])
        lo = max(int(np.searchsorted(stamps, t0, side="left")) - 1, 0)
        hi = int(np.searchsorted(stamps, t1, side="right"))
        return stamps[lo:hi], q[lo:hi]


def rest_pose(stamps: np.ndarray, q: np.ndarray, t: float, rest_s: float, tol_rad: float,
              max_gap_s: float = 0.05) -> np.ndarray | None:
    """Mean joint angles (6,) if the robot rested over [t - rest_s, t], else None.

    Rested: samples reach back to t - rest_s and forward to within ``max_gap_s`` of t, no gap
    between samples exceeds ``max_gap_s``, and every sample is within ``tol_rad`` of the mean.
    """
    stamps, q = np.asarray(stamps, float), np.asarray(q, float)
    start = int(np.searchsorted(stamps, t - rest_s, side="right")) - 1   # the last sample at or before t - rest_s
    end = int(np.searchsorted(stamps, t, side="right"))
    if start < 0 or end - start < 2 or stamps[end - 1] < t - max_gap_s:
        return None
    stamps, q = stamps[start:end], q[start:end]
    if np.max(np.diff(stamps)) > max_gap_s:
        return None
    mean = q.mean(axis=0)
    if np.max(np.abs(q - mean)) > tol_rad:
        return None
    return mean


def corners_still(previous, current, still_px: float) -> bool:
    """The same corner ids found in both detections, none moved more than ``still_px`` pixels."""
    if previous is None or current is None:
        return False
    common, i_prev, i_cur = np.intersect1d(previous.ids, current.ids, return_indices=True)
    if len(common) < max(4, 0.8 * max(len(previous.ids), len(current.ids))):   # corners lost or gained: not still
        return False
    moved = np.linalg.norm(previous.corners_px[i_prev] - current.corners_px[i_cur], axis=1)
    return bool(moved.max() <= still_px)


@dataclass
class CaptureRules:
    rest_s: float = 0.5
    rest_tol_rad: float = 2e-4      # 0.011 deg: encoder noise passes, a creeping robot does not
    still_px: float = 0.5
    min_move_rad: float = 0.01      # the robot moved this much (any joint) since the last capture
    count: int = 15
    auto: bool = True


class LiveCapturer:
    """Decides, frame by frame, what becomes a capture (see the module docstring).

    ``on_frame(stamp, image)`` returns a status line for the frame; captures go to ``writer``.
    ``fk(q) -> T_base_flange`` feeds the conditioning check.
    """

    def __init__(self, detector, writer, joints: JointHistory, fk, rules: CaptureRules | None = None, rerun=None):
        self.detector, self.writer, self.joints, self.fk = detector, writer, joints, fk
        self.rules = rules or CaptureRules()
        self.rerun = rerun
        self.requested = threading.Event()
        self.captured_q: list[np.ndarray] = []
        self.warnings: list[str] = ["no captures yet"]
        self._previous = None

    @property
    def done(self) -> bool:
        return len(self.captured_q) >= self.rules.count

    def on_frame(self, stamp: float, image: np.ndarray) -> str:
        detection, why = self.detector.detect(image)
        still = corners_still(self._previous, detection, self.rules.still_px)
        self._previous = detection
        if self.rerun is not None:
            self.rerun.log_detection(stamp, image, detection)
        if detection is None:
            return f"no board: {why}"
        stamps, q = self.joints.window(stamp - self.rules.rest_s, stamp)
        q_rest = rest_pose(stamps, q, stamp, self.rules.rest_s, self.rules.rest_tol_rad)
        if self.requested.is_set():
            self.requested.clear()
            q_now = q_rest if q_rest is not None else (q[-1] if len(q) else None)
            if q_now is None:
                return "capture requested but no joint samples yet"
            return self._capture(stamp, q_now, image, "" if q_rest is not None else " (robot was moving)")
        if not self.rules.auto or q_rest is None or not still:
            return f"board: {len(detection.ids)} corners; robot {'at rest' if q_rest is not None else 'moving'}"
        if self.captured_q and np.max(np.abs(q_rest - self.captured_q[-1])) < self.rules.min_move_rad:
            return "board seen; robot at the last capture's pose: move it"
        return self._capture(stamp, q_rest, image, "")

    def _capture(self, stamp: float, q: np.ndarray, image: np.ndarray, note: str) -> str:
        from calibration.handeye import check_conditioning

        index = self.writer.add(stamp, q, image=image)
        self.captured_q.append(np.asarray(q, float))
        T_base_flange = np.stack([self.fk(qi) for qi in self.captured_q])
        self.warnings = check_conditioning(T_base_flange)
        state = "AX = XB well posed" if not self.warnings else "; ".join(self.warnings)
        return f"capture {index} ({len(self.captured_q)}/{self.rules.count}){note}: {state}"


def key_presses(capturer: LiveCapturer, stop: threading.Event, stream) -> threading.Thread:
    """A thread that requests a capture for each line read from ``stream`` (Enter), stops on 'q'."""

    def run():
        for line in stream:
            if line.strip().lower() == "q":
                stop.set()
                return
            capturer.requested.set()

    thread = threading.Thread(target=run, name="capture-keys", daemon=True)
    thread.start()
    return thread
