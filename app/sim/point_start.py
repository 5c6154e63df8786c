"""A simulated trial made point-only: no ``initial_pose``, its ``point_prior`` moved off the crest.

Import as ``from app.sim.point_start import make_point_only``. The simulator (app/sim/simulator.py)
writes both a coarse ``initial_pose`` and a ``point_prior`` (the mesh's highest vertex, along its +z,
at the bone's first pose: the crest's top, exactly on the surface). Issue 33's start benchmark and
tests need what a surgeon gives without an alignment: a point 2-5 mm off the crest and no pose.
Only trial.yaml is rewritten (RECORDING_FORMAT.md: both keys are optional), in a trial the caller wrote.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from app.trial.meta import META_FILE, dump_meta, load_meta


def offset_point(point: np.ndarray, distance_m: float, rng: np.random.Generator) -> np.ndarray:
    """``point`` moved ``distance_m`` in a uniformly random direction (base frame)."""
    direction = rng.normal(size=3)
    return np.asarray(point, float) + distance_m * direction / np.linalg.norm(direction)


def make_point_only(trial_dir: str | Path, distance_m: float, rng: np.random.Generator,
                    keep_point: bool = True) -> np.ndarray | None:
    """Rewrite the trial's trial.yaml without ``initial_pose`` and with its ``point_prior`` moved
    ``distance_m`` off (:func:`offset_point`), or without a point either (``keep_point`` False: a start
    from nothing); returns the new point (base frame, m) or None."""
    path = Path(trial_dir) / META_FILE
    meta = load_meta(path)
    if meta.point_prior is None:
        raise ValueError(f"{path}: no point_prior to move (a simulated trial has one)")
    meta.initial_pose = None
    meta.point_prior = offset_point(meta.point_prior, distance_m, rng) if keep_point else None
    dump_meta(meta, path)
    return meta.point_prior
