"""``osteonav simulate``: write a simulated recorded trial (see :mod:`app.sim.simulator`)."""
from __future__ import annotations

from app.commands.outdir import add_overwrite_argument, prepare_dir


def register(subparsers) -> None:
    from app.sim.scenarios import DEFAULT_SCENARIO, SCENARIOS

    p = subparsers.add_parser(
        "simulate", help="simulate a trial (robot, depth camera, bone, occluders) in the recorded-trial format",
        description="Scenarios: " + "; ".join(f"{name}: {s.description}" for name, s in SCENARIOS.items()),
    )
    p.add_argument("--out", required=True, help="trial directory to write")
    p.add_argument("--mesh", help="bone mesh in metres (default: meshes/iliac_crest.ply)")
    p.add_argument("--scenario", default=DEFAULT_SCENARIO, help=f"one of: {', '.join(SCENARIOS)}")
    p.add_argument("--seconds", type=float, help="duration (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0)
    add_overwrite_argument(p, "the trial in --out")
    p.add_argument("--streams", default="depth", help="images per frame: depth (default) or e.g. depth,ir,color "
                   "(infrared and colour: trial format 1.1)")
    p.add_argument("--emitter", choices=("on", "off"), default="on", help="IR dot projector in the ir images (default on)")
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from app.errors import OsteonavError
    from app.sim.scenarios import SCENARIOS
    from app.sim.images import parse_streams
    from app.sim.simulator import simulate

    if args.scenario not in SCENARIOS:
        raise OsteonavError(f"unknown scenario '{args.scenario}'; valid: {', '.join(SCENARIOS)}")
    try:
        streams = ",".join(parse_streams(args.streams))
    except ValueError as exc:
        raise OsteonavError(f"--streams: {exc}") from None
    if args.mesh:
        from app.mesh import load_mesh

        load_mesh(args.mesh)   # unreadable or not in metres: refused before --out is touched
    prepare_dir(args.out, args.overwrite, inputs=[args.mesh])
    bar = tqdm(desc=f"simulate {args.scenario}", unit="frame")

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    summary = simulate(args.out, args.mesh, args.scenario, args.seconds, args.seed, overwrite=True, progress=progress,
                       streams=streams, emitter=args.emitter == "on")
    bar.close()
    print(f"wrote {summary.frames} frames ({summary.seconds:.1f} s, scenario {summary.scenario}, "
          f"occlusion mean {100 * summary.mean_occlusion:.0f} % max {100 * summary.max_occlusion:.0f} %) to {summary.out}")
    return 0
