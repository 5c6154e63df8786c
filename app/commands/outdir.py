"""One overwrite policy for every command that writes a directory or a file (the CLI side of
:mod:`app.outputs`, which keeps each output folder's manifest and lock).

A command that writes a directory calls :func:`prepare_dir` before writing anything:

- a path that does not exist is created (with its parents);
- an empty directory is used as it is;
- a non-empty directory is refused with a one-line :class:`OutputError` naming it and
  ``--overwrite``; with ``overwrite`` exactly the files an earlier osteonav run listed in the
  folder's manifest are removed, and a folder holding anything else is refused, naming those
  entries, before anything is removed: osteonav never deletes what it did not write;
- a folder another osteonav run is writing is refused (its lock); the input is never an output;
- a path that is a file, or a directory that cannot be written, is a one-line error.

The folder stays locked until the command ends (:func:`app.outputs.close_all`, called by the CLI).

A command that writes one file calls :func:`prepare_file`: an existing file needs ``--overwrite``,
the file may not be one of the command's inputs, and a directory in its place, a missing or
unwritable parent is a one-line error. A file written into an osteonav output folder is listed in
that folder's manifest.
"""
from __future__ import annotations

import os
from pathlib import Path

from app.outputs import MANIFEST, OutputError, is_locked, open_folder, wrote

__all__ = ["OutputError", "prepare_dir", "prepare_file", "results_file", "add_overwrite_argument"]


def prepare_dir(path: "str | Path", overwrite: bool, flag: str = "--out", inputs=()) -> Path:
    """``path`` ready and locked for a command's outputs (see the module docstring); returns it as a Path."""
    return open_folder(path, overwrite, flag, inputs).path


def prepare_file(path: "str | Path", overwrite: bool, flag: str = "--out", inputs=()) -> Path:
    """``path`` ready to be written as one file (see the module docstring); returns it as a Path."""
    path = Path(path)
    for source in inputs:
        if source is not None and Path(source).resolve() == path.resolve():
            raise OutputError(f"{flag} {path} is the input this command reads; the input is never an output: "
                              f"choose another {flag}")
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
    _list_in_output_folder(path, flag)
    return path


def _list_in_output_folder(path: Path, flag: str) -> None:
    """A file written into an osteonav output folder joins that folder's manifest (so that the
    folder's next ``--overwrite`` may remove it); a folder another run is writing is refused."""
    wrote(path)
    parent = path.parent
    if not (parent / MANIFEST).is_file():
        return
    holder = is_locked(parent)
    if holder and str(os.getpid()) not in holder.split(",")[0].split():
        raise OutputError(f"{flag} {path}: its folder is being written by another osteonav run ({holder}); wait for it "
                          f"to finish or choose another location")
    if not holder:
        import json

        with open(parent / MANIFEST, "a", encoding="utf-8") as manifest:
            manifest.write(json.dumps(path.name) + "\n")


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
