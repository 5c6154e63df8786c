"""The partial matrix: the bench's JSON rewritten while the runs finish, at a bounded cost.

The JSON holds every row so far and is rewritten whole (:func:`app.bench.report.write_json`), so
one write costs in proportion to the rows (about 1.1 ms per 3 s run's row, BENCHMARKS.md "Sweeps
on a Ray cluster"): after every run, a 10,000-run sweep would spend hours of the driver's time
writing. :class:`PartialJson` writes after a finished run unless the writes would then take more
than ``share`` of the time: after a write of ``w`` s it skips the runs finishing in the next
``w / share - w`` s. One run at a time, every run is still written until a write takes a tenth of
a run (about 1,200 rows for 13 s runs); the final JSON is always written by the caller.
"""
from __future__ import annotations

import time

from app.bench.report import write_json

DEFAULT_SHARE = 0.1


class PartialJson:
    """``on_row`` for :func:`app.bench.runs.run_bench`: the rows so far to ``path`` with
    ``meta`` and ``"partial": true`` (module docstring)."""

    def __init__(self, path, meta: dict, share: float = DEFAULT_SHARE, clock=time.monotonic, write=write_json):
        self.path, self.meta, self.share = path, meta, share
        self.clock, self.write = clock, write
        self.next_at = float("-inf")
        self.writes = 0

    def __call__(self, rows: list[dict]) -> None:
        start = self.clock()
        if start < self.next_at:
            return
        self.write(rows, self.path, {**self.meta, "partial": True})
        self.writes += 1
        self.next_at = start + (self.clock() - start) / self.share
