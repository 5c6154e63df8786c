"""The fits around a kept pose: how far the refinement's minimum spreads, and how well its far members score.

Usage (from the repository root)::

    .venv/bin/python scripts/nearby_plateau.py TRIAL [--estimate DIR] [--every N] [--starts N]
        [--sigma-p M] [--sigma-r DEG] [--from-frame K] [--config FILE] [--json OUT]

For every ``N``-th frame of the trial (from ``--from-frame``), the kept pose is the tracker's estimate in
``DIR/estimate.txt`` (a replay's output; the frame's nearest stamp) or, without ``--estimate``, the ground
truth. The kept pose is refined at width 0 (the track's own fit), then ``--starts`` poses are drawn about it
as the nearby search draws them (app/filter/motion.py ``draws_about_centroid``, ``--sigma-p`` m per axis,
``--sigma-r`` deg about the bone's centroid; the defaults are ``refine.nearby_sigma_p`` / ``_r``) and each is
refined twice, at width 0 and at the default first width. A fit whose template points (the mesh's vertices,
subsampled, as the status does without a plan) lie more than ``status.max_template_std`` from the kept fit's is
*far*: the row gives the best far fit's gap, its distance from the truth (ADD, mm), and its consistent sharp share
(app/filter/refine_track.py ``consistent_sharp``) less the kept fit's, ``delta``. The truth refined at width 0
is scored beside them.

The question it answers (issue 32, BENCHMARKS.md "Residual tissue at seed 3: no rule on the fits' scores"):
could a uniqueness rule that asks whether another fit explains the image *within* a margin (not only better by
it, as the nearby search does) tell a track on residual tissue from one on a clean crest? Only if the clean
crests' far fits score clearly below their kept fit while the tissue's score within the margin.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from app import metrics
from app.config import load_config
from app.filter.motion import draws_about_centroid
from app.filter.refine import Refiner
from app.filter.refine_track import behind_excess, consistent_sharp
from app.geometry import se3
from app.pipeline.tracker import refine_params
from app.trial.reader import open_trial
from app.trial.tum import read_tum


def _fit_row(result, T_camera_bone_kept_fit, T_camera_bone_true, points_bone) -> dict:
    """One fit's template gap from the kept fit (mm), distance from the truth (ADD, mm) and scores."""
    T = result.T_camera_bone
    return {"gap_mm": 1e3 * metrics.mdd(T, T_camera_bone_kept_fit, points_bone),
            "add_mm": 1e3 * metrics.add(T, T_camera_bone_true, points_bone),
            "consistent": consistent_sharp(result), "behind_excess": behind_excess(result),
            "converged": bool(result.converged)}


def _kept_poses(reader, estimate: str | None) -> np.ndarray:
    """(N, 4, 4) base-frame kept poses per frame: the estimate nearest in time, or the ground truth."""
    if estimate is None:
        return np.asarray(reader.groundtruth, float)
    stamps, T_base_bone = read_tum(f"{estimate}/estimate.txt")
    nearest = np.abs(stamps[None, :] - np.asarray(reader.stamps)[:, None]).argmin(axis=1)
    return T_base_bone[nearest]


def frame_row(refiner, depth, T_camera_bone_kept, T_camera_bone_true, points_bone, starts, sigma_p, sigma_r,
              rng, gap) -> dict:
    """The kept fit, the truth's fit and the far fits' best of one frame (module docstring); ``gap`` (m): a fit
    whose template lies further than this from the kept fit's is far."""
    kept = refiner.refine(depth, T_camera_bone_kept, start_width=0.0)
    T_kept_fit = kept.T_camera_bone
    row = {"kept": _fit_row(kept, T_kept_fit, T_camera_bone_true, points_bone),
           "truth": _fit_row(refiner.refine(depth, T_camera_bone_true, start_width=0.0), T_kept_fit,
                             T_camera_bone_true, points_bone)}
    centre = se3.transform_points(T_camera_bone_kept, refiner.center[None])[0]
    q0, p0 = se3.to_quat_trans(T_camera_bone_kept)
    p, q = draws_about_centroid(centre, p0, q0, starts, sigma_p, sigma_r, rng)
    fits = []
    for T_start in se3.from_quat_trans(q, p):
        for width, kwargs in (("0", {"start_width": 0.0}), ("default", {})):
            fit = _fit_row(refiner.refine(depth, T_start, **kwargs), T_kept_fit, T_camera_bone_true, points_bone)
            fits.append({**fit, "width": width})
    row["fits"] = fits
    row["far"] = [f for f in fits if f["converged"] and f["gap_mm"] > 1e3 * gap]
    best = max(row["far"], key=lambda f: f["consistent"], default=None)
    row["best_far"] = best
    row["delta"] = best["consistent"] - row["kept"]["consistent"] if best else float("nan")
    return row


def main(argv: list[str] | None = None) -> list[dict]:
    """Print one line per frame; return the rows (and write them to ``--json``)."""
    config = load_config(None)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("trial")
    ap.add_argument("--estimate", default=None, help="a replay's output folder (its estimate.txt); default: the truth")
    ap.add_argument("--every", type=int, default=45)
    ap.add_argument("--from-frame", type=int, default=30)
    ap.add_argument("--starts", type=int, default=8)
    ap.add_argument("--sigma-p", type=float, default=config.refine.nearby_sigma_p)
    ap.add_argument("--sigma-r", type=float, default=float(np.rad2deg(config.refine.nearby_sigma_r)))
    ap.add_argument("--config", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if args.every < 1 or args.starts < 1:
        ap.error(f"--every {args.every} --starts {args.starts}: give 1 or more for each")
    config = load_config(args.config)
    reader = open_trial(args.trial)
    if reader.groundtruth is None:
        raise SystemExit(f"{args.trial}: no ground truth (groundtruth.txt): nothing to measure against")
    mesh = reader.load_mesh()
    vertices = np.asarray(mesh.vertices, float)
    refiner = Refiner(vertices, np.asarray(mesh.faces), reader.meta.camera, refine_params(config), seed=config.seed)
    points_bone = vertices[::max(1, len(vertices) // 500)]
    T_base_camera, valid = reader.camera_poses()
    T_base_bone_kept = _kept_poses(reader, args.estimate)
    rng = np.random.default_rng(1)
    rows = []
    for i in range(args.from_frame, len(reader), args.every):
        depth = reader.read_depth(i)
        if depth is None or not valid[i]:
            continue
        T_camera_base = se3.inverse(T_base_camera[i])
        row = frame_row(refiner, depth, T_camera_base @ T_base_bone_kept[i], T_camera_base @ reader.groundtruth[i],
                        points_bone, args.starts, args.sigma_p, np.deg2rad(args.sigma_r), rng,
                        config.status.max_template_std)
        row["frame"] = i
        rows.append(row)
        k, t, b = row["kept"], row["truth"], row["best_far"]
        far = (f"best far: gap {b['gap_mm']:.2f} mm, ADD {b['add_mm']:.2f} mm, delta {row['delta']:+.3f}, "
               f"excess {b['behind_excess']:+.3f} (width {b['width']})" if b else "no far fit")
        print(f"frame {i:4d} | kept: ADD {k['add_mm']:.2f} mm, consistent {k['consistent']:.3f} | truth: gap "
              f"{t['gap_mm']:.2f} mm, consistent {t['consistent']:.3f} | far {len(row['far'])}/{len(row['fits'])} | "
              + far, flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return rows


if __name__ == "__main__":
    main()
