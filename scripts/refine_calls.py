"""The refinement's calls of a replay, recorded and replayed on each backend: equality and time per call.

Usage (from the repository root; short trials, run with nice on a shared machine)::

    nice .venv/bin/python scripts/refine_calls.py --crests all --seconds 1 --frames 40 --out /tmp/refine_calls.json

For each CT crest (``../shared/data/pelvis/crest_*.ply``) a ``static_clear`` trial is simulated (cached
under --cache), the default tracker runs over its first --frames frames and every call of
``Refiner.refine`` and ``Refiner.score`` is recorded (the frame, the start pose, the first Tukey width).
Each call is then run again on fresh refiners of each backend (``numpy``: the cKDTree reference,
``numba``: the kernels), and the results are compared with the numpy reference: the largest
displacement of a mesh vertex between the two refined poses (mm), the largest relative difference
of H, and the differences of the status's inputs (fitness, sharp, behind, behind_allowed, noise,
correlation, used, expected). Also the mean CPU time per call of each backend over all calls and over
the steady calls (frames after the first, whose seeding is a one-off: the least of --repeats runs),
and with --split the steady calls' split by stage (:func:`stage_timers`). This is the 8-crest comparison of issue 35 (the fast test on random
inputs is tests/test_refine_kernels.py).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))          # this checkout's app, not an installed one
PELVIS = REPO.parent / "shared" / "data" / "pelvis"
FIELDS = ("fitness", "sharp", "behind", "behind_allowed", "noise", "correlation", "behind_mean", "behind_var", "rms")
COUNTS = ("used", "expected", "confirmed", "stride", "converged")


def trial_path(cache: Path, crest: Path, scenario: str, seconds: float, seed: int) -> Path:
    from app.sim.simulator import simulate

    out = cache / f"{crest.stem}_{scenario}_{seconds:g}s_seed{seed}"
    if not (out / "groundtruth.txt").is_file() or (out / ".recording-in-progress").exists():
        simulate(out, mesh_path=crest, scenario_name=scenario, seconds=seconds, seed=seed, overwrite=True)
    return out


def record(trial: Path, frames: int) -> tuple[list, list, dict]:
    """(calls, depths, setup): each recorded call ('refine' | 'score', frame, T_camera_bone, start_width);
    ``setup`` what a refiner equal to the tracker's is built from."""
    from app.config import load_config
    from app.pipeline.tracker import DepthTracker
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    config = load_config(None)
    mesh = reader.load_mesh()
    tracker = DepthTracker(config, mesh, reader.meta.camera)
    tracker.start(reader.meta.initial_pose)
    refiner = tracker.refined_track.refiner
    calls, depths, current = [], [], [0]
    refine, score = refiner.refine, refiner.score

    def rec_refine(depth, T, start_width=None):
        calls.append(("refine", current[0], np.array(T, float), start_width))
        return refine(depth, T, start_width)

    def rec_score(depth, T):
        calls.append(("score", current[0], np.array(T, float), None))
        return score(depth, T)

    refiner.refine, refiner.score = rec_refine, rec_score
    T_base_camera, valid = reader.camera_poses()
    try:
        for i in range(min(frames, len(reader))):
            depth = reader.read_depth(i)
            depths.append(depth)
            current[0] = i
            tracker.process(depth, float(reader.stamps[i]), T_base_camera[i] if valid[i] else None)
    finally:
        tracker.release()
    setup = {"vertices": np.asarray(mesh.vertices, float), "faces": np.asarray(mesh.faces), "camera": refiner.camera,
             "params": refiner.params, "seed": config.seed}
    return calls, depths, setup


def stage_timers() -> tuple[dict, callable]:
    """(totals, undo): process CPU seconds spent in each of the refinement's stages (its kernels, the
    noise estimate of step 7, the behind moments), by wrapping them; ``undo()`` restores them."""
    import app.filter.refine as refine
    from app.filter import refine_kernels as kernels

    totals: dict[str, float] = {}
    saved = []

    def wrap(owner, name, label):
        fn = getattr(owner, name)
        saved.append((owner, name, fn))

        def timed(*a, **k):
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                totals[label] = totals.get(label, 0.0) + time.process_time() - t0
        setattr(owner, name, timed)

    for name in ("zbuffer", "measurements", "neighbours", "nearest", "gather", "normal_equations",
                 "gauss_newton", "statistics"):
        if hasattr(kernels, name):
            wrap(kernels, name, name)
    wrap(refine.Refiner, "_residual_noise", "residual_noise")
    wrap(refine, "behind_moments", "behind_moments")

    def undo():
        for owner, name, fn in reversed(saved):
            setattr(owner, name, fn)
    return totals, undo


def run_calls(refiner, calls, depths) -> tuple[list, float]:
    results = []
    t0 = time.process_time()
    for kind, frame, T, width in calls:
        if kind == "refine":
            results.append(refiner.refine(depths[frame], T, width))
        else:
            results.append(refiner.score(depths[frame], T))
    return results, time.process_time() - t0


def vertex_gap_mm(T_a: np.ndarray, T_b: np.ndarray, vertices: np.ndarray) -> float:
    """Largest displacement (mm) of a mesh vertex between two poses."""
    a = vertices @ T_a[:3, :3].T + T_a[:3, 3]
    b = vertices @ T_b[:3, :3].T + T_b[:3, 3]
    return float(1e3 * np.max(np.linalg.norm(a - b, axis=1)))


def compare(ref, new, vertices, center) -> dict:
    """The differences between two RefineResults of one call (the numpy reference's ``ref``): the pose
    (largest vertex displacement, mm), H (largest entry difference over the largest entry), the
    template's predicted error from H (relative; the mesh's vertices as the template, inflation 1),
    the status's inputs (absolute) and whether each count differs (0 / 1)."""
    from app.filter.refine import template_std

    out = {"pose_mm": vertex_gap_mm(ref.T_camera_bone, new.T_camera_bone, vertices)}
    scale = max(np.abs(ref.H).max(), 1e-30)
    out["H_rel"] = float(np.abs(new.H - ref.H).max() / scale)
    a, b = (template_std(r.H, vertices[::20] - center) for r in (ref, new))
    out["template_std_rel"] = 0.0 if a == b else float(abs(a - b) / a)
    for f in FIELDS:
        a, b = getattr(ref, f), getattr(new, f)
        out[f] = 0.0 if (np.isnan(a) and np.isnan(b)) else float(abs(a - b))
    for f in COUNTS:
        out[f] = int(getattr(ref, f) != getattr(new, f))
    return out


def main(argv=None) -> list[dict]:
    """The rows (one per crest; module docstring), printed as JSON lines and written to --out."""
    from app.filter.refine import Refiner
    from dataclasses import replace

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--crests", nargs="+", default=["all"], help="crest names (crest_left_02 ...) or all")
    ap.add_argument("--scenario", default="static_clear")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--backends", nargs="+", default=["numpy", "numba"])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/refine_calls_cache"))
    ap.add_argument("--split", action="store_true", help="also the time per stage of the default backend")
    ap.add_argument("--repeats", type=int, default=3, help="the steady calls' time: the least of this many runs")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    crests = sorted(PELVIS.glob("crest_*.ply")) if args.crests == ["all"] else [PELVIS / f"{c}.ply" for c in args.crests]
    rows = []
    for crest in crests:
        trial = trial_path(args.cache, crest, args.scenario, args.seconds, args.seed)
        calls, depths, setup = record(trial, args.frames)
        mesh_vertices = setup["vertices"]
        results, seconds = {}, {}
        for backend in args.backends:
            params = replace(setup["params"], backend=backend)
            refiner = Refiner(setup["vertices"], setup["faces"], setup["camera"], params, seed=setup["seed"])
            run_calls(refiner, calls[:3], depths)          # numba's first calls
            results[backend], seconds[backend] = run_calls(refiner, calls, depths)
        row = {"crest": crest.stem, "calls": len(calls), "ms_per_call": {b: 1e3 * s / len(calls) for b, s in seconds.items()}}
        steady = [c for c in calls if c[1] > 0]           # the first frame's seeding is a one-off
        for backend in args.backends:
            refiner = Refiner(setup["vertices"], setup["faces"], setup["camera"],
                              replace(setup["params"], backend=backend), seed=setup["seed"])
            run_calls(refiner, steady[:3], depths)
            row.setdefault("steady_ms_per_call", {})[backend] = 1e3 * min(
                run_calls(refiner, steady, depths)[1] for _ in range(args.repeats)) / len(steady)
        if args.split:
            refiner = Refiner(setup["vertices"], setup["faces"], setup["camera"], setup["params"], seed=setup["seed"])
            run_calls(refiner, steady[:3], depths)
            totals, undo = stage_timers()
            try:
                _, total = run_calls(refiner, steady, depths)
            finally:
                undo()
            split = {k: 1e3 * v / len(steady) for k, v in sorted(totals.items(), key=lambda kv: -kv[1])}
            split["other (python)"] = 1e3 * (total - sum(totals.values())) / len(steady)
            row["steady_split_ms_per_call"] = split
        for backend in args.backends:
            if backend == "numpy" or "numpy" not in results:
                continue
            diffs = [compare(a, b, mesh_vertices, refiner.center) for a, b in zip(results["numpy"], results[backend])]
            row[backend] = {k: max(d[k] for d in diffs) for k in diffs[0]}
        rows.append(row)
        print(json.dumps(row))
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
