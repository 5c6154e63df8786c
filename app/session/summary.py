"""The session's result and summary: latency per stage, rate, memory."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.interfaces import DepthFrame, Estimate, SessionEvent


@dataclass
class SessionResult:
    """The summary (also ``out/summary.json``), the last 100,000 estimates (without images), the events."""

    summary: dict
    estimates: list[Estimate]
    events: list[SessionEvent]


def _summary_stats(values: list[float]) -> dict:
    if not values:
        return {"median": None, "p99": None, "max": None, "n": 0}
    a = np.asarray(values)
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "max": float(a.max()), "n": int(len(a))}


class LatencyLog:
    """Where a frame's time goes, per processed frame (seconds on the session clock).

    capture->arrival (``frame.arrival - frame.stamp``: the source's own delay), queue wait (the
    loop's pop minus the arrival), tracker (joint interpolation and ``tracker.process``), sinks
    (every sink's ``on_estimate``). The frame-to-estimate latency is
    ``capture->arrival + queue wait + tracker``; sinks run after the estimate is made.
    """

    STAGES = ("capture_to_arrival", "queue_wait", "tracker", "sinks")

    def __init__(self):
        self.t_estimate: list[float] = []
        self.latency: list[float] = []
        self.stages: dict[str, list[float]] = {k: [] for k in self.STAGES}

    def add(self, frame: DepthFrame, t_pop: float, t_estimate: float, t_sinks_done: float) -> None:
        self.t_estimate.append(t_estimate)
        self.latency.append(t_estimate - frame.stamp)
        for key, value in zip(self.STAGES, (frame.arrival - frame.stamp, t_pop - frame.arrival,
                                             t_estimate - t_pop, t_sinks_done - t_estimate)):
            self.stages[key].append(value)

    def summary(self, window_s: float = 10.0) -> dict:
        """Latency (ms) overall, per stage, and over the first and last ``window_s`` of the session."""
        out = {"latency_ms": _ms(_summary_stats(self.latency)),
               "latency_stages_ms": {k: _ms(_summary_stats(v)) for k, v in self.stages.items()}}
        if self.t_estimate:
            t = np.asarray(self.t_estimate)
            lat = np.asarray(self.latency)
            first, last = t <= t[0] + window_s, t >= t[-1] - window_s
            out["latency_first_ms"] = _ms(_summary_stats(list(lat[first])))
            out["latency_last_ms"] = _ms(_summary_stats(list(lat[last])))
            out["latency_window_s"] = window_s
            span = max(t[-1] - t[0], 1e-9)
            out["rate_hz"] = {"all": (len(t) - 1) / span if len(t) > 1 else None,
                              "first": int(first.sum()) / min(window_s, span), "last": int(last.sum()) / min(window_s, span)}
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
