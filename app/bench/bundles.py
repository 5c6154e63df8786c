"""Folders as bytes: a trial (or a run's output folder) packed on one machine and unpacked on another.

A bench on a cluster reads each trial from its path when the worker sees it (a shared file system);
otherwise the driver packs the trial into an uncompressed tar (depth PNGs are compressed already)
and ships it as an object, and the worker unpacks it once per machine under
:func:`node_cache` ``/<fingerprint>``. :func:`fingerprint` tells whether the folder a worker sees
at the trial's path is the driver's trial and not another one cached there earlier.
"""
from __future__ import annotations

import hashlib
import io
import os
import shutil
import tarfile
import tempfile
from pathlib import Path

FINGERPRINT_FILES = ("trial.yaml", "frames.csv", "groundtruth.txt", "simulation.yaml", "joints.csv")


def fingerprint(trial: str | Path) -> str | None:
    """SHA-1 of the trial's text files (:data:`FINGERPRINT_FILES`, those present) and of its depth
    frames' names and sizes; None when ``trial`` holds no ``trial.yaml``."""
    trial = Path(trial)
    if not (trial / "trial.yaml").is_file():
        return None
    h = hashlib.sha1()
    for name in FINGERPRINT_FILES:
        f = trial / name
        if f.is_file():
            h.update(name.encode() + b"\0" + f.read_bytes() + b"\0")
    depth = trial / "depth"
    if depth.is_dir():
        for entry in sorted(os.scandir(depth), key=lambda e: e.name):
            h.update(f"{entry.name}:{entry.stat().st_size}\n".encode())
    return h.hexdigest()


def pack(folder: str | Path) -> bytes:
    """The folder's files as an uncompressed tar (paths relative to ``folder``)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        tar.add(str(folder), arcname=".")
    return buf.getvalue()


def unpack(data: bytes, dest: str | Path, replace: bool = True) -> Path:
    """Unpack :func:`pack`'s bytes into ``dest`` (made whole in a sibling folder, then renamed into
    place, so that a reader never sees half a folder). An existing ``dest`` is replaced, or with
    ``replace=False`` kept, the packed files written into it over their namesakes only."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    if not replace and dest.exists():
        with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
            tar.extractall(dest, filter="data")
        return dest
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        tar.extractall(tmp, filter="data")
    if dest.exists():
        shutil.rmtree(dest)
    tmp.rename(dest)
    return dest


def node_cache() -> Path:
    """Where a worker keeps the trials shipped to it (one folder per fingerprint)."""
    return Path(tempfile.gettempdir()) / "osteonav-shipped-trials"


def shipped_trial(data: bytes, key: str) -> Path:
    """The trial of ``data`` unpacked under :func:`node_cache` ``/key`` (once per machine: a second
    worker finding it complete reuses it; two unpacking at once both finish, the last rename wins)."""
    dest = node_cache() / key
    if fingerprint(dest) == key:
        return dest
    tmp = node_cache() / f"{key}.{os.getpid()}"
    unpack(data, tmp)
    try:
        tmp.rename(dest)
    except OSError:   # another worker renamed its copy first, or a stale folder is in the way
        if fingerprint(dest) == key:
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            shutil.rmtree(dest, ignore_errors=True)
            tmp.rename(dest)
    return dest
