"""The live session's summary statistics: correct against numpy, and bounded in memory (issue 15's soak)."""
from __future__ import annotations

import numpy as np
import pytest

from app.interfaces import DepthFrame
from app.session.summary import LatencyLog, StreamingStats


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_streaming_quantiles_bound_the_exact_ones_from_above_within_the_bin_ratio(seed):
    rng = np.random.default_rng(seed)
    # latencies from 0.1 ms to seconds, heavy-tailed like a loaded machine's
    values = np.exp(rng.normal(np.log(0.04), 0.8, size=5_000))
    stats = StreamingStats(rel=0.002)
    for v in values:
        stats.add(float(v))
    for q in (0.5, 0.99):
        # nearest-rank quantile: the ceil(q n)-th smallest value
        exact = np.sort(values)[int(np.ceil(q * len(values))) - 1]
        got = stats.quantile(q)
        assert exact <= got <= exact * 1.002 * (1 + 1e-12)
    assert stats.max == values.max() and stats.n == len(values)


def test_streaming_stats_edge_values():
    stats = StreamingStats()
    assert stats.summary() == {"median": None, "p99": None, "max": None, "n": 0}
    for v in (0.1, 0.1, 0.1):
        stats.add(v)
    assert stats.quantile(0.5) == 0.1 and stats.quantile(0.99) == 0.1   # capped by the exact maximum
    stats.add(float("nan"))                                             # not counted
    stats.add(-1e-4)                                                    # a clock skew: the first bin
    assert stats.n == 4 and stats.quantile(0.25) <= stats.lo


def _frame(stamp: float) -> DepthFrame:
    return DepthFrame(stamp=stamp, frame_id=0, depth_m=None, arrival=stamp + 0.001)


def _feed(log: LatencyLog, seconds: float, fps: float = 30.0, t0: float = 100.0) -> None:
    for i in range(int(seconds * fps)):
        stamp = t0 + i / fps
        log.add(_frame(stamp), stamp + 0.005, stamp + 0.035, stamp + 0.036)


def test_latency_log_memory_does_not_grow_with_the_session_length():
    short, long = LatencyLog(window_s=10.0), LatencyLog(window_s=10.0)
    _feed(short, 60.0)
    _feed(long, 600.0)
    # every per-frame structure is bounded by the windows (300 frames at 30 frames/s), not the length
    assert len(long.first) == len(short.first) == 301
    assert len(long.last) == len(short.last) <= 301
    assert long.latency.counts.shape == short.latency.counts.shape
    s = long.summary()
    assert s["latency_ms"]["n"] == 18_000
    assert s["latency_ms"]["median"] == pytest.approx(35.0, rel=2e-3)
    assert s["latency_first_ms"]["n"] == 301 and s["latency_last_ms"]["p99"] == pytest.approx(35.0)
    assert s["rate_hz"]["all"] == pytest.approx(30.0, rel=1e-3)
    assert s["latency_stages_ms"]["queue_wait"]["max"] == pytest.approx(4.0)
    assert s["estimate_gap_ms"]["n"] == 17_999 and s["estimate_gap_ms"]["max"] == pytest.approx(1e3 / 30, rel=1e-6)


def test_the_time_between_estimates_shows_a_loop_that_waited():
    log = LatencyLog(window_s=10.0)
    for i in range(90):
        stamp = 100.0 + i / 30 + (3.3 if i >= 45 else 0.0)        # a 3.3 s wait after frame 44
        log.add(_frame(stamp), stamp, stamp + 0.02, stamp + 0.021)
    gap = log.summary()["estimate_gap_ms"]
    assert gap["max"] == pytest.approx(3300 + 1e3 / 30, rel=2e-2) and gap["median"] == pytest.approx(1e3 / 30, rel=2e-2)
