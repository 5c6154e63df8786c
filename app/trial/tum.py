"""TUM trajectory files (``groundtruth.txt``, ``estimate.txt``) and the tracker's ``status.csv``.

Import as ``from app.trial import tum``. A TUM row is ``stamp tx ty tz qx qy qz qw``: a pose
T_base_bone (metres) with its quaternion scalar last, as TUM RGB-D and ``evo`` expect
(shared/RECORDING_FORMAT.md, "groundtruth.txt"). Code uses Hamilton (w, x, y, z); the xyzw order
exists only here, through :func:`app.geometry.quaternion.to_xyzw` / ``from_xyzw``. Values are
written with 9 decimals (the format asks for at least 6).

``read_tum`` validates: 8 finite numbers per row, stamps strictly increasing, quaternions of unit
norm within ``QUAT_NORM_ATOL`` (normalised after the check: 9 decimals leave ~1e-9 of norm error);
errors are :class:`app.errors.TrialFormatError` naming the file and the line.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from app.errors import TrialFormatError
from app.geometry import quaternion as quat
from app.geometry import se3

TUM_HEADER = "# stamp tx ty tz qx qy qz qw"
STATUS_HEADER = "stamp,status"
STATUS_HEADER_REASONS = "stamp,status,state,reasons"   # the tracker's own columns after the two of the format
STATUSES = ("ok", "uncertain", "lost")
QUAT_NORM_ATOL = 1e-4  # files rounded to 6 decimals keep |q| within ~2e-6 of 1


def format_tum_row(stamp: float, T: np.ndarray) -> str:
    """One TUM line (with its newline) for pose ``T`` (4, 4) at ``stamp`` (s)."""
    q, t = se3.to_quat_trans(np.asarray(T, dtype=float))
    values = [*t, *quat.to_xyzw(q)]
    return f"{float(stamp):.9f} " + " ".join(f"{v:.9f}" for v in values) + "\n"


def format_status_row(stamp: float, status: str, state: str | None = None, reasons=None) -> str:
    """One ``status.csv`` line (with its newline): ``stamp,status``, or with the tracker's columns
    ``stamp,status,state,reasons`` (:data:`STATUS_HEADER_REASONS`: the lifecycle state and the reason
    codes separated by ``;``) when ``state`` is given."""
    if state is None:
        return f"{float(stamp):.9f},{status}\n"
    return f"{float(stamp):.9f},{status},{state},{';'.join(reasons or ())}\n"


def write_tum(path: str | Path, stamps: np.ndarray, T: np.ndarray) -> None:
    """Write poses ``T`` (N, 4, 4) at ``stamps`` (N,) seconds to a TUM file with its header."""
    stamps = np.asarray(stamps, dtype=float).reshape(-1)
    T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
    if len(stamps) != len(T):
        raise ValueError(f"write_tum: {len(stamps)} stamps but {len(T)} poses")
    lines = [TUM_HEADER + "\n"] + [format_tum_row(s, pose) for s, pose in zip(stamps, T)]
    Path(path).write_text("".join(lines))


def read_tum(path: str | Path, allow_truncated_last_line: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file: ``(stamps (N,) s, T (N, 4, 4))``. Lines starting with '#' and blank lines are skipped.

    ``allow_truncated_last_line``: a last line without its newline (a killed writer) is dropped
    instead of checked.
    """
    path = Path(path)
    if not path.is_file():
        raise TrialFormatError(path, "missing: no such TUM trajectory file")
    text = path.read_text()
    lines = text.split("\n")
    if allow_truncated_last_line and not text.endswith("\n"):
        lines = lines[:-1]
    stamps, rows = [], []
    for lineno, line in enumerate(lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        where = f"line {lineno}"
        if len(fields) != 8:
            raise TrialFormatError(path, f"expected 8 values 'stamp tx ty tz qx qy qz qw', got {len(fields)}", where)
        try:
            values = np.array([float(f) for f in fields])
        except ValueError:
            raise TrialFormatError(path, f"expected numbers, got {line!r}", where) from None
        if not np.all(np.isfinite(values)):
            raise TrialFormatError(path, f"values must be finite, got {line!r}", where)
        norm = np.linalg.norm(values[4:])
        if abs(norm - 1.0) > QUAT_NORM_ATOL:
            raise TrialFormatError(path, f"quaternion (qx qy qz qw) must have unit norm, got norm {norm:.6g}", where)
        if stamps and values[0] <= stamps[-1]:
            raise TrialFormatError(path, f"stamps must increase strictly, got {values[0]!r} after {stamps[-1]!r}", where)
        stamps.append(values[0])
        rows.append(values[1:])
    if not rows:
        return np.zeros(0), np.zeros((0, 4, 4))
    rows = np.array(rows)
    q = quat.normalize(quat.from_xyzw(rows[:, 3:]))
    return np.array(stamps), se3.from_quat_trans(q, rows[:, :3])


def write_status_csv(path: str | Path, stamps: np.ndarray, statuses) -> None:
    """Write ``status.csv``: header ``stamp,status``, one row per processed frame (ok / uncertain / lost)."""
    stamps = np.asarray(stamps, dtype=float).reshape(-1)
    statuses = list(statuses)
    if len(stamps) != len(statuses):
        raise ValueError(f"write_status_csv: {len(stamps)} stamps but {len(statuses)} statuses")
    bad = sorted({s for s in statuses if s not in STATUSES})
    if bad:
        raise ValueError(f"write_status_csv: unknown status {bad}; expected one of {', '.join(STATUSES)}")
    lines = [STATUS_HEADER + "\n"] + [format_status_row(s, status) for s, status in zip(stamps, statuses)]
    Path(path).write_text("".join(lines))


def read_status_csv(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Read ``status.csv``: ``(stamps (N,), statuses)``."""
    path = Path(path)
    if not path.is_file():
        raise TrialFormatError(path, "missing: no such status file")
    lines = path.read_text().splitlines()
    if not lines or not lines[0].strip().startswith(STATUS_HEADER):
        raise TrialFormatError(path, f"expected the header '{STATUS_HEADER}'", "line 1")
    stamps, statuses = [], []
    for lineno, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.strip().split(",")[:2]
        try:
            stamp = float(fields[0])
        except ValueError:
            raise TrialFormatError(path, f"expected a stamp, got {fields[0]!r}", f"line {lineno}") from None
        if len(fields) != 2 or fields[1] not in STATUSES:
            raise TrialFormatError(path, f"expected 'stamp,status' with status one of {', '.join(STATUSES)}, got {line!r}",
                                   f"line {lineno}")
        stamps.append(stamp)
        statuses.append(fields[1])
    return np.array(stamps), statuses
