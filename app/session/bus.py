"""What the sources push, on their own threads: events, the joint buffer, and the bus.

The :class:`Bus` validates each frame (size, dtype, finite, non-negative, increasing stamp) and
each joint sample (finite, increasing), rejects bad ones with a logged :class:`EventLog` event,
hands good ones to the sinks, and keeps only the newest frames for the tracker (a bounded
drop-oldest queue). The :class:`JointBuffer` interpolates the joints at a frame's stamp.
"""
from __future__ import annotations

import collections
import csv
import logging
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from app.geometry.camera import PinholeCamera
from app.interfaces import DepthFrame, DropOldestQueue, JointSamples, SessionClock, SessionEvent

log = logging.getLogger("app.session")


class EventLog:
    """Thread-safe session events: logged, written to ``events.csv`` (flushed), passed to the sinks.

    The same (source, kind) within ``repeat_s`` is counted but not repeated.
    """

    def __init__(self, clock: SessionClock, path: Path | None, repeat_s: float = 1.0, history: int | None = None):
        self.clock = clock
        self.repeat_s = repeat_s
        self.counts: Counter = Counter()
        self.events: collections.deque[SessionEvent] = collections.deque(maxlen=history)  # the last `history`
        self.sinks: list = []
        self._last: dict[tuple[str, str], float] = {}
        self._lock = threading.Lock()
        self._file = None
        if path is not None:
            from app.outputs import wrote

            wrote(path)
            self._file = open(path, "w", newline="", buffering=1)
            self._file.write("stamp,source,kind,message\n")

    def emit(self, source: str, kind: str, message: str) -> None:
        now = self.clock.now()
        with self._lock:
            self.counts[f"{source}.{kind}"] += 1
            last = self._last.get((source, kind))
            if last is not None and now - last < self.repeat_s:
                return
            self._last[(source, kind)] = now
            event = SessionEvent(now, source, kind, message)
            self.events.append(event)
            if self._file is not None:
                csv.writer(self._file).writerow([f"{now:.6f}", source, kind, message])
                self._file.flush()
        level = logging.INFO if kind in ("connected", "recovered", "end") else logging.WARNING
        log.log(level, "[%.3f s] %s %s: %s", now - self.clock.t0, source, kind, message)
        for sink in self.sinks:
            try:
                sink.on_event(event)
            except Exception:
                log.exception("output failed on an event")

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class JointBuffer:
    """The recent joint samples (host stamps, increasing: the bus drops the others), interpolated at a
    frame's stamp. Thread-safe.

    The samples live in preallocated arrays, appended in place; ``_t`` / ``_q`` are views of the last
    ``seconds``. A batch is one slice copy, not a copy of the whole history (at 500 Hz and 10 s that was
    5,000 rows a batch). A reader's views stay valid: rows are written only past every view's end, and
    a full buffer moves into new arrays (never over the old ones)."""

    CAPACITY = 1024   # rows to start with; a full buffer moves its live rows into arrays twice their count

    def __init__(self, seconds: float = 10.0, max_gap_s: float = 0.05):
        self.seconds = seconds
        self.max_gap_s = max_gap_s
        self._tbuf, self._qbuf = np.empty(self.CAPACITY), np.empty((self.CAPACITY, 6))
        self._lo = self._hi = 0
        self._t, self._q = self._tbuf[:0], self._qbuf[:0]
        self._cond = threading.Condition()

    def add(self, stamps: np.ndarray, q: np.ndarray) -> None:
        n = len(stamps)
        if n == 0:
            return
        with self._cond:
            if self._hi + n > len(self._tbuf):
                self._move(n)
            self._tbuf[self._hi:self._hi + n] = stamps
            self._qbuf[self._hi:self._hi + n] = q
            self._hi += n
            cutoff = self._tbuf[self._hi - 1] - self.seconds
            self._lo += int(np.searchsorted(self._tbuf[self._lo:self._hi], cutoff, side="left"))
            self._t, self._q = self._tbuf[self._lo:self._hi], self._qbuf[self._lo:self._hi]
            self._cond.notify_all()

    def _move(self, n: int) -> None:
        """Room for ``n`` more rows: the live rows into new arrays of twice (live + n) rows."""
        live = self._hi - self._lo
        size = max(2 * (live + n), self.CAPACITY)
        tbuf, qbuf = np.empty(size), np.empty((size, 6))
        tbuf[:live], qbuf[:live] = self._tbuf[self._lo:self._hi], self._qbuf[self._lo:self._hi]
        self._tbuf, self._qbuf, self._lo, self._hi = tbuf, qbuf, 0, live

    def latest(self) -> float | None:
        with self._cond:
            return float(self._t[-1]) if len(self._t) else None

    def at(self, t: float, wait_s: float = 0.0) -> tuple[np.ndarray | None, str | None]:
        """Joints (6,) at host time ``t``, or (None, reason)."""
        deadline = time.monotonic() + wait_s
        with self._cond:
            while (not len(self._t) or self._t[-1] < t) and time.monotonic() < deadline:
                self._cond.wait(max(deadline - time.monotonic(), 0.0))
            stamps, q = self._t, self._q
        from app.geometry.ur import interpolate_joints

        if not len(stamps):
            return None, "no joint samples yet"
        if t > stamps[-1]:
            return None, f"joints end {t - stamps[-1]:.3f} s before the frame"
        if t < stamps[0]:
            return None, "frame older than the joint history"
        hi = int(np.searchsorted(stamps, t, side="left"))
        lo = max(hi - 1, 0)
        if stamps[hi] - stamps[lo] > self.max_gap_s:
            return None, f"joint samples {stamps[hi] - stamps[lo]:.3f} s apart around the frame"
        qi, valid = interpolate_joints(stamps[lo:hi + 1], q[lo:hi + 1], np.array([t]))
        return (qi[0], None) if valid[0] else (None, "joints not finite")


# ------------------------------------------------------------------------------------------------
# the bus: validation and fan-out, called from the sources' threads
# ------------------------------------------------------------------------------------------------
class Bus:
    """Validates what the sources push, fans it out to sinks, keeps the newest frames for the tracker."""

    def __init__(self, camera: PinholeCamera, events: EventLog, joints: JointBuffer, sinks: list, tracker_queue: int):
        self.camera = camera
        self.events = events
        self.joints = joints
        self.sinks = sinks
        self.frames = DropOldestQueue(tracker_queue)
        self.counts: Counter = Counter()
        self._last_frame_stamp = -np.inf
        self._last_joint_stamp = -np.inf
        self._lock = threading.Lock()

    def push_frame(self, frame: DepthFrame) -> None:
        self.counts["frames_received"] += 1
        d = frame.depth_m
        problem = None
        if not isinstance(d, np.ndarray) or d.ndim != 2:
            problem = ("corrupt_frame", f"frame {frame.frame_id}: not a 2-D array ({type(d).__name__})")
        elif d.shape != (self.camera.height, self.camera.width):
            problem = ("wrong_size_frame", f"frame {frame.frame_id}: {d.shape[1]}x{d.shape[0]}, expected "
                                           f"{self.camera.width}x{self.camera.height}")
        elif d.dtype != np.float32:
            problem = ("corrupt_frame", f"frame {frame.frame_id}: dtype {d.dtype}, expected float32 metres")
        elif not np.isfinite(frame.stamp):
            problem = ("clock", f"frame {frame.frame_id}: stamp {frame.stamp}")
        elif frame.stamp <= self._last_frame_stamp:
            problem = ("clock", f"frame {frame.frame_id}: stamp {frame.stamp:.6f} not after the previous "
                                f"{self._last_frame_stamp:.6f} (clock went back)")
        else:
            bad = ~np.isfinite(d) | (d < 0)
            if bad.any():
                problem = ("corrupt_frame", f"frame {frame.frame_id}: {int(bad.sum())} pixels NaN, infinite or negative")
        if problem is not None:
            self.counts[f"frames_rejected_{problem[0]}"] += 1
            self.events.emit("camera", *problem)
            return
        self._last_frame_stamp = frame.stamp
        self.counts["frames_accepted"] += 1
        for sink in self.sinks:
            sink.on_frame(frame)
        self.frames.put(frame)

    def push_joints(self, samples: JointSamples) -> None:
        t = np.asarray(samples.stamps, float)
        q = np.asarray(samples.q, float)
        self.counts["joint_samples_received"] += len(t)
        if q.ndim != 2 or q.shape != (len(t), 6):
            self.counts["joint_samples_rejected"] += len(t)
            self.events.emit("robot", "corrupt_joints", f"joint batch of shape {q.shape}, expected ({len(t)}, 6)")
            return
        with self._lock:
            finite = np.all(np.isfinite(q), axis=1) & np.isfinite(t)
            if not finite.all():
                self.events.emit("robot", "nan_joints", f"{int((~finite).sum())} joint samples not finite, dropped")
            keep = finite.copy()
            last = self._last_joint_stamp
            for k in np.flatnonzero(finite):
                if t[k] <= last:
                    keep[k] = False
                else:
                    last = t[k]
            if (finite & ~keep).any():
                self.events.emit("robot", "clock", f"{int((finite & ~keep).sum())} joint samples not after the "
                                                   "previous stamp (clock went back), dropped")
            self.counts["joint_samples_rejected"] += int((~keep).sum())
            if not keep.any():
                return
            self._last_joint_stamp = last
            good = JointSamples(t[keep], q[keep])
            self.joints.add(good.stamps, good.q)
        for sink in self.sinks:
            sink.on_joints(good)
