"""How often the one-point initialiser finds the bone: ``python -m app.bench.init_point TRIAL... [--seeds N]``.

For each trial (with ground truth and ``point_prior``), the sampler (app/filter/smc_init/, the
default settings and the default tracker's backend) runs ``--seeds`` times on the first frame with
different seeds (settings: the default tracker config's ``init.*``); a run succeeds when its pose is within 5 mm ADD and 5 degrees of the truth.
Prints a table (success count, ADD median, wall and process-CPU time medians, evaluations) and
writes JSON (``--json``). ``--restarts``, ``--no-symmetry-check`` and ``--full-resolution`` (every
evaluation at the filter's resolution and mesh, the initialiser before its coarse levels) compare
the initialiser's options. The first run of a process also searches the mesh's symmetries
(cached for the next runs): its time is in ``symmetry_search_s``, apart.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from app import metrics
from app.config import load_config
from app.depth_image import downsample_nearest
from app.filter.smc_init import OnePointInitialiser, mesh_symmetries, smc_config_for
from app.pipeline.tracker import DepthTracker
from app.trial.reader import open_trial

SUCCESS_ADD_MM, SUCCESS_ROT_DEG = 5.0, 5.0


def run_trial(path: Path, seeds: int, restarts: int | None = None, symmetry_check: bool = True,
              full_resolution: bool = False) -> dict:
    """The initialiser ``seeds`` times on the trial's first frame: per-run ADD (mm), rotation (deg),
    wall and process-CPU seconds, evaluations."""
    trial = open_trial(path)
    if trial.groundtruth is None or trial.meta.point_prior is None:
        raise SystemExit(f"{path}: needs groundtruth.txt and point_prior")
    config = load_config(None)
    mesh = trial.load_mesh()
    tracker = DepthTracker(config, mesh, trial.meta.camera)
    frame = next(iter(trial.iter_frames()))
    T_base_camera, _ = trial.camera_poses()
    depth = downsample_nearest(frame.depth_m, *config.resolution)
    points, T_gt = np.asarray(mesh.vertices), trial.groundtruth[0]
    smc = smc_config_for(config, restarts=restarts, symmetry_check=symmetry_check,
                         coarse_levels=() if full_resolution else None)
    runs = []
    try:
        t0 = time.perf_counter()
        if symmetry_check:   # once per mesh and process (cached): timed apart from the runs
            mesh_symmetries(tracker.mesh_vertices, tracker.mesh_faces)
        symmetry_search_s = time.perf_counter() - t0
        for seed in range(seeds):
            initialiser = OnePointInitialiser(tracker.backend, tracker.camera, tracker.mesh_vertices,
                                              tracker.mesh_faces, smc, np.random.default_rng(100 + seed))
            c0 = time.process_time()
            result = initialiser.run(depth, T_base_camera[0], trial.meta.point_prior)
            T = result.estimate.T_base_bone
            runs.append({"seed": 100 + seed, "add_mm": 1e3 * metrics.add(T, T_gt, points),
                         "rotation_deg": float(np.degrees(metrics.rotation_error(T, T_gt))),
                         "seconds": result.seconds, "cpu_seconds": time.process_time() - c0,
                         "evaluations": result.evaluations, "levels": result.levels})
    finally:
        tracker.release()
    ok = [r for r in runs if r["add_mm"] < SUCCESS_ADD_MM and r["rotation_deg"] < SUCCESS_ROT_DEG]
    return {"trial": str(path), "mesh": trial.meta.mesh, "runs": runs, "successes": len(ok),
            "add_mm_median": float(np.median([r["add_mm"] for r in runs])),
            "seconds_median": float(np.median([r["seconds"] for r in runs])),
            "cpu_seconds_median": float(np.median([r["cpu_seconds"] for r in runs])),
            "evaluations_median": float(np.median([r["evaluations"] for r in runs])),
            "symmetry_search_s": symmetry_search_s, "gl": tracker.gl_description}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m app.bench.init_point", description=__doc__.split("\n\n")[0])
    parser.add_argument("trials", nargs="+", type=Path)
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--restarts", type=int, default=None, help="runs per initialisation (default: the config's)")
    parser.add_argument("--no-symmetry-check", action="store_true", help="without the mesh-symmetry check")
    parser.add_argument("--full-resolution", action="store_true",
                        help="every evaluation at the filter's resolution and mesh (no coarse levels)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    results = [run_trial(p, args.seeds, args.restarts, not args.no_symmetry_check, args.full_resolution)
               for p in args.trials]
    print(f"{'trial':<40} {'mesh':<22} {'found':>7} {'ADD med mm':>11} {'s med':>7} {'CPU s med':>9} "
          f"{'evals med':>9} {'sym s':>6}")
    for r in results:
        print(f"{r['trial']:<40} {r['mesh']:<22} {r['successes']:>3}/{len(r['runs']):<3} "
              f"{r['add_mm_median']:>11.1f} {r['seconds_median']:>7.2f} {r['cpu_seconds_median']:>9.2f} "
              f"{r['evaluations_median']:>9.0f} {r['symmetry_search_s']:>6.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
