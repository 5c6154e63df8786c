"""``osteonav bench-init``: the start from a point on the CT crests (issue 33; app/bench/start.py), or,
with ``--samplers``, the thesis's static samplers beside the detector on the same starts
(app/bench/samplers.py)."""
from __future__ import annotations

from app.cli_types import finite_float, int_at_least, positive_int, positive_seconds
from app.commands.outdir import add_overwrite_argument, results_file
from app.sim.scenarios import SCENARIOS

PELVIS_HELP = "../shared/data/pelvis"


def register(subparsers) -> None:
    p = subparsers.add_parser("bench-init", help="start from a point 2-5 mm off each CT crest with the defaults: "
                              "found within 1 mm, work and CPU to it, frames ok while > 2 mm off")
    p.add_argument("--crests", default="crest_*.ply", help=f"mesh glob in {PELVIS_HELP} (default: crest_*.ply, the 8 crests)")
    p.add_argument("--scenarios", nargs="+", default=["static_clear"], choices=sorted(SCENARIOS), metavar="SCENARIO",
                   help="simulated scenes (default: static_clear; static_other_side and static_far see the bone "
                   "from the other side and from 0.65 m, static_occluded has a hand and an instrument)")
    from app.sim.sensors import SENSORS

    p.add_argument("--sensor", default=None, choices=sorted(SENSORS), metavar="NAME",
                   help="the simulator's depth sensor model (independent, stereo, tof; default: the simulator's, "
                   "independent): a start on a stereo camera's correlated noise and shadows")
    p.add_argument("--views", type=positive_int, default=1,
                   help="simulator seeds per crest and scenario (bone tilt, tissue), >= 1 (default 1)")
    p.add_argument("--first-view", type=int_at_least(0), default=0,
                   help="the first simulator seed: views FIRST-VIEW .. FIRST-VIEW + VIEWS - 1, >= 0 (default 0; "
                   "views never used to choose the defaults, e.g. --first-view 6)")
    p.add_argument("--seeds", type=positive_int, default=1, help="point draws per view, >= 1 (default 1)")
    p.add_argument("--first-seed", type=int_at_least(0), default=0,
                   help="the first point draw: draws FIRST-SEED .. FIRST-SEED + SEEDS - 1, >= 0 (default 0; "
                   "another subset of the same starts)")
    p.add_argument("--seconds", type=positive_seconds, default=2.5, help="trial length in seconds, > 0 (default 2.5)")
    p.add_argument("--off-mm", type=finite_float, nargs=2, default=(2.0, 5.0), metavar=("LOW", "HIGH"),
                   help="the point's distance off the crest's top, 0 <= LOW <= HIGH mm (default 2 5)")
    p.add_argument("--no-point", action="store_true",
                   help="give no point either: the detector searches the whole image (experimental)")
    p.add_argument("--samplers", action="store_true",
                   help="compare MH, multiple-try Metropolis, the SMC and the detector on each start's first frame "
                   "instead of replaying (success within 2 mm / 2 deg, evaluations to success)")
    p.add_argument("--budget", type=int_at_least(100), default=30000,
                   help="likelihood evaluations per sampler with --samplers, >= 100 (default 30000)")
    p.add_argument("--work", default="recordings/bench_init",
                   help="folder the simulated trials are cached in (default: recordings/bench_init)")
    p.add_argument("--json", help="where to write the results (an existing file needs --overwrite; default: "
                   "recordings/bench_init.json, or a dated name beside it when that exists); the plot of success "
                   "against budget goes beside it, the same name with .png")
    add_overwrite_argument(p, "the --json file and its plot")
    p.set_defaults(func=run)


def run(args) -> int:
    import json
    import time
    from pathlib import Path

    from app.bench import budget
    from app.commands.outdir import prepare_file
    from app.errors import OsteonavError

    low, high = args.off_mm
    if not 0 <= low <= high:
        raise OsteonavError(f"--off-mm takes LOW HIGH with 0 <= LOW <= HIGH (mm), got {low:g} {high:g}")
    if args.samplers and args.no_point:
        raise OsteonavError("--samplers compares samplers from a point: drop --no-point")
    pelvis = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "pelvis"
    meshes = sorted(pelvis.glob(args.crests))
    if not meshes:
        raise OsteonavError(f"--crests {args.crests}: no mesh matches in {pelvis}")
    default = "recordings/bench_init_samplers.json" if args.samplers else "recordings/bench_init.json"
    args.json = str(results_file(args.json, default, args.overwrite))
    png = prepare_file(Path(args.json).with_suffix(".png"), args.overwrite, "--json's plot")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = []
    for mesh in meshes:
        for scenario in args.scenarios:
            for view in range(args.first_view, args.first_view + args.views):
                for seed in range(args.first_seed, args.first_seed + args.seeds):
                    rows.extend(_one(args, work, mesh, scenario, view, seed, first=not rows))
    if args.samplers:
        report = _samplers_report(rows)
    else:
        report = _start_report(rows, args.no_point)
    report["args"] = {k: str(v) for k, v in vars(args).items() if k != "func"}
    Path(args.json).write_text(json.dumps(report, indent=2))
    budget.plot(report["budget"], png, _plot_title(args, rows))
    print(f"\n{len(rows)} runs in {time.perf_counter() - t0:.0f} s; wrote {args.json} and {png}")
    if not args.samplers and report["missed"]:
        print(f"{report['missed']} of {len(rows)} starts missed (not within 1 mm, or ok while > 2 mm off): exit 1")
        return 1
    return 0


def _one(args, work, mesh, scenario: str, view: int, seed: int, first: bool) -> list[dict]:
    """One start: its trial (simulated, cached), then the replay's measures or every sampler's run."""
    from dataclasses import asdict

    from app.bench import start

    sensor = f"_{args.sensor}" if args.sensor else ""
    trial = work / f"{mesh.stem}_{scenario}{sensor}_v{view}_s{seed}{'_nopoint' if args.no_point else ''}"
    off = start.simulate_point_trial(trial, mesh, view, seed, args.seconds, (1e-3 * args.off_mm[0], 1e-3 * args.off_mm[1]),
                                     not args.no_point, scenario, args.sensor)
    key = {"crest": mesh.stem, "scenario": scenario, "sensor": args.sensor or "independent", "view": view,
           "seed": seed, "off_mm": 1e3 * off}
    if args.samplers:
        runs = [{**key, **asdict(r)} for r in _compare(trial, args.budget, seed)]
        for r in runs:
            print(f"{mesh.stem} {scenario} v{view} s{seed} {r['sampler']}: success {r['success']} ({r['evaluations_to_success']} "
                  f"evaluations), ADD {r['add_mm']:.1f} mm, {r['rotation_deg']:.1f} deg, {r['cpu_s']:.2f} s CPU", flush=True)
        return runs
    if first:
        start.run_start(trial, max_frames=3)                   # warm-up: numba compiles, not counted
    row = {**key, **start.run_start(trial)}
    add = row["add_found_mm"]
    print(f"{mesh.stem} {scenario} v{view} s{seed}: off {row['off_mm']:.1f} mm, found {row['found']} "
          f"(ADD {float('nan') if add is None else add:.2f} mm) after {row['attempts']} attempt(s), {row['evaluations']} "
          f"evaluations, {row['refinements']} refinements, {row['cpu_s']:.2f} s CPU; ok > 2 mm off: "
          f"{row['ok_off_2mm']}; first ok {row['first_ok_s']} s", flush=True)
    return [row]


def _compare(trial, budget: int, seed: int):
    from app.bench.samplers import compare
    from app.config import load_config
    from app.depth_image import downsample_nearest
    from app.pipeline.tracker import DepthTracker
    from app.trial.reader import open_trial

    reader = open_trial(trial)
    config = load_config(None)
    tracker = DepthTracker(config, reader.load_mesh(), reader.meta.camera)
    try:
        T_base_camera, _ = reader.camera_poses()
        depth = reader.read_depth(0)
        return compare(tracker, downsample_nearest(depth, *config.resolution), depth, T_base_camera[0],
                       reader.meta.point_prior, reader.groundtruth[0], budget, seed)
    finally:
        tracker.release()


def _start_report(rows: list[dict], no_point: bool) -> dict:
    from app.bench import budget, start

    crests = start.per_crest(rows)
    print()
    print(start.table(crests))
    worst = start.worst(crests)
    missed = sum(1 for r in rows if not r["found_1mm"] or r["ok_off_2mm"])
    print(f"\nworst crest: {worst['crest']} ({worst['found_1mm']}/{worst['runs']} within 1 mm, CPU max "
          f"{worst['cpu_s_max']} s); frames ok while > 2 mm off: {sum(c['ok_off_2mm'] for c in crests)}"
          f"{' (no point: the whole image)' if no_point else ''}")
    method = "detector, whole image" if no_point else "detector, from the point"
    solved = [{"method": method, "evaluations": r["evaluations"],
               "evaluations_to_success": r["evaluations"] if r["found_1mm"] else None} for r in rows]
    return {"runs": rows, "crests": crests, "worst": worst, "missed": missed,
            "budget": budget.curve(solved, "method")}


def _samplers_report(rows: list[dict]) -> dict:
    from app.bench import budget
    from app.bench.samplers import sampler_table

    table, per_sampler = sampler_table(rows)
    print()
    print(table)
    return {"runs": rows, "samplers": per_sampler, "budget": budget.curve(rows, "sampler")}


def _plot_title(args, rows: list[dict]) -> str:
    """The plot's title: what was run, and what success means there."""
    starts = len({(r["crest"], r["scenario"], r["view"], r["seed"]) for r in rows})
    what = ("success within 2 mm / 2 deg on the start's first frame" if args.samplers else
            "the replay's start: the frame found on within 1 mm ADD")
    return f"osteonav bench-init: {starts} starts ({', '.join(args.scenarios)}); {what}"
