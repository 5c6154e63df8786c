"""``osteonav calibrate``: camera intrinsics (ChArUco), eye-in-hand hand-eye and projector calibration.

Subcommands::

    osteonav calibrate simulate  --out DIR [--count 20] [--noise] [--seed N] [--corrupt 3:blank]
    osteonav calibrate intrinsics --images DIR [--board SPEC] [--out camera.yaml]
    osteonav calibrate hand-eye  --captures DIR [--camera camera.yaml] [--method auto] [--out FILE]
                                 [--rrd FILE]
    osteonav calibrate capture   --config session.yaml --out DIR [--count 15] [--image ir|color] [--manual]
                                 [--rrd FILE | --no-viewer]     (live: RealSense + UR; or camera: simulated)
    osteonav calibrate projector --captures DIR [--camera camera.yaml] [--out FILE] [--simulate N]
                                 [--live --config session.yaml --poses 8 --screen K]

Try it without hardware::

    osteonav calibrate simulate --out /tmp/cal --noise
    osteonav calibrate intrinsics --images /tmp/cal/images --out /tmp/cal/camera_fit.yaml
    osteonav calibrate hand-eye --captures /tmp/cal --rrd /tmp/cal/hand_eye.rrd
    osteonav calibrate projector --simulate 5 --captures /tmp/projcal

Every step refuses to replace an earlier output (a non-empty capture folder, an existing YAML or
.rrd) unless given --overwrite, which first removes that step's own earlier outputs.

Formats: the board SPEC in ``calibration.board``, capture folders in ``calibration.captures``,
the camera YAML in ``calibration.intrinsics``, the hand-eye YAML in ``calibration.handeye``.
"""
from __future__ import annotations

import argparse
import logging
import re
import sys
from pathlib import Path

from app.cli_types import deprecated_alias, int_at_least, non_negative_int, positive_int, seed
from app.commands.outdir import add_overwrite_argument, prepare_dir, prepare_file
from app.outputs import wrote

log = logging.getLogger(__name__)

DEFAULT_BOARD = "charuco:7x5:0.04:0.03:DICT_5X5_100"   # = calibration.board.DEFAULT_BOARD_SPEC


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate", help="camera intrinsics, hand-eye and projector calibration (ChArUco board)",
        description=_plain(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="calibrate_command", metavar="STEP")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    _add_intrinsics(sub)
    _add_hand_eye(sub)
    _add_capture(sub)
    _add_simulate(sub)
    _add_projector(sub)


def _add_intrinsics(sub) -> None:
    """``calibrate intrinsics``: K and distortion from ChArUco images."""
    s = sub.add_parser("intrinsics", help="K and distortion from ChArUco images")
    s.add_argument("--images", required=True, type=Path, help="folder of board images")
    s.add_argument("--board", default=DEFAULT_BOARD,
                   help=f"board SPEC 'charuco:SXxSY:SQUARE_M:MARKER_M:DICT' or a YAML file "
                        f"(default {DEFAULT_BOARD})")
    s.add_argument("--out", type=Path, help="camera YAML to write (default IMAGES/camera.yaml)")
    k3 = s.add_mutually_exclusive_group()
    k3.add_argument("--fix-k3", action="store_true",
                    help="keep the distortion's k3 at 0 (default: fixed unless freeing it lowers the RMS by 5 %%)")
    k3.add_argument("--free-k3", action="store_true", help="always estimate k3")
    add_overwrite_argument(s, "an existing --out file")
    s.set_defaults(func=run_intrinsics)


def _add_hand_eye(sub) -> None:
    """``calibrate hand-eye``: T_flange_camera from captures, every method compared."""
    s = sub.add_parser("hand-eye", help="T_flange_camera from captures (AX = XB), all methods compared")
    s.add_argument("--captures", required=True, type=Path, help="capture folder")
    s.add_argument("--camera", type=Path,
                   help="camera YAML with the intrinsics (default CAPTURES/camera.yaml)")
    s.add_argument("--board", help="board SPEC (default: capture.yaml's, else the default board)")
    s.add_argument("--robot", help="robot model, e.g. ur5e (default: capture.yaml's robot block)")
    s.add_argument("--method", default="auto",
                   choices=["auto", "tsai", "park", "horaud", "andreff", "daniilidis"],
                   help="method whose result is written (default auto: the lowest reprojection error)")
    s.add_argument("--out", type=Path, help="hand-eye YAML to write (default CAPTURES/hand_eye.yaml)")
    s.add_argument("--rrd", type=Path, metavar="FILE.rrd",
                   help="also log captures, frusta and board to this rerun file (default: none)")
    add_overwrite_argument(s, "existing --out / --rrd files")
    s.set_defaults(func=run_hand_eye)


def _add_capture(sub) -> None:
    """``calibrate capture``: captures taken live from a session's camera and robot."""
    s = sub.add_parser("capture", help="collect captures live from a session's camera and robot",
                       description="A session with camera and robot plugins (e.g. realsense with streams "
                                   "depth,ir + ur): captures when the robot rested 0.5 s with the board seen, "
                                   "or on Enter (calibration/live.py). 'camera: simulated' uses the "
                                   "calibration simulator instead.")
    s.add_argument("--config", required=True, type=Path, help="session YAML (camera and robot plugins)")
    s.add_argument("--out", required=True, type=Path, help="capture folder to create")
    s.add_argument("--count", type=positive_int, default=15, help="captures to take, >= 1 (default 15)")
    s.add_argument("--seed", type=seed, default=0, help="seed of the simulated source, an integer >= 0 (default 0)")
    s.add_argument("--image", choices=("ir", "color"), default="ir",
                   help="the camera stream the board is detected in (default ir: the depth camera's own K)")
    s.add_argument("--manual", action="store_true", help="capture only on Enter (no automatic capture at rest)")
    s.add_argument("--board", default=DEFAULT_BOARD, help=f"board SPEC (default {DEFAULT_BOARD})")
    s.add_argument("--rrd", type=Path, metavar="FILE.rrd",
                   help="log the live detection to this rerun file (default: spawn the viewer)")
    s.add_argument("--no-viewer", action="store_true", help="no rerun logging")
    add_overwrite_argument(s, "the captures in --out")
    s.set_defaults(func=run_capture)


def _add_simulate(sub) -> None:
    """``calibrate simulate``: a folder of simulated captures."""
    s = sub.add_parser("simulate", help="write a folder of simulated captures (no hardware needed)")
    s.add_argument("--out", required=True, type=Path, help="capture folder to create")
    s.add_argument("--count", type=int_at_least(3, "a capture count"), default=20,
                   help="number of captures, >= 3 (default 20)")
    deprecated_alias(s, "--captures", "--count")   # --captures is a folder in hand-eye and projector
    s.add_argument("--noise", action="store_true", help="blur, image noise and encoder noise")
    s.add_argument("--seed", type=seed, default=0, help="simulation seed, an integer >= 0 (default 0)")
    s.add_argument("--corrupt", default="",
                   help="captures to spoil, e.g. '3:blank,7:missing' (blank, noise, missing, garbage; default: none)")
    add_overwrite_argument(s, "the captures in --out")
    s.set_defaults(func=run_simulate)


def _add_projector(sub) -> None:
    """``calibrate projector``: K_p and T_camera_projector from Gray-code captures."""
    s = sub.add_parser("projector", help="K_p and T_camera_projector from Gray-code captures of the board",
                       description="Gray-code structured light on a ChArUco board (calibration/projector.py). "
                                   "Try: osteonav calibrate projector --simulate 5 --captures /tmp/projcal")
    s.add_argument("--captures", required=True, type=Path, help="projector capture folder (pose_*/pattern_*.png)")
    s.add_argument("--camera", type=Path, help="camera intrinsics YAML (default CAPTURES/camera.yaml)")
    s.add_argument("--board", help="board SPEC (default: projector_capture.yaml's)")
    s.add_argument("--out", type=Path, help="projector YAML to write (default CAPTURES/projector.yaml)")
    s.add_argument("--distortion", choices=("none", "k1k2"), default="none",
                   help="projector lens distortion to estimate (default none: with few poses k1/k2 trade off "
                        "against the focal length and T_camera_projector; see calibration/projector.py)")
    s.add_argument("--simulate", type=non_negative_int, default=0, metavar="N",
                   help="first write N >= 3 simulated board poses into CAPTURES (no hardware needed; default 0: none)")
    s.add_argument("--noise", action="store_true", help="with --simulate: image noise and blur")
    s.add_argument("--seed", type=seed, default=0, help="with --simulate: simulation seed, an integer >= 0 (default 0)")
    s.add_argument("--live", action="store_true", help="first capture live: the Gray-code sequence in the projector "
                   "window, the session camera's images (--config), Enter per board pose")
    s.add_argument("--config", type=Path, help="with --live: session YAML naming the camera plugin (required with --live)")
    s.add_argument("--poses", type=positive_int, default=8, help="with --live: board poses to capture, >= 1 (default 8)")
    s.add_argument("--screen", type=int, default=-1, help="with --live: the projector's screen (default the last)")
    s.add_argument("--image", choices=("ir", "color"), default="ir", help="with --live: camera stream (default ir)")
    add_overwrite_argument(s, "the poses in --captures (with --simulate) and an existing --out file")
    s.set_defaults(func=run_projector)


def _plain(doc: str) -> str:
    """A docstring as --help text: no reST markup (``code``, ``::``)."""
    return re.sub(r"::\n", ":\n", doc.replace("``", ""))


def run_projector(args) -> int:
    from app.errors import ConfigError
    from calibration.projector import MIN_VIEWS, run_command

    if args.simulate:
        if args.simulate < MIN_VIEWS:
            raise ConfigError("--simulate", f"at least {MIN_VIEWS} board poses needed, got {args.simulate}")
        prepare_dir(args.captures, args.overwrite, "--captures")
    if args.live:
        from calibration.projector_live import run_live_projector_capture

        if args.config is None:
            raise ConfigError("--config", "--live needs the session file naming the camera (e.g. realsense, streams depth,ir)")
        if args.simulate:
            raise ConfigError("--live", "give --live or --simulate, not both")
        prepare_dir(args.captures, args.overwrite, "--captures")
        run_live_projector_capture(args.config, args.captures, args.poses, args.screen, args.image, args.board)
    prepare_file(args.out or args.captures / "projector.yaml", args.overwrite)
    return run_command(args)


def _board_arg(text: str):
    from app.errors import ConfigError
    from calibration.board import parse_board_spec

    try:
        return parse_board_spec(text)
    except (ValueError, OSError) as exc:
        raise ConfigError("--board", str(exc)) from None


def run_intrinsics(args) -> int:
    from app.errors import ConfigError
    from calibration.intrinsics import calibrate_intrinsics_folder, result_info, write_camera_yaml

    spec = _board_arg(args.board)
    if not args.images.is_dir():
        raise ConfigError("--images", f"image folder {args.images} does not exist")
    out = prepare_file(args.out or args.images / "camera.yaml", args.overwrite)
    try:
        result = calibrate_intrinsics_folder(args.images, spec,
                                             fix_k3=True if args.fix_k3 else False if args.free_k3 else None)
    except ValueError as exc:
        raise ConfigError("--images", str(exc)) from None
    write_camera_yaml(out, result.camera, result_info(result))
    K = result.camera.K
    print(f"board {result.board}: {len(result.per_image)} images used, {len(result.skipped)} skipped")
    for s in result.skipped:
        print(f"  skipped {s['image']}: {s['reason']}")
    for r in result.per_image:
        print(f"  {r['image']}: {r['error_px']:.3f} px RMS ({r['corners']} corners)")
    print(f"RMS reprojection error {result.rms_px:.3f} px (k3 {result.k3})")
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    print(f"fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f}  "
          f"dist {[round(float(v), 5) for v in result.camera.dist]}")
    print(f"wrote {out}")
    return 0


def run_hand_eye(args) -> int:
    import numpy as np

    from app.errors import ConfigError
    from calibration import handeye
    from calibration.intrinsics import read_camera_yaml

    camera_path = args.camera or args.captures / "camera.yaml"
    if not camera_path.is_file():
        raise ConfigError("--camera", f"no intrinsics: {camera_path} does not exist; run "
                          f"`osteonav calibrate intrinsics` first or pass --camera FILE")
    camera = read_camera_yaml(camera_path)
    out = args.out or args.captures / "hand_eye.yaml"
    prepare_file(out, args.overwrite)
    if args.rrd is not None:
        prepare_file(args.rrd, args.overwrite, "--rrd")
    board = _board_arg(args.board).to_string() if args.board else None
    robot = {"model": args.robot} if args.robot else None
    obs, skipped, robot = handeye.observations_from_folder(
        args.captures, camera.K, camera.dist, board=board, robot=robot, keep_images=args.rrd is not None)
    try:
        result = handeye.calibrate_hand_eye(obs, camera.K, camera.dist, args.method)
    except ValueError as exc:
        raise ConfigError("--captures", f"{args.captures}: {exc}") from None
    result.skipped = skipped
    data = handeye.result_to_dict(result, robot=robot, camera=camera.to_dict())
    handeye.write_hand_eye_yaml(out, data)

    print(f"{len(obs)} captures used, {len(skipped)} skipped")
    for s in skipped:
        print(f"  skipped capture {s['capture']}: {s['reason']}")
    print(f"{'method':<11} {'rot deg':>8} {'trans mm':>9} {'reproj px':>10} {'vs chosen mm':>13}")
    for m, mr in result.methods.items():
        summ, d = mr.summary(), data["methods"][m]
        rp = summ["reprojection_px_rms"]
        print(f"{m:<11} {summ['rotation_deg_rms']:8.3f} {summ['translation_mm_rms']:9.3f} "
              f"{(f'{rp:10.3f}' if rp is not None else '         -')} "
              f"{d['differs_from_chosen_mm']:13.3f}{'  <- chosen' if m == result.chosen.method else ''}")
    c = result.chosen
    print("per capture (chosen method): capture, rotation deg, translation mm, reprojection px")
    for k, o in enumerate(obs):
        print(f"  {o.capture:6d} {c.rotation_deg[k]:8.3f} {c.translation_mm[k]:9.3f} "
              f"{c.reprojection_px[k]:10.3f}")
    if result.robot_world:
        rw = result.robot_world
        dt = 1000 * np.linalg.norm(rw["hand_eye"][:3, 3] - c.T_flange_camera[:3, 3])
        print(f"robot-world ({rw['method']}): board at {np.round(rw['T_base_board'][:3, 3], 4)} m in "
              f"the base; its hand-eye differs by {dt:.3f} mm")
    for w in result.warnings:
        print(f"WARNING: {w}")
    print("hand_eye (T_flange_camera):")
    print(np.array2string(c.T_flange_camera, precision=5, suppress_small=True))
    print(f"wrote {out}")
    if args.rrd is not None:
        from calibration.rerun_log import log_hand_eye

        log_hand_eye(args.rrd, result, camera.K, camera.width, camera.height,
                     board or _folder_board(args.captures))
        print(f"wrote {args.rrd}")
    return 0


def _folder_board(root: Path) -> str:
    from calibration.board import DEFAULT_BOARD_SPEC
    from calibration.captures import read_captures

    return read_captures(root).board or DEFAULT_BOARD_SPEC


def _source_kind(config: dict, key: str, source: str) -> str:
    from app.errors import ConfigError

    value = config.get(key, "simulated" if key == "robot" else None)
    if isinstance(value, dict):
        value = value.get("plugin", value.get("type"))
    if value is None:
        raise ConfigError(key, "missing; calibration capture needs a camera (e.g. 'camera: simulated')",
                          source)
    if value != "simulated":
        raise ConfigError(key, f"source {value!r} is not supported by `calibrate capture` yet; "
                          f"only 'simulated' (live camera and robot plugins are not wired in)", source)
    return value


def _session_rig(path: Path, config: dict):
    """The session's rig as a calibration SimulationConfig, and where it came from.

    calibration.hand_eye and robot.model from the session file when given; otherwise the simulated
    sources' own: the trial in their ``trial_dir`` when it exists, else the trial simulator's
    constants (app.sim: T_FLANGE_CAMERA, the D415 640x480 intrinsics, a UR5e), which is the trial
    those sources would simulate. So the captures solve for the hand-eye the session's trial uses.
    """
    import numpy as np

    from app.session.config import _matrix4
    from app.sim import world
    from app.sim.simulator import D415_640x480
    from calibration.simulator import SimulationConfig

    camera, robot, T_flange_camera, source = D415_640x480, {"model": "ur5e"}, world.T_FLANGE_CAMERA, "app.sim"
    params = (config.get("camera") or {}).get("params", {}) if isinstance(config.get("camera"), dict) else {}
    trial_dir = params.get("trial_dir")
    found = [d for d in (Path(str(trial_dir)), path.parent / str(trial_dir)) if (d / "trial.yaml").is_file()]
    if trial_dir and found:   # the working directory's (as the plugin resolves it today), else the file's
        from app.trial.meta import load_meta

        meta = load_meta(found[0] / "trial.yaml")
        camera, robot, T_flange_camera = meta.camera, dict(meta.robot), meta.T_flange_camera
        source = str(found[0])
    calib = config.get("calibration") if isinstance(config.get("calibration"), dict) else {}
    if calib.get("hand_eye") is not None:
        T_flange_camera, source = _matrix4("calibration.hand_eye", calib["hand_eye"], path.parent, str(path)), str(path)
    robot_block = config.get("robot") if isinstance(config.get("robot"), dict) else {}
    if "model" in robot_block or "dh" in robot_block:
        robot = {k: robot_block[k] for k in ("model", "dh") if k in robot_block}
    sim = SimulationConfig(width=camera.width, height=camera.height, K=np.asarray(camera.K, float), robot=robot,
                           T_flange_camera=np.asarray(T_flange_camera, float))
    return sim, source


def run_capture(args) -> int:
    import numpy as np
    import yaml

    from app.errors import ConfigError
    from calibration.board import parse_board_spec
    from calibration.captures import CaptureWriter, collect_captures
    from calibration.intrinsics import CameraIntrinsics, write_camera_yaml
    from calibration.simulator import SimulatedCaptureRig, make_scene, plan_captures

    if not args.config.is_file():
        raise ConfigError("--config", f"{args.config} does not exist")
    try:
        config = yaml.safe_load(args.config.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError("(file)", f"not valid YAML: {str(exc).splitlines()[0]}", str(args.config)) from None
    if not isinstance(config, dict):
        raise ConfigError("(top level)", "expected a mapping", str(args.config))
    camera = config.get("camera")
    if (camera.get("plugin", camera.get("type")) if isinstance(camera, dict) else camera) not in (None, "simulated"):
        from calibration.live_session import run_command

        return run_command(args)   # a live session: its camera and robot plugins
    _source_kind(config, "camera", str(args.config))
    _source_kind(config, "robot", str(args.config))
    sim, rig_source = _session_rig(args.config, config)
    prepare_dir(args.out, args.overwrite, inputs=[args.config])
    rng = np.random.default_rng(args.seed)
    scene = make_scene(sim)
    rig = SimulatedCaptureRig(scene, plan_captures(scene, args.count, rng), rng)
    with CaptureWriter(args.out, robot=sim.robot, board=parse_board_spec(sim.board).to_string()) as w:
        n = collect_captures(rig, rig, w, args.count, trigger=rig.move)
    write_camera_yaml(args.out / "camera.yaml", CameraIntrinsics(sim.K, np.zeros(5), sim.width, sim.height),
                      {"source": "simulated camera (true intrinsics)"})
    truth = {"note": "simulated session's rig; readers of capture folders ignore this file", "rig": rig_source,
             "hand_eye": sim.T_flange_camera.tolist(), "T_base_board": scene.T_base_board.tolist()}
    wrote(args.out / "truth.yaml")
    (args.out / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False, default_flow_style=None))
    print(f"wrote {n} captures to {args.out} (the session's rig from {rig_source}; truth in truth.yaml)")
    return 0


def _parse_corrupt(text: str) -> dict[int, str]:
    from app.errors import ConfigError
    from calibration.simulator import CORRUPTIONS

    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        try:
            k, kind = item.split(":")
            out[int(k)] = kind
        except ValueError:
            raise ConfigError("--corrupt", f"expected INDEX:KIND items, got {item!r}") from None
        if kind not in CORRUPTIONS:
            raise ConfigError("--corrupt", f"unknown kind {kind!r}; valid: {', '.join(CORRUPTIONS)}")
    return out


def run_simulate(args) -> int:
    import numpy as np

    from app.errors import ConfigError
    from calibration.simulator import SimulationConfig, noisy, simulate_captures

    corrupt = _parse_corrupt(args.corrupt)
    bad = [k for k in corrupt if not 0 <= k < args.count]
    if bad:
        raise ConfigError("--corrupt", f"capture indices {bad} outside 0..{args.count - 1}")
    prepare_dir(args.out, args.overwrite)
    config = noisy() if args.noise else SimulationConfig()
    try:
        truth = simulate_captures(args.out, args.count, np.random.default_rng(args.seed), config,
                                  corrupt=corrupt)
    except RuntimeError as exc:
        raise ConfigError("--count", str(exc)) from None
    print(f"wrote {args.count} simulated captures to {args.out} "
          f"({'noisy' if args.noise else 'noise-free'}; truth in truth.yaml)")
    print("true hand_eye (T_flange_camera):")
    print(np.array2string(truth.T_flange_camera, precision=5, suppress_small=True))
    return 0
