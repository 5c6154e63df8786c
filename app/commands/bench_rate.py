"""``osteonav bench-rate``: the filter's frame rate and stage split per likelihood backend (see :mod:`app.bench.rate`)."""
from __future__ import annotations

from app.cli_types import positive_int, positive_seconds

from app.commands.outdir import add_overwrite_argument, results_file


def register(subparsers) -> None:
    p = subparsers.add_parser("bench-rate", help="frames/s of the particle filter per backend, particle count and resolution")
    p.add_argument("--backends", nargs="+", default=None, help="likelihood backends side by side: cpu gl (default: both)")
    p.add_argument("--particles", type=positive_int, nargs="+", default=None,
                   help="particle counts, integers >= 1 (default: 200 700 1500)")
    p.add_argument("--resolutions", nargs="+", default=None, help="filter image sizes WxH in pixels, each >= 8 (default: 80x60 100x75 160x120)")
    p.add_argument("--frames", type=positive_int, default=30, help="frames timed per configuration, >= 1 (default 30)")
    p.add_argument("--config", help="tracker YAML whose other settings to use (default: configs/default.yaml's values)")
    p.add_argument("--whole", action="store_true",
                   help="the whole default tracker per frame (filter, refinement, status, wide searches) on a CT-crest "
                        "trial, beside the Open3D ICP baseline on the same frames, as a ratio (--frames frames timed)")
    p.add_argument("--trial", help="with --whole: the trial directory to run on (default: a static_clear trial of the "
                                   "first ../shared/data/pelvis crest, simulated once into recordings/bench/)")
    p.add_argument("--stages", nargs="+", choices=("serial", "parallel"), default=None,
                   help="with --whole: the filter.stages modes to run the tracker in side by side, each on the same "
                        "frames, with their ratio and whether their outputs were identical (default: serial parallel)")
    p.add_argument("--seconds", type=positive_seconds, default=1.0,
                   help="with --whole and no --trial: the simulated trial's length in seconds, > 0 (default 1.0)")
    p.add_argument("--json", help="where to write the results (an existing file needs --overwrite; default: "
                   "recordings/bench_rate.json, with --whole recordings/bench_rate_whole.json, or a dated name "
                   "beside it when that exists)")
    add_overwrite_argument(p, "the --json file")
    p.set_defaults(func=run)


def _parse(args):
    """(backends, particles, resolutions) from the arguments; a clear error for a bad value."""
    from app.bench import rate
    from app.errors import OsteonavError

    try:
        resolutions = [tuple(int(x) for x in r.lower().split("x")) for r in args.resolutions] if args.resolutions else rate.RESOLUTIONS
        if any(len(r) != 2 or min(r) < 8 for r in resolutions):
            raise ValueError("two integers >= 8")
    except ValueError as exc:
        raise OsteonavError(f"--resolutions takes WxH values like 80x60 ({exc})") from exc
    backends = args.backends or rate.BACKENDS
    bad = [b for b in backends if b not in rate.BACKENDS]
    if bad:
        raise OsteonavError(f"--backends: {', '.join(bad)} unknown; valid: {' '.join(rate.BACKENDS)} "
                            "(auto is not measured: it picks one of them)")
    particles = args.particles or rate.PARTICLES
    return backends, particles, resolutions


def run(args) -> int:
    if args.whole:
        return run_whole(args)
    if args.stages is not None:
        from app.errors import OsteonavError

        raise OsteonavError("--stages is for --whole (the filter alone has no refinement to overlap): add --whole")
    if args.trial is not None:
        from app.errors import OsteonavError

        raise OsteonavError("--trial is for --whole (the filter alone runs on a synthetic sequence): add --whole")
    args.json = str(results_file(args.json, "recordings/bench_rate.json", args.overwrite))
    import json
    from pathlib import Path

    from app.bench import rate
    from app.config import load_config

    backends, particles, resolutions = _parse(args)
    results = rate.run(particles, resolutions, args.frames, load_config(args.config), backends=backends,
                       progress=lambda r: print(f"  measured {r['backend']} N={r['particles']} at {r['resolution']}: "
                                                f"{r['fps']:.1f} frames/s", flush=True))
    for description in dict.fromkeys(r["description"] for r in results):
        print(description)
    first = [r for r in results if r["first_call_s"] is not None]
    if first:
        print(f"cpu backend: first kernel calls {first[0]['first_call_s']:.2f} s (numba cache: {first[0]['numba_cache']}), "
              "not included in the rates")
    print()
    print(rate.table(results))
    Path(args.json).write_text(json.dumps(results, indent=2))
    print(f"\nwrote {args.json}")
    return 0


def run_whole(args) -> int:
    """``--whole``: the whole tracker beside the ICP baseline on one trial (:mod:`app.bench.whole`)."""
    import json
    from pathlib import Path

    from app.bench import whole
    from app.bench.trials import DEFAULT_CACHE
    from app.config import load_config
    from app.errors import OsteonavError

    if args.backends or args.particles or args.resolutions:
        raise OsteonavError("--whole runs the tracker as configured: set backend, particles and resolution in "
                            "--config, not --backends/--particles/--resolutions")
    config = load_config(args.config)
    args.json = str(results_file(args.json, "recordings/bench_rate_whole.json", args.overwrite))
    if args.trial is not None:
        trial = Path(args.trial)
        if not (trial / "trial.yaml").is_file():
            raise OsteonavError(f"--trial {trial}: not a trial directory (no trial.yaml); record or simulate one first")
    else:
        mesh = whole.default_crest()
        if mesh is None:
            raise OsteonavError("--whole: no CT crest mesh in ../shared/data/pelvis; give a trial with --trial DIR")
        print(f"trial: {whole.SCENARIO}, {args.seconds:g} s of {mesh.name} (simulated once into {DEFAULT_CACHE})", flush=True)
        trial = whole.simulated_trial(mesh, args.seconds, DEFAULT_CACHE)
    try:
        result = whole.measure(trial, config, frames=args.frames, stages=tuple(args.stages or whole.STAGE_MODES))
    except ValueError as exc:
        raise OsteonavError(f"--trial: {exc}") from exc
    print(f"tracker: {result['tracker']['description']}; {result['frames']} frames timed after "
          f"{result['warmup']} warm-up frames, one engine after the other on each frame (the stages modes' "
          "order swapped every frame)")
    print()
    print(whole.table(result))
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(f"\nwrote {args.json}")
    return 0
