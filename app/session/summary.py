"""The session's result and summary: latency per stage, rate, memory.

Everything kept per frame is bounded, so a session's memory stays flat however long it runs
(issue 15's soak): the overall latency statistics are a fixed log-spaced histogram
(:class:`StreamingStats`), the first and last windows keep only their own frames, and the loop keeps
the last :data:`ESTIMATE_HISTORY` estimates in memory (the whole history is in the session's files).
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from app.interfaces import DepthFrame, Estimate, SessionEvent

ESTIMATE_HISTORY = 2_000   # estimates kept in memory (~1 min at 30 frames/s); estimate.txt has them all
EVENT_HISTORY = 10_000     # events kept in memory; events.csv has them all


@dataclass
class SessionResult:
    """The summary (also ``out/summary.json``), the last :data:`ESTIMATE_HISTORY` estimates (without
    images) and the last :data:`EVENT_HISTORY` events."""

    summary: dict
    estimates: list[Estimate]
    events: list[SessionEvent]


class StreamingStats:
    """Median, p99, max and count of a stream of non-negative durations (s) in constant memory.

    The values are counted in log-spaced bins from ``lo`` to ``hi`` with ratio ``1 + rel``: a
    quantile is the upper edge of the bin that holds the nearest-rank quantile (capped by the exact
    maximum), so it is never below the exact quantile and at most a factor ``1 + rel`` (0.2 %) above
    it: a latency is never understated. Values at or below ``lo`` (10 us) count in the first bin, above
    ``hi`` in the last. The maximum and the count are exact. Memory: ~9,200 counters, whatever n.
    """

    def __init__(self, lo: float = 1e-5, hi: float = 1e3, rel: float = 0.002):
        self.lo, self.log_ratio = lo, math.log1p(rel)
        self.counts = np.zeros(int(math.ceil(math.log(hi / lo) / self.log_ratio)) + 1, dtype=np.int64)
        self.n, self.max = 0, -math.inf

    def add(self, value: float) -> None:
        if not math.isfinite(value):
            return
        self.n += 1
        self.max = max(self.max, value)
        i = 0 if value <= self.lo else int(math.log(value / self.lo) / self.log_ratio) + 1
        self.counts[min(i, len(self.counts) - 1)] += 1

    def quantile(self, q: float) -> float | None:
        """The nearest-rank ``q`` quantile (0 < q <= 1), or None without values."""
        if self.n == 0:
            return None
        rank = max(1, int(math.ceil(q * self.n)))
        i = int(np.searchsorted(np.cumsum(self.counts), rank))
        return min(self.lo * math.exp(i * self.log_ratio), self.max)

    def summary(self) -> dict:
        if self.n == 0:
            return {"median": None, "p99": None, "max": None, "n": 0}
        return {"median": self.quantile(0.5), "p99": self.quantile(0.99), "max": self.max, "n": self.n}


def _summary_stats(values) -> dict:
    """Exact median / p99 / max / n of a short list (the first and last windows)."""
    if len(values) == 0:
        return {"median": None, "p99": None, "max": None, "n": 0}
    a = np.asarray(values)
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "max": float(a.max()), "n": int(len(a))}


class LatencyLog:
    """Where a frame's time goes, per processed frame (seconds on the session clock), in bounded memory.

    capture->arrival (``frame.arrival - frame.stamp``: the source's own delay), queue wait (the
    loop's pop minus the arrival), tracker (joint interpolation and ``tracker.process``), sinks
    (every sink's ``on_estimate``). The frame-to-estimate latency is
    ``capture->arrival + queue wait + tracker``; sinks run after the estimate is made. The gap is the
    time between two successive estimates (a loop that waits for a search shows one long gap). Overall
    figures come from :class:`StreamingStats`; the first and last ``window_s`` keep their frames.
    """

    STAGES = ("capture_to_arrival", "queue_wait", "tracker", "sinks")

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        self.latency = StreamingStats()
        self.stages = {k: StreamingStats() for k in self.STAGES}
        self.first: list[float] = []                      # latencies while t <= t0 + window_s
        self.last: collections.deque = collections.deque()  # (t, latency) with t >= t_last - window_s
        self.t0: float | None = None
        self.t_last: float | None = None
        self.gap = StreamingStats()                       # session-clock time between two estimates

    def add(self, frame: DepthFrame, t_pop: float, t_estimate: float, t_sinks_done: float) -> None:
        latency = t_estimate - frame.stamp
        self.latency.add(latency)
        for key, value in zip(self.STAGES, (frame.arrival - frame.stamp, t_pop - frame.arrival,
                                             t_estimate - t_pop, t_sinks_done - t_estimate)):
            self.stages[key].add(value)
        if self.t0 is None:
            self.t0 = t_estimate
        else:
            self.gap.add(t_estimate - self.t_last)
        self.t_last = t_estimate
        if t_estimate <= self.t0 + self.window_s:
            self.first.append(latency)
        self.last.append((t_estimate, latency))
        while self.last[0][0] < t_estimate - self.window_s:
            self.last.popleft()

    def summary(self) -> dict:
        """Latency (ms) overall, per stage, and over the first and last ``window_s`` of the session."""
        out = {"latency_ms": _ms(self.latency.summary()),
               "latency_stages_ms": {k: _ms(v.summary()) for k, v in self.stages.items()},
               "estimate_gap_ms": _ms(self.gap.summary())}     # a search on the loop showed as one long gap
        if self.t0 is not None:
            window_s, n = self.window_s, self.latency.n
            out["latency_first_ms"] = _ms(_summary_stats(self.first))
            out["latency_last_ms"] = _ms(_summary_stats([lat for _, lat in self.last]))
            out["latency_window_s"] = window_s
            span = max(self.t_last - self.t0, 1e-9)
            out["rate_hz"] = {"all": (n - 1) / span if n > 1 else None,
                              "first": len(self.first) / min(window_s, span),
                              "last": len(self.last) / min(window_s, span)}
        return out


def rss_mb() -> float | None:
    """This process's resident memory now (MB; Linux /proc, else None)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    import os

    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def _ms(stats: dict) -> dict:
    return {k: (None if v is None else (1e3 * v if k != "n" else v)) for k, v in stats.items()}
