"""Projector calibration: Gray-code structured light on a ChArUco board -> K_p and T_camera_projector.

The projector is an inverse camera (app/projector/model.py). At each of several board poses the
camera captures the board lit white (to detect its ChArUco corners, calibration/board.py) and lit
by every Gray-code pattern (calibration/graycode.py). Decoding tells, for each camera pixel, which
projector pixel lights it. For every detected corner a **local homography** (Moreno & Taubin 2012,
"Simple, accurate, and robust projector-camera calibration") from the decoded camera pixels within
``window`` pixels of the corner to their projector pixels maps the corner into the projector image
with sub-pixel accuracy (the board is planar, so the map is a homography near the corner). The
projector then has 3D board points and their projector pixels, like a camera:

- ``cv2.calibrateCamera`` on (board points, projector pixels) -> K_p, distortion, RMS (projector px);
- ``cv2.stereoCalibrate`` with the camera intrinsics fixed (camera = first, projector = second)
  -> R, T with p_projector = R p_camera + T, i.e. T_projector_camera; T_camera_projector is its inverse;
  RMS over both (px).

The camera's intrinsics come from ``osteonav calibrate intrinsics`` (camera.yaml).

Capture folder (written by :func:`write_captures`, read by :func:`read_captures`)::

    DIR/projector_capture.yaml   {projector: {width, height}, board: SPEC, poses: N, order: gray-code}
    DIR/camera.yaml              the camera intrinsics (calibration/intrinsics.py format)
    DIR/pose_000/pattern_000.png ... pattern_PPP.png   grey camera images, graycode.patterns order
    DIR/truth.yaml               (simulated folders only) the true K_p and T_camera_projector

Simulation (:class:`ProjectorSimulation`): the board is a plane, so camera pixel <- board point <-
projector pixel are homographies; each camera image = albedo (the board image warped into the
camera, supersampled) x (ambient + projector pattern warped into the camera, supersampled) + noise.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.geometry import se3
from calibration.board import DEFAULT_BOARD_SPEC, BoardDetector, Detection, board_image, parse_board_spec
from calibration.graycode import Decoded, decode, pattern_count, patterns
from app.outputs import wrote

log = logging.getLogger(__name__)

WINDOW_PX = 12   # half-size of the camera window around a corner whose decoded pixels fit the local homography
MIN_WINDOW_POINTS = 40
MIN_CORNERS_PER_VIEW = 8
MIN_VIEWS = 3
SUPERSAMPLE = 2


# --- simulation ----------------------------------------------------------------------------------

@dataclass
class ProjectorSimulation:
    """A camera and a projector on a rig looking at a ChArUco board (all lengths metres)."""

    K_camera: np.ndarray = field(default_factory=lambda: np.array([[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1]]))
    camera_size: tuple[int, int] = (640, 480)
    K_projector: np.ndarray = field(default_factory=lambda: np.array([[520.0, 0, 310.0], [0, 520.0, 215.0], [0, 0, 1]]))
    projector_size: tuple[int, int] = (640, 400)
    T_camera_projector: np.ndarray = field(default_factory=lambda: se3.from_rotvec_trans(
        np.deg2rad([1.5, -7.0, 0.8]), [0.06, 0.004, 0.002]))
    board: str = DEFAULT_BOARD_SPEC
    ambient: float = 25.0
    pixel_noise: float = 0.0
    blur_sigma: float = 0.0

    def board_poses(self, n: int, rng: np.random.Generator) -> list[np.ndarray]:
        """``n`` poses T_camera_board: 0.38-0.52 m away, tilted up to ~30 degrees, centred in view."""
        spec = parse_board_spec(self.board)
        w, h = spec.size
        poses = []
        for k in range(n):
            tilt = rng.uniform(-1, 1, 2) * np.deg2rad(30.0)
            if k < 2:                       # two strongly tilted views make the problem well posed
                tilt = np.deg2rad([25.0, -20.0]) * (1 if k == 0 else -1)
            roll = rng.uniform(-1, 1) * np.deg2rad(20.0)
            R = se3.from_rotvec_trans(np.array([tilt[0], tilt[1], roll]), np.zeros(3))[:3, :3]
            centre = np.array([rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), rng.uniform(0.38, 0.52)])
            t = centre - R @ np.array([w / 2, h / 2, 0.0])   # board centre at ``centre``
            poses.append(se3.make_pose(R, t))
        return poses

    def render_pose(self, T_camera_board: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(P, H, W) uint8 camera images of the board under each Gray-code pattern (graycode order)."""
        return np.stack([self.pattern_renderer(T_camera_board)(p, rng) for p in patterns(*self.projector_size)])

    def pattern_renderer(self, T_camera_board: np.ndarray):
        """``render(pattern (ph, pw) uint8, rng) -> (H, W) uint8``: the camera image of the board at
        ``T_camera_board`` lit by any projector image (the live capture shows patterns one by one)."""
        import cv2

        W, H = self.camera_size
        pw, ph = self.projector_size
        s = SUPERSAMPLE
        S = np.array([[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5], [0, 0, 1.0]])   # pixel centres kept
        img, px_per_m = board_image(self.board, 100)
        B = np.array([[1 / px_per_m, 0, 0.5 / px_per_m], [0, 1 / px_per_m, 0.5 / px_per_m], [0, 0, 1.0]])
        H_cam_board = self.K_camera @ T_camera_board[:3, [0, 1, 3]]
        T_projector_board = se3.inverse(self.T_camera_projector) @ T_camera_board
        H_proj_board = self.K_projector @ T_projector_board[:3, [0, 1, 3]]
        albedo = cv2.warpPerspective(img, S @ H_cam_board @ B, (W * s, H * s), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=255).astype(np.float32) / 255.0
        # projector pixel lighting each supersampled camera pixel (the board plane maps one to the other)
        H_proj_cam = H_proj_board @ np.linalg.inv(S @ H_cam_board)
        v, u = np.mgrid[0:H * s, 0:W * s].astype(np.float64)
        q = np.tensordot(H_proj_cam, np.stack([u, v, np.ones_like(u)]), axes=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi, yi = np.rint(q[0] / q[2]), np.rint(q[1] / q[2])
        lit = (q[2] > 0) & (xi >= 0) & (xi < pw) & (yi >= 0) & (yi < ph)
        flat = np.where(lit, yi * pw + xi, 0).astype(np.intp)
        base = (albedo * self.ambient).astype(np.float32)
        gain = (albedo * lit * (255.0 - self.ambient) / 255.0).astype(np.float32)

        def render(pattern: np.ndarray, rng: np.random.Generator) -> np.ndarray:
            big = cv2.addWeighted(gain * np.asarray(pattern).ravel()[flat].astype(np.float32), 1.0, base, 1.0, 0.0)
            im = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
            if self.blur_sigma > 0:
                im = cv2.GaussianBlur(im, (0, 0), self.blur_sigma)
            if self.pixel_noise > 0:
                im = im + rng.normal(0.0, self.pixel_noise, im.shape)
            return np.clip(np.rint(im), 0, 255).astype(np.uint8)

        return render

    def truth(self) -> dict:
        return {"width": self.projector_size[0], "height": self.projector_size[1], "K": self.K_projector.tolist(),
                "T_camera_projector": self.T_camera_projector.tolist()}


# --- capture folders -----------------------------------------------------------------------------

def write_captures(out: "str | Path", views: list[np.ndarray], projector_size: tuple[int, int], board: str,
                   K_camera: np.ndarray, camera_size: tuple[int, int], truth: dict | None = None) -> None:
    """Write a capture folder (module docstring) from (P, H, W) uint8 stacks, one per pose."""
    import yaml
    from PIL import Image

    from calibration.intrinsics import CameraIntrinsics, write_camera_yaml

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for k, stack in enumerate(views):
        d = out / f"pose_{k:03d}"
        wrote(d, folder=True)
        d.mkdir(exist_ok=True)
        for i, im in enumerate(stack):
            wrote(d / f"pattern_{i:03d}.png")
            Image.fromarray(im).save(d / f"pattern_{i:03d}.png", compress_level=1)
    meta = {"projector": {"width": int(projector_size[0]), "height": int(projector_size[1])},
            "board": parse_board_spec(board).to_string(), "poses": len(views), "order": "gray-code"}
    wrote(out / "projector_capture.yaml")
    (out / "projector_capture.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    write_camera_yaml(out / "camera.yaml", CameraIntrinsics(np.asarray(K_camera, float), np.zeros(5), *camera_size),
                      {"source": "simulated camera (true intrinsics)"})
    if truth is not None:
        wrote(out / "truth.yaml")
        (out / "truth.yaml").write_text(yaml.safe_dump({"projector": truth}, sort_keys=False))


def read_captures(folder: "str | Path") -> tuple[dict, list[tuple[str, np.ndarray | None, str]]]:
    """(meta, [(pose name, (P, H, W) uint8 stack or None, reason it is unusable)]) of a capture folder."""
    import yaml
    from PIL import Image

    from app.errors import ConfigError

    folder = Path(folder)
    meta_path = folder / "projector_capture.yaml"
    if not meta_path.is_file():
        raise ConfigError("--captures", f"{meta_path} does not exist (write captures with "
                          "`osteonav calibrate projector --simulate N --captures DIR` or your capture tool)")
    meta = yaml.safe_load(meta_path.read_text()) or {}
    try:
        pw, ph = int(meta["projector"]["width"]), int(meta["projector"]["height"])
    except (KeyError, TypeError, ValueError):
        raise ConfigError("projector", "projector_capture.yaml needs projector: {width, height}", str(meta_path)) from None
    n = pattern_count(pw, ph)
    views = []
    for d in sorted(p for p in folder.glob("pose_*") if p.is_dir()):
        files = [d / f"pattern_{i:03d}.png" for i in range(n)]
        missing = [f.name for f in files if not f.is_file()]
        if missing:
            views.append((d.name, None, f"{len(missing)} of {n} pattern images missing (first: {missing[0]})"))
            continue
        try:
            stack = np.stack([np.asarray(Image.open(f).convert("L")) for f in files])
        except (OSError, ValueError) as exc:
            views.append((d.name, None, f"unreadable image: {exc}"))
            continue
        views.append((d.name, stack, ""))
    return meta, views


# --- calibration ---------------------------------------------------------------------------------

def corners_in_projector(detection: Detection, decoded: Decoded, window: int = WINDOW_PX,
                         min_points: int = MIN_WINDOW_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Projector pixels of the detected corners by local homographies.

    Returns
    -------
    uv_projector : (M, 2) float64 (NaN where not enough decoded pixels surround the corner)
    ok : (M,) bool
    """
    import cv2

    H, W = decoded.valid.shape
    out = np.full((len(detection.corners_px), 2), np.nan)
    for k, (u, v) in enumerate(detection.corners_px):
        x0, x1 = max(0, int(round(u)) - window), min(W, int(round(u)) + window + 1)
        y0, y1 = max(0, int(round(v)) - window), min(H, int(round(v)) + window + 1)
        ys, xs = np.nonzero(decoded.valid[y0:y1, x0:x1])
        if len(xs) < min_points:
            continue
        src = np.column_stack([xs + x0, ys + y0]).astype(np.float64)
        dst = np.column_stack([decoded.col[ys + y0, xs + x0], decoded.row[ys + y0, xs + x0]]).astype(np.float64)
        Hm, _ = cv2.findHomography(src, dst, cv2.RANSAC, 1.5)
        if Hm is None:
            continue
        p = Hm @ np.array([u, v, 1.0])
        out[k] = p[:2] / p[2]
    ok = np.all(np.isfinite(out), axis=1)
    return out, ok


@dataclass
class ProjectorCalibration:
    """Result: K_p (3, 3), dist_p (5,), T_camera_projector (4, 4) metres; errors in pixels."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    T_camera_projector: np.ndarray
    rms_projector_px: float
    rms_stereo_px: float
    per_view: list[dict]
    skipped: list[dict]
    distortion: str = "none"
    alternative_rms_px: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "projector": {"width": self.width, "height": self.height, "K": self.K.tolist(),
                          "dist": [float(v) for v in self.dist], "T_camera_projector": self.T_camera_projector.tolist()},
            "calibration": {"method": "gray-code + local homographies, cv2.calibrateCamera + cv2.stereoCalibrate",
                            "distortion": self.distortion,
                            "rms_projector_px": float(self.rms_projector_px),
                            "rms_projector_px_other_distortion_models": self.alternative_rms_px,
                            "rms_stereo_px": float(self.rms_stereo_px),
                            "views": self.per_view, "skipped": self.skipped}}


DISTORTION_MODELS = ("none", "k1k2")


def calibrate_projector(views: list[tuple[str, np.ndarray | None, str]], projector_size: tuple[int, int],
                        K_camera: np.ndarray, dist_camera: np.ndarray | None = None, board: str = DEFAULT_BOARD_SPEC,
                        distortion: str = "none") -> ProjectorCalibration:
    """K_p and T_camera_projector from Gray-code captures (module docstring).

    Parameters
    ----------
    views : (name, (P, H, W) uint8 stack in graycode order or None, reason) per board pose
    projector_size : (width, height) of the projector, pixels
    K_camera, dist_camera : the camera's intrinsics (fixed)
    distortion : 'none' (the default: no projector lens distortion) or 'k1k2' (radial k1, k2).
        Measured on simulated captures of a distortion-free projector, k1/k2 trade off against the
        focal length and the extrinsics: T_camera_projector 2.2 mm off with 5 poses and 1.1 mm with
        15, against 0.71 and 0.48 mm without them; projector lenses are designed near
        distortion-free. ``alternative_rms_px`` reports the other model's projector RMS, so a lens
        that does distort shows itself.

    Raises ValueError when fewer than MIN_VIEWS poses are usable.
    """
    import cv2

    pw, ph = projector_size
    detector = BoardDetector(board)
    dist_camera = np.zeros(5) if dist_camera is None else np.asarray(dist_camera, dtype=np.float64).ravel()
    obj, cam, proj, names, skipped = [], [], [], [], []
    for name, stack, reason in views:
        if stack is None:
            skipped.append({"view": name, "reason": reason})
            continue
        det, why = detector.detect(stack[0])
        if det is None:
            skipped.append({"view": name, "reason": f"board not found: {why}"})
            continue
        uv_p, ok = corners_in_projector(det, decode(stack, pw, ph))
        if ok.sum() < MIN_CORNERS_PER_VIEW:
            skipped.append({"view": name, "reason": f"{int(ok.sum())} corners lit and decoded, need {MIN_CORNERS_PER_VIEW}"})
            continue
        obj.append(det.points_board[ok].astype(np.float32).reshape(-1, 1, 3))
        cam.append(det.corners_px[ok].astype(np.float32).reshape(-1, 1, 2))
        proj.append(uv_p[ok].astype(np.float32).reshape(-1, 1, 2))
        names.append(name)
    if len(obj) < MIN_VIEWS:
        raise ValueError(f"{len(obj)} usable board poses, need at least {MIN_VIEWS} "
                         f"(skipped: {'; '.join(s['view'] + ': ' + s['reason'] for s in skipped) or 'none'})")
    if distortion not in DISTORTION_MODELS:
        raise ValueError(f"unknown distortion model {distortion!r}; valid: {', '.join(DISTORTION_MODELS)}")
    K0 = np.array([[float(pw), 0, (pw - 1) / 2], [0, float(pw), (ph - 1) / 2], [0, 0, 1]])

    def fit(model: str):
        flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3 | cv2.CALIB_USE_INTRINSIC_GUESS
        if model == "none":
            flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
        return cv2.calibrateCamera(obj, proj, (pw, ph), K0.copy(), np.zeros(5), flags=flags)

    rms_p, K_p, dist_p, rvecs, tvecs = fit(distortion)
    alternative = next(m for m in DISTORTION_MODELS if m != distortion)
    alternative_rms = float(fit(alternative)[0])
    rms_s, _, _, _, _, R, T, _, _ = cv2.stereoCalibrate(
        obj, cam, proj, np.asarray(K_camera, np.float64), dist_camera, K_p, dist_p, (pw, ph),
        flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10))
    T_projector_camera = se3.make_pose(R, T.ravel())
    per_view = []
    for k, name in enumerate(names):
        p, _ = cv2.projectPoints(obj[k], rvecs[k], tvecs[k], K_p, dist_p)
        e = np.linalg.norm(p.reshape(-1, 2) - proj[k].reshape(-1, 2), axis=1)
        per_view.append({"view": name, "corners": int(len(e)), "rms_projector_px": float(np.sqrt(np.mean(e ** 2)))})
    return ProjectorCalibration(int(pw), int(ph), K_p, dist_p.ravel()[:5], se3.inverse(T_projector_camera),
                                float(rms_p), float(rms_s), per_view, skipped, distortion,
                                {alternative: alternative_rms})


def simulate_views(sim: ProjectorSimulation, n: int, rng: np.random.Generator) -> list[tuple[str, np.ndarray, str]]:
    """``n`` simulated board poses as calibrate_projector's views."""
    return [(f"pose_{k:03d}", sim.render_pose(T, rng), "") for k, T in enumerate(sim.board_poses(n, rng))]


def write_projector_yaml(path: "str | Path", result: ProjectorCalibration) -> None:
    import yaml

    text = ("# osteonav projector calibration (osteonav calibrate projector); the `projector:` block is\n"
            "# read by configs/projector.yaml's loader (app/projector/config.py)\n")
    wrote(path)
    Path(path).write_text(text + yaml.safe_dump(result.to_dict(), sort_keys=False, default_flow_style=None))


# --- command -------------------------------------------------------------------------------------

def run_command(args) -> int:
    """``osteonav calibrate projector`` (see app/commands/calibrate.py for the arguments)."""
    import yaml

    from app.errors import ConfigError
    from calibration.intrinsics import read_camera_yaml

    if args.simulate:
        if args.simulate < MIN_VIEWS:
            raise ConfigError("--simulate", f"at least {MIN_VIEWS} board poses needed, got {args.simulate}")
        sim = ProjectorSimulation(pixel_noise=2.0 if args.noise else 0.0, blur_sigma=0.7 if args.noise else 0.0)
        rng = np.random.default_rng(args.seed)
        views = simulate_views(sim, args.simulate, rng)
        write_captures(args.captures, [v[1] for v in views], sim.projector_size, sim.board, sim.K_camera,
                       sim.camera_size, truth=sim.truth())
        print(f"wrote {args.simulate} simulated board poses x {pattern_count(*sim.projector_size)} Gray-code "
              f"images to {args.captures}")
    meta, views = read_captures(args.captures)
    camera_path = args.camera or args.captures / "camera.yaml"
    if not camera_path.is_file():
        raise ConfigError("--camera", f"no camera intrinsics: {camera_path} does not exist; run "
                          f"`osteonav calibrate intrinsics` first or pass --camera FILE")
    camera = read_camera_yaml(camera_path)
    board = args.board or meta.get("board", DEFAULT_BOARD_SPEC)
    try:
        board = parse_board_spec(board).to_string()
    except ValueError as exc:
        raise ConfigError("--board", str(exc)) from None
    size = (int(meta["projector"]["width"]), int(meta["projector"]["height"]))
    try:
        result = calibrate_projector(views, size, camera.K, camera.dist, board, distortion=args.distortion)
    except ValueError as exc:
        raise ConfigError("--captures", f"{args.captures}: {exc}") from None
    out = args.out or args.captures / "projector.yaml"
    write_projector_yaml(out, result)
    print(f"{len(result.per_view)} board poses used, {len(result.skipped)} skipped")
    for s in result.skipped:
        print(f"  skipped {s['view']}: {s['reason']}")
    for v in result.per_view:
        print(f"  {v['view']}: {v['corners']} corners, {v['rms_projector_px']:.3f} px RMS in the projector")
    K = result.K
    print(f"projector {size[0]}x{size[1]}: fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f}  "
          f"dist {[round(float(v), 5) for v in result.dist]}")
    print(f"RMS reprojection: projector {result.rms_projector_px:.3f} px, stereo {result.rms_stereo_px:.3f} px")
    for model, rms in result.alternative_rms_px.items():
        print(f"lens distortion: {result.distortion}; with '{model}' the projector RMS would be {rms:.3f} px "
              f"(choose with --distortion; 'k1k2' only when the lens visibly distorts and many poses back it)")
    print("T_camera_projector:")
    print(np.array2string(result.T_camera_projector, precision=5, suppress_small=True))
    truth_path = args.captures / "truth.yaml"
    if truth_path.is_file():
        truth = (yaml.safe_load(truth_path.read_text()) or {}).get("projector", {})
        Kt, Tt = np.asarray(truth["K"]), np.asarray(truth["T_camera_projector"])
        dt = 1000 * np.linalg.norm(result.T_camera_projector[:3, 3] - Tt[:3, 3])
        dr = np.rad2deg(float(se3.rotation_angle(result.T_camera_projector, Tt)))
        print(f"vs truth: fx {100 * (K[0, 0] / Kt[0, 0] - 1):+.3f} %, fy {100 * (K[1, 1] / Kt[1, 1] - 1):+.3f} %, "
              f"cx {K[0, 2] - Kt[0, 2]:+.2f} px, cy {K[1, 2] - Kt[1, 2]:+.2f} px, "
              f"translation {dt:.3f} mm, rotation {dr:.4f} deg")
    print(f"wrote {out}")
    return 0
