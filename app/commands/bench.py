"""``osteonav bench``: every configuration on every trial, one table (see :mod:`app.bench.bench`)."""
from __future__ import annotations

from app.cli_types import finite_positive_float, positive_int, seed
from app.commands.outdir import add_overwrite_argument, prepare_dir, results_file

DEFAULT_JSON = "recordings/bench/bench.json"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "bench", help="compare tracker configurations and the ICP baseline on the same trials",
        description="Runs every configuration on every trial and prints frames/s, ADD, rotation error, VSD recall, "
                    "lost and ok fractions, dangerous frames (status ok while ADD > 5 mm) and jitter while the bone "
                    "is static. Without --trials, the standard scenarios are simulated (cached) for the default mesh "
                    "and each ../shared/data/pelvis crest mesh.")
    p.add_argument("--trials", nargs="+", metavar="DIR", help="trial directories with groundtruth.txt (default: simulate)")
    from app.bench.configs import builtin_configs

    p.add_argument("--configs", nargs="+", metavar="NAME", help=f"built-in names ({' '.join(builtin_configs())}: "
                   "configs/bench/) or YAML files (default: all built-ins)")
    p.add_argument("--json", metavar="OUT", help=f"results JSON (an existing one needs --overwrite; default: {DEFAULT_JSON}, "
                   "or a dated name beside it when that exists)")
    p.add_argument("--plots", metavar="DIR", help="write PNG plots (error over time per trial, rate per configuration; "
                   "default: none)")
    p.add_argument("--seconds", nargs="+", metavar="S|NAME=S", help="seconds per trial, S > 0 (simulated: duration; "
                   "recorded: the first S seconds; default: the scenario's, the whole trial); NAME=S for one scenario, e.g. --seconds 3 bone_moves=4.5")
    p.add_argument("--seeds", nargs="+", type=seed, metavar="N", help="simulation seeds, integers >= 0 (default: 0); several seeds: "
                   "trials of seed N are cached in <cache>/<mesh>/<scenario>_seedN, each simulated just before its "
                   "first run, and the JSON is rewritten as the runs finish (a partial matrix stays usable; after every run "
                   "while writing takes under 10 %% of the time)")
    p.add_argument("--jobs", type=positive_int, default=1,
                   help="parallel processes, >= 1 (default 1: frames/s are then not shared)")
    p.add_argument("--executor", choices=("local", "ray"), default="local", help="where the runs execute: local "
                   "(this machine, --jobs processes; default) or ray (one Ray task per run; needs pip install -e '.[ray]'; "
                   "see BENCHMARKS.md, Sweeps on a Ray cluster)")
    p.add_argument("--address", metavar="auto|HOST:PORT", help="with --executor ray: the cluster (auto: the one "
                   "`ray start` began on this machine; HOST:PORT: its head); default: that one if any, else a Ray instance "
                   "started for this bench")
    p.add_argument("--task-memory", type=finite_positive_float, metavar="GB", help="with --executor ray: memory reserved "
                   "per run (GiB > 0; default 1)")
    p.add_argument("--quick", action="store_true", help="a short run (minutes): 3 configurations (osteonav_default, A_cpu, "
                   "icp) on static_clear (1.5 s) and bone_moves (3.5 s, until its move ends), the default mesh only")
    from app.sim.scenarios import SCENARIOS, STANDARD

    p.add_argument("--scenarios", nargs="+", metavar="NAME", help=f"simulated scenarios (default: the standard four, "
                   f"{' '.join(STANDARD)}); all: {' '.join(SCENARIOS)}")
    p.add_argument("--meshes", nargs="+", metavar="MESH", help="meshes to simulate, in metres (default: the project's and "
                   "the pelvis crests)")
    from app.sim.sensors import SENSORS

    p.add_argument("--sensors", nargs="+", metavar="NAME[:KEY=VALUE,...]", help="depth sensor models to simulate each "
                   f"trial with (default: independent); any of {' '.join(SENSORS)}, e.g. --sensors independent stereo "
                   "stereo:window_px=9; another model than independent is cached in <scenario>[_seedN]@<model> and "
                   "tabled as <scenario>@<model>")
    p.add_argument("--cache", default="recordings/bench", help="where simulated trials are cached (default: %(default)s)")
    p.add_argument("--out", help="keep each run's estimate.txt / status.csv under OUT/<config>/<mesh>/<scenario> "
                   "(default: not kept)")
    p.add_argument("--no-vsd", action="store_true", help="skip VSD (saves two renderings per frame)")
    p.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    add_overwrite_argument(p, "the --json file and the --plots and --out folders' earlier contents")
    p.set_defaults(func=run)


def parse_seconds(items) -> float | dict | None:
    """``--seconds``: None, one duration for every trial, or (with NAME=S items) a duration per scenario
    name (every registered scenario: the plain S given, else its own length)."""
    from app.errors import ConfigError
    from app.sim.scenarios import SCENARIOS

    if not items:
        return None
    default, by_name = None, {}
    for item in items:
        name, _, value = item.rpartition("=")
        try:
            s = float(value)
        except ValueError:
            s = -1.0
        if not 0 < s < float("inf"):
            raise ConfigError("--seconds", f"expected S or NAME=S with a duration > 0 s, got '{item}'")
        if not name:
            default = s
        elif name not in SCENARIOS:
            raise ConfigError("--seconds", f"unknown scenario '{name}' in '{item}'; valid: {', '.join(SCENARIOS)}")
        else:
            by_name[name] = s
    if not by_name:
        return default
    return {name: by_name.get(name, default if default else scenario.seconds) for name, scenario in SCENARIOS.items()}


def run(args) -> int:
    from app.bench import bench
    from app.bench.executors import make_executor
    from app.errors import ConfigError

    args.seconds = parse_seconds(args.seconds)
    if args.sensors and args.trials:
        raise ConfigError("--sensors", "applies to simulated trials only: give --sensors or --trials, not both "
                          "(a recorded trial's model is in its trial.yaml)")
    bench.parse_sensors(args.sensors)   # an unknown model is refused before any output is touched
    executor = make_executor(args.executor, args.jobs, args.address, args.task_memory)
    try:
        return _run(args, executor)
    finally:
        executor.close()


def _run(args, executor) -> int:
    import logging
    import platform
    import time

    from app.bench import bench
    from app.bench.partial import PartialJson

    args.json = str(results_file(args.json, DEFAULT_JSON, args.overwrite))
    configs = bench.resolve_configs(args.configs or (bench.QUICK_CONFIGS if args.quick else None))
    if args.plots:
        prepare_dir(args.plots, args.overwrite, "--plots")
    if args.out:
        prepare_dir(args.out, args.overwrite, "--out")
    seconds = args.seconds or (bench.quick_seconds() if args.quick else None)
    if args.trials:
        trials = bench.recorded_trials(args.trials, seconds)
    else:
        from app.sim.simulator import DEFAULT_MESH

        scenarios = args.scenarios or (bench.QUICK_SCENARIOS if args.quick else None)
        meshes = args.meshes or ([DEFAULT_MESH] if args.quick else None)
        if not args.meshes and not args.quick and not bench.pelvis_crest_meshes():
            logging.getLogger(__name__).warning("no pelvis crest meshes at %s: the default mesh only", bench.PELVIS_DIR)
        trials = bench.standard_trials(args.cache, scenarios, seconds, meshes, jobs=args.jobs, seeds=args.seeds,
                                       lazy=bool(args.seeds) or executor.name == "ray", sensors=args.sensors)
    print(f"{len(configs)} configurations x {len(trials)} trials "
          f"({sum(t.max_frames or t.frames for t in trials)} frames each configuration), {executor.describe()}")
    for c in configs:
        print(f"  {c.name:<18} {c.describe()}")
    meta = {"machine": platform.platform(), "processor": platform.processor(), "jobs": args.jobs,
            "executor": executor.name, **({"cluster": executor.cluster()} if executor.name == "ray" else {}),
            "seconds": seconds, "seeds": args.seeds or [0], "configs": {c.name: c.describe() for c in configs},
            "planned_runs": len(configs) * len(trials)}
    t0 = time.perf_counter()
    stream = args.seeds or executor.name == "ray"   # the JSON as runs finish: a long sweep's partial matrix
    on_row = PartialJson(args.json, meta) if stream else None
    rows = bench.run_bench(configs, trials, out_dir=args.out, with_vsd=not args.no_vsd, on_row=on_row,
                           executor=executor)
    elapsed = time.perf_counter() - t0
    gl = next((r["gl"] for r in rows if r["tracker"] == "particle_filter" and r.get("gl")), None)
    print(f"\n{gl or ''}  ({platform.processor() or platform.machine()}, {elapsed:.0f} s)\n")
    print(bench.table(rows, markdown=args.markdown))
    if len(rows) > len({(r["config"], r["scenario"]) for r in rows}):
        print("\nper scenario over meshes and seeds: median / worst (worst run: mesh#seed)\n")
        print(bench.summary_table(rows, markdown=args.markdown))
    print("\nADD, rot: median / p95 of every frame (mm, deg); VSD rec: e_VSD < 0.3 (tau 20 mm); lost %: ADD > 10 mm; "
          "danger: status ok with ADD > 5 mm; jit: RMS frame-to-frame change while the bone is static; "
          "ADD cam: median ADD in the camera frame (the true camera when the trial records it); "
          "outline max: the projected outline's largest displacement on the bone on ok frames (mm)")
    bench.write_json(rows, args.json, {**meta, "gl": gl, "elapsed_s": elapsed})
    print(f"wrote {args.json}")
    if args.plots:
        written = bench.plot(rows, args.plots)
        print(f"wrote {len(written)} plots to {args.plots}")
    return 0
