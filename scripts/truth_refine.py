"""Refine from the ground truth on frames of a trial: where the refinement's minimum lies (BENCHMARKS.md §6o).

Usage (from the repository root)::

    .venv/bin/python scripts/truth_refine.py TRIAL [--from S] [--to S] [--every N] [--config FILE] [--json OUT]

For every ``N``-th frame between ``--from`` and ``--to`` seconds (from the trial's first stamp), the
tracker's refinement (app/filter/refine.py, the configuration's ``refine.*``) is started at the
true pose once at width 0 (as the track refines each frame) and once at the default first Tukey
width (as a seeded start, the filter's estimate and the wide search's second step refine): how far
each ends from the truth (ADD over the mesh's vertices, mm; rotation, deg), its sharp share within
1 σ, its consistent sharp share (less the share behind the model beyond the noise's bound), its
share behind the model beyond that bound, and the pixels it explains. A frame whose width-0 fit
stays at the truth while the default width slides shows a loose direction of the image (the
crest's roll with a third of it in view); a fit that scores better than the truth's while leaving
more behind the model than the noise explains is one the status's behind rule rejects.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from app import metrics
from app.config import load_config
from app.filter.refine import Refiner
from app.filter.refine_track import behind_excess, consistent_sharp
from app.filter.wide_search import explained_pixels
from app.geometry import se3
from app.pipeline.tracker import refine_params
from app.trial.reader import open_trial


def _row(result, T_camera_bone_true, points_bone) -> dict:
    """One refinement's distance from the truth (ADD over ``points_bone``, mm; rotation, deg) and its scores."""
    T_camera_bone = result.T_camera_bone
    return {"add_mm": 1e3 * metrics.add(T_camera_bone, T_camera_bone_true, points_bone),
            "rot_deg": float(np.rad2deg(se3.rotation_angle(T_camera_bone, T_camera_bone_true))),
            "sharp": result.sharp, "consistent": consistent_sharp(result), "behind_excess": behind_excess(result),
            "pixels": explained_pixels(result), "converged": result.converged}


def main(argv: list[str] | None = None) -> list[dict]:
    """Print the table; return its rows (and write them to ``--json``)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("trial")
    ap.add_argument("--from", dest="t_from", type=float, default=0.0)
    ap.add_argument("--to", dest="t_to", type=float, default=float("inf"))
    ap.add_argument("--every", type=int, default=9)
    ap.add_argument("--config", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if args.every < 1:
        ap.error(f"--every {args.every}: give a frame step of 1 or more")
    config = load_config(args.config)
    reader = open_trial(args.trial)
    if reader.groundtruth is None:
        raise SystemExit(f"{args.trial}: no ground truth (groundtruth.txt): nothing to refine from")
    mesh = reader.load_mesh()
    vertices = np.asarray(mesh.vertices, float)
    refiner = Refiner(vertices, np.asarray(mesh.faces), reader.meta.camera, refine_params(config), seed=config.seed)
    T_base_camera, valid = reader.camera_poses()
    points_bone = vertices[::max(1, len(vertices) // 500)]
    rows = []
    print(f"{'t (s)':>6} | {'width 0: ADD mm / deg, sharp, consistent, behind':<50} | default width: the same")
    for i in range(0, len(reader), args.every):
        t = float(reader.stamps[i] - reader.stamps[0])
        if not (args.t_from <= t <= args.t_to) or not valid[i]:
            continue
        depth = reader.read_depth(i)
        if depth is None:
            continue
        T_camera_bone_true = se3.inverse(T_base_camera[i]) @ reader.groundtruth[i]
        narrow = _row(refiner.refine(depth, T_camera_bone_true, start_width=0.0), T_camera_bone_true, points_bone)
        wide = _row(refiner.refine(depth, T_camera_bone_true), T_camera_bone_true, points_bone)
        rows.append({"t": t, "frame": i, "width0": narrow, "default": wide})
        print(f"{t:6.2f} | " + " | ".join(
            f"{r['add_mm']:5.2f} mm / {r['rot_deg']:4.1f} deg, {r['sharp']:.3f}, {r['consistent']:.3f}, "
            f"{r['behind_excess']:+.3f}" for r in (narrow, wide)), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return rows


if __name__ == "__main__":
    main()
