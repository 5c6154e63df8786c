"""One overwrite policy for every command that writes a directory or a file.

A command that writes a directory calls :func:`prepare_dir` before writing anything:

- a path that does not exist is created (with its parents);
- an empty directory is used as it is;
- a non-empty directory is refused with a one-line :class:`OutputError` naming it and
  ``--overwrite``, unless ``overwrite`` is true; then the entries the command OWNS (its ``owned``
  glob patterns, e.g. ``log.rrd``, ``images``) are removed first, so no stale file of an earlier run
  (a log.rrd, captures, a hand_eye.yaml, images) is left beside the new outputs;
- a directory that also holds entries the command does not own is refused even with
  ``--overwrite``: osteonav never deletes what it did not write;
- a path that is a file, or a directory that cannot be written, is a one-line error.

A command that writes one file calls :func:`prepare_file`: an existing file needs ``--overwrite``,
a directory in its place, a missing or unwritable parent is a one-line error.

A directory holding a trial (``trial.yaml`` or the ``.recording-in-progress`` marker) is the
trial's entirely: :data:`TRIAL` owns every entry of it.
"""
from __future__ import annotations

import fnmatch
import os
import shutil
from pathlib import Path

from app.errors import OsteonavError

TRIAL = "trial"
"""A trial directory: everything in it belongs to the trial (RECORDING_FORMAT.md)."""
TRIAL_MARKERS = ("trial.yaml", ".recording-in-progress")
REPLAY = ("estimate.txt", "status.csv", "summary.json", "log.rrd", "projector")
SESSION = ("estimate.txt", "status.csv", "events.csv", "summary.json", "log.rrd", "*.rrd", "latency.csv",
           "projector")
CAPTURES = ("capture.yaml", "captures.csv", "images", "camera.yaml", "camera_fit.yaml", "truth.yaml",
            "hand_eye.yaml", "*.rrd")
PROJECTOR_CAPTURES = ("projector_capture.yaml", "pose_*", "camera.yaml", "truth.yaml", "projector.yaml")
PLOTS = ("*.png",)


class OutputError(OsteonavError):
    """An output path cannot be used; the message names it and the fix."""


def _owned(name: str, owned) -> bool:
    return any(fnmatch.fnmatch(name, pattern) for pattern in owned)


def prepare_dir(path: "str | Path", overwrite: bool, owned=TRIAL, flag: str = "--out") -> Path:
    """``path`` ready for a command's outputs (see the module docstring); returns it as a Path."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{flag} {path} is a file, not a directory; choose a directory")
    if path.is_dir():
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputError(f"{flag} {path}: the directory is not writable; choose another one")
        entries = sorted(os.listdir(path))
        if entries:
            _clear(path, entries, overwrite, owned, flag)
    else:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{flag} {path}: cannot create the directory ({exc.strerror or exc})") from None
    return path


def _clear(path: Path, entries: list[str], overwrite: bool, owned, flag: str) -> None:
    if not overwrite:
        raise OutputError(f"{flag} {path} is not empty ({len(entries)} entries, e.g. {entries[0]}); pass "
                          f"--overwrite to replace its contents, or choose a new directory")
    if owned == TRIAL:   # everything in a trial directory is the trial's; nothing elsewhere is
        owned = ("*",) if any(m in entries for m in TRIAL_MARKERS) else ()
    foreign = [e for e in entries if not _owned(e, owned)]
    if foreign:
        raise OutputError(f"{flag} {path} holds {foreign[0]!r}, which this command did not write; --overwrite "
                          f"only replaces the command's own outputs: remove it or choose a new directory")
    for name in entries:
        target = path / name
        try:
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            else:
                target.unlink()
        except OSError as exc:
            raise OutputError(f"{flag} {path}: cannot remove the old {name} ({exc.strerror or exc})") from None


def prepare_file(path: "str | Path", overwrite: bool, flag: str = "--out") -> Path:
    """``path`` ready to be written as one file (see the module docstring); returns it as a Path."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{flag} {path} is a directory; give a file name")
    if path.exists() and not overwrite:
        raise OutputError(f"{flag} {path} already exists; pass --overwrite to replace it, or choose another name")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{flag} {path}: cannot create the folder {parent} ({exc.strerror or exc})") from None
    if not os.access(parent, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise OutputError(f"{flag} {path}: not writable; choose another location")
    return path


def results_file(path: "str | None", default: str, overwrite: bool, flag: str = "--json") -> Path:
    """Where a benchmark writes its results file: ``path`` when given (:func:`prepare_file`: an
    existing file needs ``--overwrite``); without it ``default``, or, when ``default`` already exists
    and ``overwrite`` is not given, ``<stem>-<date>-<time><suffix>`` beside it, so a second run never
    replaces the first one's results (the same rule as a session's rerun log)."""
    if path is not None:
        return prepare_file(path, overwrite, flag)
    target = Path(default)
    if target.exists() and not overwrite:
        import time

        target = target.with_name(f"{target.stem}-{time.strftime('%Y%m%d-%H%M%S')}{target.suffix}")
    return prepare_file(target, True, flag)


def add_overwrite_argument(parser, what: str = "the outputs") -> None:
    """The one ``--overwrite`` flag, worded the same for every command."""
    parser.add_argument("--overwrite", action="store_true",
                        help=f"replace {what} of an earlier run (without it a non-empty output is refused)")
