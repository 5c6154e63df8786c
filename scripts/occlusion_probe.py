"""Probe the slide under the hand (static_occluded): per-frame ADD against the hand's occlusion share.

Usage: nice .venv/bin/python scripts/occlusion_probe.py TRIAL [--variant default|trackonly|nofeedback|...]
    [--every N] [--max-frames N] [--json OUT]

Variants (BENCHMARKS.md §6c): ``default`` (the tracker's defaults); ``trackonly`` (the refinement's own
track alone: never re-seeded from the filter, no feedback; its competitor gap of 1e9 is, since issue 32,
also the recovery's "far": no pose is far, so the recovery's far-gated triggers never fire); ``nofeedback``; ``filteronly`` (refinement off);
``noprior`` (without the static prior, app/filter/static_prior.py: the tracker before §6c) and
``trackonly_noprior`` (§6c's "track alone" probe).
"""
from __future__ import annotations

import argparse
import csv
import json
from dataclasses import replace
from pathlib import Path

import numpy as np


def config_for(variant: str):
    from app.config import load_config

    c = load_config(None)
    if variant == "default":
        return c
    if variant == "trackonly":
        return replace(c, refine=replace(c.refine, feedback=False, reseed_fitness=0.0,
                                         competitor_distance=1e9))
    if variant == "nofeedback":
        return replace(c, refine=replace(c.refine, feedback=False))
    if variant == "filteronly":
        return replace(c, refine=replace(c.refine, enabled=False))
    if variant == "noprior":
        return replace(c, refine=replace(c.refine, static_prior=False))
    if variant == "trackonly_noprior":
        return replace(c, refine=replace(c.refine, static_prior=False, feedback=False, reseed_fitness=0.0,
                                         competitor_distance=1e9))
    raise SystemExit(f"unknown variant {variant!r}")


def occlusion(trial: Path) -> dict[int, float]:
    with open(trial / "simulation.csv") as f:
        return {int(r["frame"]): float(r["occlusion"]) for r in csv.DictReader(f)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("trial")
    ap.add_argument("--variant", default="default")
    ap.add_argument("--every", type=int, default=30)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    from app import metrics
    from app.pipeline.tracker import DepthTracker
    from app.trial.reader import open_trial

    trial = Path(a.trial)
    reader = open_trial(trial)
    mesh = reader.load_mesh()
    tracker = DepthTracker(config_for(a.variant), mesh, reader.meta.camera)
    tracker.start(reader.meta.initial_pose)
    T_base_camera, valid = reader.camera_poses()
    truth = reader.groundtruth
    occ = occlusion(trial)
    pts = np.asarray(mesh.vertices)[:: max(1, len(mesh.vertices) // 2000)]
    rows = []
    for frame in reader.iter_frames():
        i = frame.index
        if a.max_frames is not None and i >= a.max_frames:
            break
        out = tracker.process(frame.depth_m, frame.stamp, T_base_camera[i] if valid[i] else None)
        add = 1e3 * metrics.add(out.T_base_bone, truth[i], pts)
        info = getattr(tracker.refined_track, "last_info", {}) if tracker.refined_track else {}
        row = {"i": i, "occ": occ.get(frame.frame_id, float("nan")), "add": add, "status": out.status.name,
               "fit": out.refine_fitness, "std_mm": 1e3 * out.template_std if out.template_std is not None else None,
               **info}
        rows.append(row)
        if i % a.every == 0:
            print(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
    add = np.array([r["add"] for r in rows])
    ok = np.array([r["status"] == "OK" for r in rows])
    print(f"SUMMARY {trial} {a.variant}: ADD median {np.median(add):.2f} max {add.max():.2f} lost {np.mean(add > 10):.3f} "
          f"ok {ok.mean():.3f} danger {int(np.sum(ok & (add > 5)))}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
