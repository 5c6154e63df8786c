"""The session's per-frame files in ``out``: ``estimate.txt`` (TUM) and ``status.csv``, streamed.

The rows are :mod:`app.trial.tum`'s (the same header, :func:`~app.trial.tum.format_tum_row`, the
same status row as :func:`~app.trial.tum.write_status_csv`), written as they come and flushed
line by line, so a killed session leaves every processed frame on disk.
"""
from __future__ import annotations

from pathlib import Path

from app.interfaces import Estimate
from app.trial import tum


class EstimateFiles:
    """estimate.txt (TUM) and status.csv, one row per processed frame, flushed row by row."""

    def __init__(self, out: Path):
        self.tum = open(out / "estimate.txt", "w", buffering=1)
        self.tum.write(tum.TUM_HEADER + "\n")
        self.status = open(out / "status.csv", "w", buffering=1)
        self.status.write(tum.STATUS_HEADER + "\n")

    def write(self, est: Estimate) -> None:
        if est.T_base_bone is not None:
            self.tum.write(tum.format_tum_row(est.stamp, est.T_base_bone))
        self.status.write(f"{est.stamp:.9f},{est.status}\n")

    def close(self) -> None:
        self.tum.close()
        self.status.close()
