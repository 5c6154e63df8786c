"""Replay a simulated trial and write every frame's tests against the truth (a probe for wrong ok frames).

    python scripts/replay_diag.py TRIAL OUT.csv [--config YAML] [--start-at-truth]

One row per frame: the stamp (s from the start), the status and lifecycle state, ADD (mm, against the
trial's groundtruth.txt), the refinement's evidence the status's tests read (fitness, consistent sharp
share, the template's predicted std, the behind excess, the held Δχ², the nearby competitor's gap,
the competitor flag), whether the frame was weighed, refined or re-initialised, and the reason
codes. The search work is in the last line's ``recovery`` column (JSON).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    from app import metrics
    from app.config import load_config
    from app.filter.status import codes
    from app.pipeline.tracker import DepthTracker, start_tracker
    from app.trial.reader import open_trial

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trial", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--start-at-truth", action="store_true",
                    help="start the tracker at the first frame's true pose instead of the trial's initial pose (a probe)")
    args = ap.parse_args(argv)
    reader = open_trial(args.trial)
    mesh = reader.load_mesh()
    points = np.asarray(mesh.vertices)
    tracker = DepthTracker(load_config(args.config), mesh, reader.meta.camera)
    start_tracker(tracker, reader.groundtruth[0] if args.start_at_truth else reader.meta.initial_pose,
                  reader.meta.point_prior)
    last: dict = {}
    if tracker.refined_track is not None:                       # keep each frame's refinement outcome
        update = tracker.refined_track.update

        def recorded(*a, **kw):
            last["out"] = update(*a, **kw)
            return last["out"]
        tracker.refined_track.update = recorded
    T_base_camera, valid = reader.camera_poses()
    fields = ["t", "status", "state", "add_mm", "fitness", "sharp", "template_std_mm", "behind", "held_chi2",
              "nearby", "competitor", "weighed", "refined", "reinitialised", "reasons"]
    with open(args.out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        for frame in reader.iter_frames():
            i = frame.index
            last["out"] = None
            r = tracker.process(frame.depth_m, frame.stamp, T_base_camera[i] if valid[i] else None)
            add = 1e3 * metrics.add(r.T_base_bone, reader.groundtruth[i], points)
            ev = last.get("out")
            w.writerow([f"{frame.stamp - reader.stamps[0]:.4f}", str(r.status), r.state, f"{add:.3f}",
                        f"{r.refine_fitness:.4f}", f"{r.refine_sharp:.4f}", f"{1e3 * r.template_std:.3f}",
                        f"{getattr(ev, 'behind', float('nan')):.5f}", f"{getattr(ev, 'held_chi2', float('nan')):.3f}",
                        f"{r.nearby:.5f}", int(r.competitor), int(r.weighed), int(r.refined), int(r.reinitialised),
                        ";".join(codes(r.reasons))])
        w.writerow(["recovery", json.dumps(tracker.report()["recovery"])])
    tracker.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
