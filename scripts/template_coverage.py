"""Calibrate the predicted template error (status.covariance_inflation): predicted against measured.

Usage (from the repository root, on simulated trials with ground truth, e.g. the bench's cache)::

    nice .venv/bin/python scripts/template_coverage.py recordings/matrix/cache/crest_*/static_clear \
        --out /tmp/coverage.json

Each trial is replayed with the default tracker (DepthTracker, frame by frame). On every refined
frame after ``--settle`` s it records the refinement's predicted template std at inflation 1,
σ₁ = template_std / sqrt(inflation) (app/filter/refine.py: the largest predicted std over the
template's points, Σ = H⁻¹), and the measured template error e = max over the same points of
|T_est x − T_gt x|. The inflation that makes sqrt(inflation) σ₁ cover e on a share q of the frames is
quantile_q(e / σ₁)²; the script prints, per inflation candidate, the coverage (share of frames with
e <= sqrt(inflation) σ₁) over all frames and for the worst trial, and the share of frames whose
bound stays under status.max_template_std (1 mm), i.e. what the ok status could keep.

``--edge-band PX`` is a probe of where the error comes from: each frame's measured pixels within PX
pixels of a depth discontinuity (a jump over ``EDGE_JUMP_M`` between neighbours) are made invalid
before the tracker sees them (the time-of-flight model's multipath bias and mixed pixels sit there;
BENCHMARKS.md "The seen test on time of flight"). The filter and every status test see the masked
image too, so its ok share is not the product's. ``scripts/seen_candidates.py`` compares bounds over
several sensor models' JSON files.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

INFLATIONS = (1.0, 2.0, 4.0, 6.0, 9.0, 16.0, 25.0)
QUANTILES = (0.5, 0.68, 0.9, 0.95)
EDGE_JUMP_M = 0.010   # m, a depth jump between neighbours that --edge-band treats as a discontinuity (probe only)


def edge_masked(depth_m: np.ndarray, band_px: int, jump_m: float = EDGE_JUMP_M) -> np.ndarray:
    """``depth_m`` with the pixels within ``band_px`` of a depth discontinuity set to 0 (invalid): the pixels
    either side of a jump over ``jump_m``, or next to an invalid one (app/sim/sensors/common.py
    :func:`depth_edges`, the sensor models' own), grown by ``band_px`` pixels; ``band_px`` 0 returns the
    image unchanged."""
    if band_px <= 0:
        return depth_m
    from scipy import ndimage

    from app.sim.sensors.common import depth_edges

    edge = ndimage.binary_dilation(depth_edges(depth_m, jump_m), iterations=band_px)
    return np.where(edge, 0.0, depth_m).astype(depth_m.dtype)


def frames_of(trial: Path, settle_s: float, edge_band: int = 0) -> dict:
    """Per refined frame of ``trial``: raw predicted std (m), measured template error (m), ADD (mm), status."""
    from app import metrics
    from app.config import load_config
    from app.pipeline.tracker import DepthTracker
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    config = load_config(None)
    mesh = reader.load_mesh()
    tracker = DepthTracker(config, mesh, reader.meta.camera)
    tracker.start(reader.meta.initial_pose)
    track = tracker.refined_track
    plan = track.plan_points + track.refiner.center
    inflation = track.inflation
    T_base_camera, valid = reader.camera_poses()
    points = np.asarray(mesh.vertices)
    out = {"std1_m": [], "error_m": [], "add_mm": [], "status": [], "t": [], "f": [], "noise_m": [], "sigma_model_m": []}
    t0 = reader.stamps[0]
    for frame in reader.iter_frames():
        i = frame.index
        r = tracker.process(edge_masked(frame.depth_m, edge_band), frame.stamp, T_base_camera[i] if valid[i] else None)
        if not getattr(r, "refined", False) or frame.stamp - t0 < settle_s or not np.isfinite(r.template_std):
            continue
        T_gt = reader.groundtruth[i]
        moved = (plan @ r.T_base_bone[:3, :3].T + r.T_base_bone[:3, 3]) - (plan @ T_gt[:3, :3].T + T_gt[:3, 3])
        out["std1_m"].append(float(r.template_std / np.sqrt(inflation)))
        out["error_m"].append(float(np.linalg.norm(moved, axis=1).max()))
        out["add_mm"].append(float(1e3 * metrics.add(r.T_base_bone, T_gt, points)))
        out["status"].append(str(r.status))
        out["t"].append(float(frame.stamp - t0))
        out["f"].append(float(track.last_info.get("correlation", np.nan)))
        out["noise_m"].append(1e-3 * float(track.last_info.get("noise_mm", np.nan)))
        z = (np.linalg.inv(T_base_camera[i]) @ r.T_base_bone)[2, 3]
        out["sigma_model_m"].append(float(track.refiner.sigma(np.array([z]))[0]))
    tracker.release()
    return out


def report(runs: dict[str, dict]) -> dict:
    """The coverage table (module docstring) as a dict, printed too."""
    ratio_all = np.concatenate([np.asarray(r["error_m"]) / np.asarray(r["std1_m"]) for r in runs.values() if r["std1_m"]])
    std_all = np.concatenate([np.asarray(r["std1_m"]) for r in runs.values() if r["std1_m"]])
    table = {"frames": int(len(ratio_all)), "trials": len(runs),
             "needed_inflation": {str(q): float(np.quantile(ratio_all, q) ** 2) for q in QUANTILES}, "rows": []}
    print(f"{len(ratio_all)} refined frames of {len(runs)} trials; measured / predicted (inflation 1) ratio quantiles:")
    for q in QUANTILES:
        print(f"  q {q:.2f}: ratio {np.quantile(ratio_all, q):.2f} -> inflation {np.quantile(ratio_all, q) ** 2:.1f}")
    print("\ninflation | coverage all | coverage worst trial (which) | bound <= 1 mm (share of frames) | bound median (mm)")
    for k in INFLATIONS:
        per = {name: float(np.mean(np.asarray(r["error_m"]) <= np.sqrt(k) * np.asarray(r["std1_m"])))
               for name, r in runs.items() if r["std1_m"]}
        worst = min(per, key=per.get)
        cover = float(np.mean(ratio_all <= np.sqrt(k)))
        under = float(np.mean(np.sqrt(k) * std_all <= 1e-3))
        med = float(1e3 * np.sqrt(k) * np.median(std_all))
        table["rows"].append({"inflation": k, "coverage": cover, "worst_coverage": per[worst], "worst_trial": worst,
                              "bound_under_1mm": under, "bound_median_mm": med})
        print(f"{k:9.1f} | {cover:12.2f} | {per[worst]:.2f} ({worst}) | {under:.2f} | {med:.2f}")
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("trials", nargs="+", type=Path)
    parser.add_argument("--settle", type=float, default=0.5, help="seconds left out at the start (convergence)")
    parser.add_argument("--out", type=Path, help="JSON of the per-frame values and the table")
    parser.add_argument("--edge-band", type=int, default=0, help="px about depth discontinuities made invalid (a probe)")
    args = parser.parse_args()
    runs = {}
    for trial in args.trials:
        name = f"{trial.parent.name}/{trial.name}"
        if not (trial / "groundtruth.txt").is_file():
            print(f"{trial}: skipped (not a simulated trial with groundtruth.txt)")
            continue
        runs[name] = frames_of(trial, args.settle, args.edge_band)
        if args.out:
            args.out.write_text(json.dumps({"runs": runs}))
        r = runs[name]
        print(f"{name}: {len(r['std1_m'])} frames, predicted (inflation 1) median "
              f"{1e3 * np.median(r['std1_m']):.3f} mm, measured median {1e3 * np.median(r['error_m']):.3f} mm", flush=True)
    table = report(runs)
    if args.out:
        args.out.write_text(json.dumps({"table": table, "runs": runs}))


if __name__ == "__main__":
    main()
