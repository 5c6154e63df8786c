"""``osteonav bench-rate``: the filter's frame rate and stage split per likelihood backend (see :mod:`app.bench.rate`)."""
from __future__ import annotations

from app.cli_types import positive_int

from app.commands.outdir import add_overwrite_argument, results_file


def register(subparsers) -> None:
    p = subparsers.add_parser("bench-rate", help="frames/s of the particle filter per backend, particle count and resolution")
    p.add_argument("--backends", nargs="+", default=None, help="likelihood backends side by side: cpu gl (default: both)")
    p.add_argument("--particles", type=positive_int, nargs="+", default=None,
                   help="particle counts, integers >= 1 (default: 200 700 1500)")
    p.add_argument("--resolutions", nargs="+", default=None, help="filter image sizes WxH in pixels, each >= 8 (default: 80x60 100x75 160x120)")
    p.add_argument("--frames", type=positive_int, default=30, help="frames timed per configuration, >= 1 (default 30)")
    p.add_argument("--config", help="tracker YAML whose other settings to use (default: configs/default.yaml's values)")
    p.add_argument("--json", help="where to write the results (an existing file needs --overwrite; default: "
                   "recordings/bench_rate.json, or a dated name beside it when that exists)")
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
