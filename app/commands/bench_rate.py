"""``osteonav bench-rate``: the filter's frame rate and stage split (see :mod:`app.bench.rate`)."""
from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser("bench-rate", help="frames/s of the particle filter for particle counts and resolutions")
    p.add_argument("--particles", type=int, nargs="+", default=None, help="default: 200 700 1500")
    p.add_argument("--resolutions", nargs="+", default=None, help="WxH, default: 80x60 100x75 160x120")
    p.add_argument("--frames", type=int, default=30, help="frames timed per configuration")
    p.add_argument("--config", help="tracker YAML whose other settings to use")
    p.add_argument("--json", default="recordings/bench_rate.json", help="where to write the results")
    p.set_defaults(func=run)


def run(args) -> int:
    import json
    from pathlib import Path

    from app.bench import rate
    from app.config import load_config
    from app.errors import OsteonavError

    try:
        resolutions = [tuple(int(x) for x in r.lower().split("x")) for r in args.resolutions] if args.resolutions else rate.RESOLUTIONS
    except ValueError as exc:
        raise OsteonavError(f"--resolutions takes WxH values like 80x60 ({exc})") from exc
    particles = args.particles or rate.PARTICLES
    results = rate.run(particles, resolutions, args.frames, load_config(args.config),
                       progress=lambda r: print(f"  measured N={r['particles']} at {r['resolution'][0]}x{r['resolution'][1]}: {r['fps']:.1f} frames/s", flush=True))
    print(f"\n{results[0]['gl']}\n")
    print(rate.table(results))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(results, indent=2))
    print(f"\nwrote {args.json}")
    return 0
