"""What a command wrote: the output folder's manifest and its writer's lock.

An output folder that osteonav writes holds two bookkeeping files beside the outputs:

- ``.osteonav-outputs``: the manifest, one JSON string per line, each the path (relative to the
  folder, ``/``-separated) of a file this command wrote there, or of a folder it created (ending
  in ``/``). A writer lists a path *before* it creates the file (:func:`wrote`), and every line is
  one ``write`` of an append-only file, so a run killed at any moment still lists every file it
  left. A line without its newline (cut by a kill) is ignored: its file was never created.
- ``.osteonav-lock``: held with ``fcntl.flock`` by the one process writing the folder; its text
  names that process. A second writer is refused by name; a lock file left by a process that has
  died holds no lock (the kernel released it) and is taken over, with a warning.

:meth:`OutputFolder.open` with ``overwrite`` removes exactly the manifest's files (and the folders
it created, once empty); anything else in the folder is refused, by name, before anything is
removed. There is no owned-by-name rule: a file is the command's only if its manifest lists it.

Writers call :func:`wrote` (``wrote(path)``, ``wrote(folder, folder=True)``) before creating a
file; it finds the innermost folder this process has open (:func:`open_folder`) that holds
``path`` and lists it there, and does nothing for a path outside every open folder (library use).
"""
from __future__ import annotations

import atexit
import errno
import fcntl
import json
import logging
import os
import sys
import threading
import time
from pathlib import Path

from app.errors import OsteonavError

log = logging.getLogger(__name__)

MANIFEST = ".osteonav-outputs"
LOCK = ".osteonav-lock"
BOOKKEEPING = (MANIFEST, LOCK)
MAX_NAMED = 8
"""How many foreign entries a refusal names before '... and N more'."""


class OutputError(OsteonavError):
    """An output path cannot be used; the message names it and the fix."""


def read_manifest(folder: Path) -> set[str]:
    """The paths the manifest of ``folder`` lists (empty without one); a line cut by a kill is ignored."""
    try:
        text = (Path(folder) / MANIFEST).read_text(encoding="utf-8")
    except FileNotFoundError:
        return set()
    listed = set()
    for line in text.splitlines(keepends=True):
        if not line.endswith("\n"):
            break
        try:
            listed.add(str(json.loads(line)))
        except ValueError:
            continue
    return listed


# ------------------------------------------------------------------ the lock

def _holder(fd: int) -> str:
    """The text a lock holder wrote into the lock file (who it is), or '' when it wrote none."""
    try:
        return os.pread(fd, 512, 0).decode("utf-8", "replace").strip()
    except OSError:
        return ""


def _lock(folder: Path, flag: str) -> int:
    """Hold ``folder``'s lock (see the module docstring); the lock file's descriptor."""
    path = folder / LOCK
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputError(f"{flag} {folder}: cannot create the lock {LOCK} ({exc.strerror or exc}); "
                              f"choose a writable directory") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd) or "another process"
            os.close(fd)
            raise OutputError(f"{flag} {folder} is being written by another osteonav run ({holder}); wait for it to "
                              f"finish or choose another directory") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:   # else its holder removed it between our open and our lock: try again
            break
        os.close(fd)
    stale = _holder(fd)
    if stale:
        log.warning("%s: the lock left by %s, which is no longer running, is taken over", folder, stale)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()}, {' '.join(Path(sys.argv[0]).name.split()[:1] + sys.argv[1:3])}, since "
                  f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode(), 0)
    return fd


def is_locked(folder: Path) -> str | None:
    """Who holds ``folder``'s lock (its text), or None when nobody does."""
    try:
        fd = os.open(Path(folder) / LOCK, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _holder(fd) or "another process"
    finally:
        os.close(fd)
    return None


# ------------------------------------------------------------------ what --overwrite removes

class _Plan:
    """What clearing a folder removes (files, then folders, deepest first) and what it refuses."""

    def __init__(self):
        self.files: list[Path] = []
        self.folders: list[Path] = []
        self.foreign: list[str] = []
        self.busy: list[str] = []


def _survey(folder: Path, listed: set[str], plan: _Plan, shown: str = "", skip=()) -> bool:
    """Add ``folder``'s entries (but ``skip``) to ``plan``; True when every entry is the command's (so it empties)."""
    clean = True
    for entry in sorted(os.scandir(folder), key=lambda e: e.name):
        rel, path = entry.name, Path(entry.path)
        if rel in skip:
            continue
        if entry.is_dir(follow_symlinks=False):
            if rel + "/" not in listed:
                plan.foreign.append(f"{shown}{rel}/")
                clean = False
            elif (path / MANIFEST).exists():       # a nested output folder: its own manifest says
                holder = is_locked(path)
                if holder:
                    plan.busy.append(f"{shown}{rel}/ ({holder})")
                if _survey_folder(path, plan, f"{shown}{rel}/"):
                    plan.folders.append(path)
                else:
                    clean = False
            elif _survey(path, {p[len(rel) + 1:] for p in listed if p.startswith(rel + "/")}, plan, f"{shown}{rel}/"):
                plan.folders.append(path)
            else:
                clean = False
        elif rel in listed:
            plan.files.append(path)
        else:
            plan.foreign.append(f"{shown}{rel}")
            clean = False
    return clean


def _survey_folder(folder: Path, plan: _Plan, shown: str = "") -> bool:
    """:func:`_survey` of an output folder: its manifest and lock are its own (removed with it)."""
    return _survey(folder, read_manifest(folder), plan, shown, skip=BOOKKEEPING)


def unlisted(folder: "str | Path") -> list[str]:
    """The entries of output folder ``folder`` (nested output folders included) that no manifest
    lists: what ``--overwrite`` would refuse. Empty for a folder holding only osteonav's outputs."""
    plan = _Plan()
    _survey_folder(Path(folder), plan)
    return plan.foreign


def _names(names: list[str]) -> str:
    more = f" and {len(names) - MAX_NAMED} more" if len(names) > MAX_NAMED else ""
    return ", ".join(names[:MAX_NAMED]) + more


def _entries(folder: Path) -> list[str]:
    return sorted(n for n in os.listdir(folder) if n not in BOOKKEEPING)


def _clear(folder: Path, flag: str) -> None:
    """Remove what ``folder``'s manifest lists; refuse, before removing anything, when more is there."""
    plan = _Plan()
    _survey_folder(folder, plan)
    if plan.foreign:
        raise OutputError(f"{flag} {folder} holds files this command did not write: {_names(plan.foreign)}; "
                          f"--overwrite only replaces osteonav's own outputs: move them or choose a new directory")
    if plan.busy:
        raise OutputError(f"{flag} {folder}: {_names(plan.busy)} is being written by another osteonav run; wait for "
                          f"it to finish or choose another directory")
    try:
        for path in plan.files:
            path.unlink()
        for path in plan.folders:
            for name in BOOKKEEPING:
                (path / name).unlink(missing_ok=True)
            path.rmdir()
    except OSError as exc:
        raise OutputError(f"{flag} {folder}: cannot remove the earlier output {exc.filename} "
                          f"({exc.strerror or exc})") from None


# ------------------------------------------------------------------ an open output folder

class OutputFolder:
    """A folder this process writes: its lock held and its manifest open for :meth:`wrote`."""

    def __init__(self, path: Path, lock_fd: int, flag: str):
        self.path, self.flag = path, flag
        self.root = path.resolve()
        self._lock_fd = lock_fd
        self._listed = read_manifest(path)
        self._fd = os.open(path / MANIFEST, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._mutex = threading.Lock()

    @classmethod
    def open(cls, path: "str | Path", overwrite: bool, flag: str = "--out", inputs=()) -> "OutputFolder":
        """``path`` locked and ready for a command's outputs.

        A path that does not exist is created; an empty folder (or one holding only an earlier run's
        bookkeeping) is used as it is; a non-empty one needs ``overwrite``, which removes exactly
        what its manifest lists and refuses anything else by name. ``inputs`` (paths the command
        reads) may be neither the folder nor inside it.
        """
        path = Path(path)
        _refuse_inputs(path, inputs, flag)
        if path.exists() and not path.is_dir():
            raise OutputError(f"{flag} {path} is a file, not a directory; choose a directory")
        if not path.is_dir():
            try:
                path.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise OutputError(f"{flag} {path}: cannot create the directory ({exc.strerror or exc})") from None
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputError(f"{flag} {path}: the directory is not writable; choose another one")
        fd = _lock(path, flag)
        try:
            entries = _entries(path)
            if entries and not overwrite:
                raise OutputError(_not_empty(path, entries, flag))
            if entries:
                _clear(path, flag)
            (path / MANIFEST).unlink(missing_ok=True)   # a fresh manifest: this run's outputs only
            return cls(path, fd, flag)
        except BaseException:
            _unlock(path, fd)
            raise

    def wrote(self, path: "str | Path", folder: bool = False) -> None:
        """List ``path`` (inside this folder) and the folders above it, before they are created."""
        rel = _full(path).relative_to(self.root).as_posix()
        if rel == ".":
            return
        names, parts = [], rel.split("/")
        for i in range(1, len(parts)):
            names.append("/".join(parts[:i]) + "/")
        names.append(rel + "/" if folder else rel)
        with self._mutex:
            new = [n for n in names if n not in self._listed]
            if not new:
                return
            os.write(self._fd, "".join(json.dumps(n) + "\n" for n in new).encode("utf-8"))
            self._listed.update(new)

    def listed(self) -> set[str]:
        """The paths listed so far (this run's)."""
        with self._mutex:
            return set(self._listed)

    def close(self) -> None:
        """Close the manifest (it stays: the next ``--overwrite`` reads it) and release the lock."""
        if self._fd is None:
            return
        os.close(self._fd)
        self._fd = None
        _unlock(self.path, self._lock_fd)


def _unlock(folder: Path, fd: int) -> None:
    try:
        (folder / LOCK).unlink(missing_ok=True)
    except OSError:
        pass
    os.close(fd)


def _not_empty(path: Path, entries: list[str], flag: str) -> str:
    earlier = " of an earlier osteonav run" if read_manifest(path) else ""
    return (f"{flag} {path} is not empty ({len(entries)} entries{earlier}, e.g. {entries[0]}); pass --overwrite to "
            f"replace osteonav's own outputs there, or choose a new directory")


def _refuse_inputs(path: Path, inputs, flag: str) -> None:
    target = path.resolve()
    for source in inputs:
        if source is None:
            continue
        source = Path(source).resolve()
        if source == target or source.is_relative_to(target):
            raise OutputError(f"{flag} {path} would hold the input {source} it reads; the input is never an output: "
                              f"choose another {flag}")


# ------------------------------------------------------------------ this process's open folders

_open: dict[Path, OutputFolder] = {}
_registry_lock = threading.Lock()


def open_folder(path: "str | Path", overwrite: bool, flag: str = "--out", inputs=()) -> OutputFolder:
    """:meth:`OutputFolder.open`, registered so that :func:`wrote` finds it; a folder this process
    already has open, and those inside it, are closed first (an earlier command of the same process
    is done with them). A folder inside another open one is listed there as a folder of its own."""
    key = Path(path).resolve()
    with _registry_lock:
        earlier = [_open.pop(k) for k in list(_open) if k == key or key in k.parents]
    for folder in earlier:
        folder.close()
    wrote(key, folder=True)   # in the open folder around it, if any
    folder = OutputFolder.open(path, overwrite, flag, inputs)
    with _registry_lock:
        _open[key] = folder
    return folder


def _innermost(path: Path) -> OutputFolder | None:
    with _registry_lock:
        for parent in path.parents:
            if parent in _open:
                return _open[parent]
    return None


def _full(path: "str | Path") -> Path:
    """``path`` with its folder resolved (the file itself need not exist, nor be followed if a link)."""
    path = Path(path)
    return path.parent.resolve() / path.name


def wrote(path: "str | Path", folder: bool = False) -> None:
    """List ``path`` in the innermost open output folder holding it (none: nothing to do)."""
    if not _open:
        return
    full = _full(path)
    owner = _innermost(full)
    if owner is not None:
        owner.wrote(full, folder)


def close_folder(path: "str | Path") -> None:
    """Release the folder's lock (its manifest stays)."""
    with _registry_lock:
        folder = _open.pop(Path(path).resolve(), None)
    if folder is not None:
        folder.close()


def close_all() -> None:
    """Release every folder this process has open (the end of a command)."""
    with _registry_lock:
        folders = list(_open.values())
        _open.clear()
    for folder in folders:
        folder.close()


atexit.register(close_all)


def write_failure(exc: OSError, what: str) -> str:
    """A one-line message for a failed write: ``what`` and the reason (a full disk said so)."""
    reason = "the disk is full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
    return f"{what}: {reason}"
