"""Probe the nearby search's competitors against the truth (issue 32, BENCHMARKS.md "Residual tissue").

    python scripts/competitor_probe.py TRIAL [--every 3]

Replays a simulated trial with the defaults. On every ``--every``-th frame on which the nearby search holds
a competitor it prints nothing but collects: the ADD (mm) of the kept pose and of the competitor to the
truth; their shares as the search compares them (:func:`app.filter.refine_track.consistent_sharp`, each
pose scored on the frame as it is); and a *paired* share: each pose's share within 1 sigma on the common
cells only (stride 1; cells usable at both poses, neither buried, more than ``refine.front_sigmas`` sigma
in front of the model, nor on the tissue's border at either). The summary says how often the competitor is
nearer the truth and how often each score ranks it above the kept pose.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app import metrics  # noqa: E402
from app.config import load_config  # noqa: E402
from app.filter.refine_track import consistent_sharp  # noqa: E402
from app.geometry import se3  # noqa: E402
from app.pipeline.tracker import DepthTracker, start_tracker  # noqa: E402
from app.trial.reader import open_trial  # noqa: E402


def cells(refiner, depth, T_camera_bone) -> dict:
    """Per usable cell (stride 1) of one pose: its pixel key, sharp (within 1 sigma of the model), and
    excluded (buried or on the tissue's border, refine.py step 5)."""
    zbuf, (x0, y0, _, _) = refiner.model_depth(T_camera_bone, 1)
    z, zb, usable = refiner._usable_cells(depth, zbuf, x0, y0, 1)
    prm, cam = refiner.params, refiner.camera
    with np.errstate(invalid="ignore"):
        buried = usable & ((zb - z) > prm.front_sigmas * refiner.sigma(np.where(np.isfinite(z), z, 1.0)))
    border = ndimage.binary_dilation(buried, structure=np.ones((3, 3), bool)) & usable & ~buried
    rows, cols = np.nonzero(usable)
    zi = z[rows, cols]
    u, v = x0 + cols, y0 + rows
    y = np.column_stack([(u - cam.cx) / cam.fx * zi, (v - cam.cy) / cam.fy * zi, zi])
    d = refiner._associate(y, T_camera_bone)[3]
    return dict(key=v.astype(np.int64) * 100_000 + u, sharp=d < prm.sharp_sigmas * refiner.sigma(zi),
                excluded=(buried | border)[rows, cols])


def paired(a: dict, b: dict) -> tuple[float, float]:
    """The two poses' sharp shares on the cells both use."""
    _, ia, ib = np.intersect1d(a["key"], b["key"], return_indices=True)
    keep = ~a["excluded"][ia] & ~b["excluded"][ib]
    return float(a["sharp"][ia[keep]].mean()), float(b["sharp"][ib[keep]].mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trial", type=Path)
    ap.add_argument("--every", type=int, default=3)
    args = ap.parse_args(argv)
    reader = open_trial(args.trial)
    mesh = reader.load_mesh()
    vertices = np.asarray(mesh.vertices)
    tracker = DepthTracker(load_config(None), mesh, reader.meta.camera)
    start_tracker(tracker, reader.meta.initial_pose, reader.meta.point_prior)
    T_base_camera, valid = reader.camera_poses()
    track = tracker.refined_track
    rows = []
    for frame in reader.iter_frames():
        i = frame.index
        tracker.process(frame.depth_m, frame.stamp, T_base_camera[i] if valid[i] else None)
        T_kept_competitor, T_base_kept = track.nearby._T_kept_competitor, track.T_base_bone
        if T_kept_competitor is None or T_base_kept is None or not valid[i] or i % args.every:
            continue
        T_base_competitor = T_base_kept @ T_kept_competitor
        T_camera_base = se3.inverse(T_base_camera[i])
        T_kept, T_comp = T_camera_base @ T_base_kept, T_camera_base @ T_base_competitor
        pair = paired(cells(track.refiner, frame.depth_m, T_kept), cells(track.refiner, frame.depth_m, T_comp))
        rows.append((1e3 * metrics.add(T_base_kept, reader.groundtruth[i], vertices),
                     1e3 * metrics.add(T_base_competitor, reader.groundtruth[i], vertices),
                     consistent_sharp(track.refiner.score(frame.depth_m, T_kept)),
                     consistent_sharp(track.refiner.score(frame.depth_m, T_comp)), *pair))
    tracker.release()
    print(args.trial, f"frames probed: {len(rows)}")
    if rows:
        a = np.array(rows)
        print(f"  ADD median kept {np.median(a[:, 0]):.2f} mm, competitor {np.median(a[:, 1]):.2f} mm; "
              f"competitor nearer the truth on {int(np.sum(a[:, 1] < a[:, 0]))} of {len(a)}")
        for name, k, c in (("consistent sharp (the search's)", 2, 3), ("paired, common cells", 4, 5)):
            diff = a[:, c] - a[:, k]
            print(f"  {name}: competitor - kept median {np.median(diff):+.4f} [{diff.min():+.4f}, {diff.max():+.4f}], "
                  f"competitor above on {int(np.sum(diff > 0))} of {len(a)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
