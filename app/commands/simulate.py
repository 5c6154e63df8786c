"""``osteonav simulate``: write a simulated recorded trial (see :mod:`app.sim.simulator`)."""
from __future__ import annotations

from app.cli_types import positive_seconds, seed
from app.commands.outdir import add_overwrite_argument, prepare_dir


def register(subparsers) -> None:
    from app.sim.scenarios import DEFAULT_SCENARIO, SCENARIOS
    from app.sim.sensors import DEFAULT_SENSOR, SENSORS

    p = subparsers.add_parser(
        "simulate", help="simulate a trial (robot, depth camera, bone, occluders) in the recorded-trial format",
        description="Scenarios: " + "; ".join(f"{name}: {s.description}" for name, s in SCENARIOS.items()),
    )
    p.add_argument("--out", required=True, help="trial directory to write")
    p.add_argument("--mesh", help="bone mesh in metres (default: meshes/iliac_crest.ply)")
    p.add_argument("--scenario", default=DEFAULT_SCENARIO, choices=list(SCENARIOS), metavar="NAME",
                   help=f"one of: {', '.join(SCENARIOS)} (default {DEFAULT_SCENARIO})")
    p.add_argument("--seconds", type=positive_seconds, help="duration, s > 0 (default: the scenario's)")
    p.add_argument("--seed", type=seed, default=0, help="simulation seed, an integer >= 0 (default 0)")
    add_overwrite_argument(p, "the trial in --out")
    p.add_argument("--streams", default="depth", help="images per frame: depth (default) or e.g. depth,ir,color "
                   "(infrared and colour: trial format 1.1)")
    p.add_argument("--sensor", default=DEFAULT_SENSOR, metavar="NAME[:KEY=VALUE,...]",
                   help=f"depth sensor model, one of: {', '.join(SENSORS)} (default %(default)s); parameters as e.g. "
                   "stereo:window_px=9,sigma_d_px=0.1 (app/sim/sensors/); written into trial.yaml's 'sensor'")
    p.add_argument("--emitter", choices=("on", "off"), default="on", help="IR dot projector in the ir images (default on)")
    p.add_argument("--pointer", action="store_true", help="draw a pointer tool held on the crest (its tip 3 mm off the "
                   "crest's top) into the ir images, as a session's bone.pointer reads it (app/sim/pointer.py; needs "
                   "--streams with ir)")
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from app.errors import OsteonavError
    from app.sim.images import parse_streams
    from app.sim.pointer import SimulatedPointer
    from app.sim.sensors import parse_sensor
    from app.sim.simulator import simulate

    try:
        streams = ",".join(parse_streams(args.streams))
    except ValueError as exc:
        raise OsteonavError(f"--streams: {exc}") from None
    try:
        sensor = parse_sensor(args.sensor)
    except ValueError as exc:
        raise OsteonavError(f"--sensor: {exc}") from None
    if args.pointer and "ir" not in streams.split(","):
        raise OsteonavError(f"--pointer: the pointer's marker is drawn into the infrared images: add ir to --streams "
                            f"(e.g. --streams depth,ir), got {streams!r}")
    if args.mesh:
        from app.mesh import load_mesh

        load_mesh(args.mesh)   # unreadable or not in metres: refused before --out is touched
    prepare_dir(args.out, args.overwrite, inputs=[args.mesh])
    bar = tqdm(desc=f"simulate {args.scenario}", unit="frame")

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    summary = simulate(args.out, args.mesh, args.scenario, args.seconds, args.seed, overwrite=True, progress=progress,
                       streams=streams, emitter=args.emitter == "on", sensor=sensor,
                       pointer=SimulatedPointer() if args.pointer else None)
    bar.close()
    print(f"wrote {summary.frames} frames ({summary.seconds:.1f} s, scenario {summary.scenario}, sensor {sensor.name}, "
          f"occlusion mean {100 * summary.mean_occlusion:.0f} % max {100 * summary.max_occlusion:.0f} %) to {summary.out}")
    return 0
