"""The static prior's state frame by frame against the truth (app/filter/static_prior.py).

Usage (from the repository root, on a simulated trial with ground truth, e.g. the bench's cache)::

    nice .venv/bin/python scripts/prior_probe.py TRIAL [--every 10] [--config configs/default.yaml]

The trial is replayed with the given configuration (no rerun, no projector). Every ``--every``-th
update of the prior, and every release or discount, prints one line: the time from the first frame,
the image's predicted template error σ (on the configured grid) and the clearest since the last
release, released / held / discounted, the contradiction and motion Δχ², trace(Λ) / trace(H') (how
many frames of the current view the prior's information is worth), and the error (ADD mm / rotation
deg) of the prior's pose (the anchor) and of the image's own fit against the ground truth. It is how
BENCHMARKS.md §6h found a fast reposition's anchor held 1-2 mm off by information gathered on a
poorer view.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np


def _error(vertices: np.ndarray, T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """ADD (mm) and rotation (deg) of ``T`` against ``T_true``."""
    from app import metrics
    from app.geometry import se3

    return 1e3 * metrics.add(T, T_true, vertices), math.degrees(se3.rotation_angle(T, T_true))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trial", type=Path)
    ap.add_argument("--every", type=int, default=10, help="print every k-th update of the prior (default 10)")
    ap.add_argument("--config", type=Path, default=None, help="tracker configuration (default: configs/default.yaml)")
    args = ap.parse_args(argv)

    from app.config import load_config
    from app.filter import static_prior
    from app.pipeline import tracker
    from app.pipeline.replay import replay
    from app.trial.reader import open_trial

    vertices = np.asarray(open_trial(args.trial).load_mesh().vertices)
    truth = _truth(args.trial)
    state = {"stamp": 0.0, "t0": None, "n": 0}
    process = tracker.DepthTracker.process
    update = static_prior.StaticPrior.update

    def traced_process(self, depth_m, stamp, T_base_camera):
        state["stamp"] = stamp
        state["t0"] = stamp if state["t0"] is None else state["t0"]
        return process(self, depth_m, stamp, T_base_camera)

    def traced_update(self, T_image, H, image_std=0.0):
        ratio = np.trace(self.information) / max(np.trace(H) / self.inflation, 1e-30) if self.active else 0.0
        best = self._best_std
        T_anchor = update(self, T_image, H, image_std)
        state["n"] += 1
        if state["n"] % max(args.every, 1) == 0 or self.released or self.discounted:
            T_true = truth(state["stamp"])
            anchor, image = _error(vertices, T_anchor, T_true), _error(vertices, T_image, T_true)
            print(f"{state['stamp'] - state['t0']:6.2f} s  σ {1e3 * image_std:5.2f} mm (best {1e3 * best:5.2f})  "
                  f"released {int(self.released)} held {int(self.held)} discounted {int(self.discounted)}  "
                  f"Δχ² {self.chi2:7.1f} motion {self.motion_chi2:7.1f}  Λ/H' {ratio:5.0f}  "
                  f"anchor {anchor[0]:5.2f} mm {anchor[1]:5.2f} deg  image {image[0]:5.2f} mm {image[1]:5.2f} deg")
        return T_anchor

    tracker.DepthTracker.process = traced_process
    static_prior.StaticPrior.update = traced_update
    try:
        result = replay(args.trial, None, config=load_config(args.config), rrd=False, projector=False)
    finally:
        tracker.DepthTracker.process = process
        static_prior.StaticPrior.update = update
    add = result.summary.get("add_mm") or {}
    print(f"ADD median {add.get('median', float('nan')):.2f} mm, p95 {add.get('p95', float('nan')):.2f} mm")


def _truth(trial: Path):
    """T_base_bone_true(stamp): the ground-truth pose nearest in time (the trial's groundtruth.txt)."""
    from app.trial.tum import read_tum

    stamps, T = read_tum(trial / "groundtruth.txt")
    return lambda stamp: T[int(np.argmin(np.abs(stamps - stamp)))]


if __name__ == "__main__":
    main()
