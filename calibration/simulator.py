"""Calibration simulator: a ChArUco board seen by a robot-mounted camera from many robot poses.

Scene (frames as in DESIGN.md): a UR robot (default UR5e) carries a pinhole camera on its flange at
a known ``T_flange_camera``; a planar ChArUco board lies fixed at ``T_base_board``. For joint angles
q the board is seen at

    T_camera_board = (T_base_flange(q) T_flange_camera)^-1 T_base_board                   (1)

Rendering: OpenCV's own board image (``calibration.board.board_image``, board point (x, y) at
board-image pixel (x, y) * s - 0.5, s pixels per metre) is mapped into the camera image by the
plane-induced homography

    H = K [r1 r2 t] S^-1,   S^-1 = [[1/s, 0, 0.5/s], [0, 1/s, 0.5/s], [0, 0, 1]]           (2)

with r1, r2, t the first two columns and the translation of T_camera_board (points z = 0 of the
board). ``cv2.warpPerspective`` renders it at ``SUPERSAMPLE`` times the resolution on a white
background, area-averaged down (anti-aliasing), then optionally blurred (Gaussian, sigma in
pixels) and given Gaussian grey-level noise; images are 8-bit grey.

Poses: each view looks at the board's centre (jittered) from a distance in ``distance_m``, its
optical axis tilted from the board normal by up to ``max_tilt_deg`` in a random direction and
rolled about the axis by up to ``max_roll_deg``. The flange pose that puts the camera there is
reached by damped Gauss-Newton inverse kinematics on ``app.geometry.ur.forward_kinematics``,
started from a nominal pose looking at the board. A view is kept when the whole board is in the
image and its rotation is at least ``min_separation_deg`` from every view kept so far (hand-eye
calibration needs varied rotations).

Noise models: ``blur_sigma`` (px), ``pixel_noise`` (grey levels, of 255) and ``joint_noise``
(rad, on the joint angles written to captures.csv, i.e. encoder noise). ``NOISY`` is the preset of
``osteonav calibrate simulate --noise``.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from calibration.board import DEFAULT_BOARD_SPEC, board_image, parse_board_spec
from app.outputs import wrote

log = logging.getLogger(__name__)

SUPERSAMPLE = 3
NOMINAL_Q = np.array([0.0, -1.5707963267948966, 1.5707963267948966, -1.5707963267948966,
                      -1.5707963267948966, 0.0])
"""UR 'home' pose with tool0's z axis pointing down (radians)."""


def _rotvec_matrix(r: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(r).as_matrix()


def _matrix_rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def _pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def default_hand_eye() -> np.ndarray:
    """A plausible, deliberately non-trivial T_flange_camera: 5 cm off-axis, a few degrees tilted."""
    return _pose(_rotvec_matrix(np.radians([2.0, -3.0, 12.0])), [0.012, 0.05, 0.035])


@dataclass
class SimulationConfig:
    """Everything the simulator needs; lengths metres, angles as named."""

    width: int = 640
    height: int = 480
    K: np.ndarray = field(default_factory=lambda: np.array(
        [[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]]))
    board: str = DEFAULT_BOARD_SPEC
    robot: dict = field(default_factory=lambda: {"model": "ur5e"})
    T_flange_camera: np.ndarray = field(default_factory=default_hand_eye)
    nominal_q: np.ndarray = field(default_factory=lambda: NOMINAL_Q.copy())
    nominal_distance_m: float = 0.45
    distance_m: tuple[float, float] = (0.33, 0.55)
    max_tilt_deg: float = 35.0
    max_roll_deg: float = 70.0
    min_separation_deg: float = 20.0
    margin_px: float = 12.0
    blur_sigma: float = 0.0
    pixel_noise: float = 0.0
    joint_noise: float = 0.0


NOISY = dict(blur_sigma=1.2, pixel_noise=6.0, joint_noise=5e-5)
"""Noise preset: 1.2 px blur, 6 grey levels of noise, 5e-5 rad (0.003 deg) encoder noise."""


def _fk_functions(robot: dict) -> Callable[[np.ndarray], np.ndarray]:
    from app.geometry.ur import dh_from_config, forward_kinematics

    dh = dh_from_config(robot)
    return lambda q: forward_kinematics(dh, q)


def solve_ik(fk: Callable[[np.ndarray], np.ndarray], T_base_flange: np.ndarray, q0: np.ndarray,
             iterations: int = 60, tol: float = 1e-10) -> tuple[np.ndarray, float]:
    """Joint angles reaching a flange pose, damped Gauss-Newton with a finite-difference Jacobian.

    Parameters
    ----------
    fk : q (..., 6) -> T_base_flange (..., 4, 4).
    T_base_flange : (4, 4) target. q0 : (6,) start, radians.

    Returns
    -------
    q : (6,) radians. error : float, final residual norm (metres + radians).
    """
    q = np.asarray(q0, dtype=np.float64).copy()
    h = 1e-7

    def residual(T):
        e_t = T_base_flange[:3, 3] - T[..., :3, 3]
        R_err = T_base_flange[:3, :3] @ np.swapaxes(T[..., :3, :3], -1, -2)
        return np.concatenate([e_t, _matrix_rotvec(R_err).reshape(e_t.shape)], axis=-1)

    err = np.inf
    for _ in range(iterations):
        Q = np.vstack([q, q + h * np.eye(6)])
        E = residual(fk(Q))
        e = E[0]
        err = float(np.linalg.norm(e))
        if err < tol:
            break
        J = -(E[1:] - e).T / h     # d(pose)/dq, (6, 6)
        lam = 1e-6
        dq = np.linalg.solve(J.T @ J + lam * np.eye(6), J.T @ e)
        step = np.linalg.norm(dq)
        if step > 0.5:
            dq *= 0.5 / step
        q = q + dq
    return q, err


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle of Ra^T Rb in degrees."""
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@dataclass
class CalibrationScene:
    """The simulated rig: robot kinematics, camera, hand-eye, and the board's place."""

    config: SimulationConfig
    T_base_board: np.ndarray
    fk: Callable[[np.ndarray], np.ndarray]

    def T_camera_board(self, q: np.ndarray) -> np.ndarray:
        """Eq. (1) for joint angles q (6,)."""
        T_base_camera = self.fk(np.asarray(q, dtype=np.float64)) @ self.config.T_flange_camera
        return np.linalg.inv(T_base_camera) @ self.T_base_board


def make_scene(config: SimulationConfig | None = None,
               fk: Callable[[np.ndarray], np.ndarray] | None = None) -> CalibrationScene:
    """Place the board ``nominal_distance_m`` in front of the camera at the nominal pose, facing it."""
    config = config or SimulationConfig()
    fk = fk or _fk_functions(config.robot)
    spec = parse_board_spec(config.board)
    w, h = spec.size
    T_base_camera = fk(config.nominal_q) @ config.T_flange_camera
    # board axes parallel to the camera's, its centre on the optical axis
    T_camera_board = _pose(np.eye(3), [-w / 2, -h / 2, config.nominal_distance_m])
    return CalibrationScene(config, T_base_camera @ T_camera_board, fk)


def project_board_outline(config: SimulationConfig, T_camera_board: np.ndarray) -> np.ndarray | None:
    """(4, 2) pixel positions of the board's outer corners, or None if one is behind the camera."""
    w, h = parse_board_spec(config.board).size
    corners = np.array([[0, 0, 0, 1], [w, 0, 0, 1], [w, h, 0, 1], [0, h, 0, 1]], dtype=np.float64)
    p = (T_camera_board @ corners.T)[:3]
    if np.any(p[2] <= 0.05):
        return None
    uv = config.K @ p
    return (uv[:2] / uv[2]).T


def _board_fully_visible(config: SimulationConfig, T_camera_board: np.ndarray) -> bool:
    uv = project_board_outline(config, T_camera_board)
    if uv is None:
        return False
    m = config.margin_px
    return bool(np.all((uv[:, 0] >= m) & (uv[:, 0] <= config.width - 1 - m)
                       & (uv[:, 1] >= m) & (uv[:, 1] <= config.height - 1 - m)))


def _sample_view(scene: CalibrationScene, rng: np.random.Generator) -> np.ndarray:
    """A random T_board_camera looking at the board's centre."""
    cfg = scene.config
    w, h = parse_board_spec(cfg.board).size
    target = np.array([w / 2, h / 2, 0.0]) + np.append(rng.uniform(-0.15, 0.15, 2) * [w, h], 0.0)
    tilt = np.radians(rng.uniform(0.0, cfg.max_tilt_deg))
    azimuth = rng.uniform(0.0, 2 * np.pi)
    roll = np.radians(rng.uniform(-cfg.max_roll_deg, cfg.max_roll_deg))
    R_tilt = _rotvec_matrix(tilt * np.array([np.cos(azimuth), np.sin(azimuth), 0.0]))
    R_board_camera = R_tilt @ _rotvec_matrix([0.0, 0.0, roll])
    distance = rng.uniform(*cfg.distance_m)
    position = target - distance * R_board_camera[:, 2]
    return _pose(R_board_camera, position)


def plan_captures(scene: CalibrationScene, count: int, rng: np.random.Generator,
                  max_attempts: int = 4000) -> np.ndarray:
    """Joint configurations of ``count`` varied views of the whole board.

    Returns
    -------
    (count, 6) float64 joint angles, radians. Raises RuntimeError when the constraints cannot be met.
    """
    cfg = scene.config
    T_flange_camera_inv = np.linalg.inv(cfg.T_flange_camera)
    qs: list[np.ndarray] = []
    rotations: list[np.ndarray] = []
    for _ in range(max_attempts):
        if len(qs) == count:
            break
        T_board_camera = _sample_view(scene, rng)
        T_camera_board = np.linalg.inv(T_board_camera)
        if not _board_fully_visible(cfg, T_camera_board):
            continue
        R_base_flange = (scene.T_base_board @ T_board_camera @ T_flange_camera_inv)[:3, :3]
        if any(rotation_angle_deg(R_base_flange, R) < cfg.min_separation_deg for R in rotations):
            continue
        target = scene.T_base_board @ T_board_camera @ T_flange_camera_inv
        q, err = solve_ik(scene.fk, target, cfg.nominal_q)
        if err > 1e-8 or np.max(np.abs(q - cfg.nominal_q)) > 2.5:
            continue
        qs.append(q)
        rotations.append(R_base_flange)
    if len(qs) < count:
        raise RuntimeError(f"found only {len(qs)} of {count} views at least {cfg.min_separation_deg} "
                           f"deg apart; lower min_separation_deg or the capture count")
    return np.array(qs)


class BoardRenderer:
    """Renders the board image seen from T_camera_board (eq. 2), with blur and noise."""

    def __init__(self, config: SimulationConfig, px_per_square: int = 120):
        self.config = config
        self.board_image, self.px_per_m = board_image(config.board, px_per_square)

    def render(self, T_camera_board: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """(height, width) uint8 grey image. ``rng`` is needed only when pixel_noise > 0."""
        import cv2

        cfg = self.config
        s = SUPERSAMPLE
        S_out = np.array([[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5], [0, 0, 1.0]])
        S_board_inv = np.array([[1 / self.px_per_m, 0, 0.5 / self.px_per_m],
                                [0, 1 / self.px_per_m, 0.5 / self.px_per_m], [0, 0, 1.0]])
        Rt = T_camera_board[:3, [0, 1, 3]]
        H = S_out @ cfg.K @ Rt @ S_board_inv
        big = cv2.warpPerspective(self.board_image, H, (cfg.width * s, cfg.height * s),
                                  flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                  borderValue=255)
        image = cv2.resize(big, (cfg.width, cfg.height), interpolation=cv2.INTER_AREA).astype(np.float64)
        if cfg.blur_sigma > 0:
            image = cv2.GaussianBlur(image, (0, 0), cfg.blur_sigma)
        if cfg.pixel_noise > 0:
            if rng is None:
                raise ValueError("pixel_noise > 0 needs an rng")
            image = image + rng.normal(0.0, cfg.pixel_noise, image.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


CORRUPTIONS = ("blank", "noise", "missing", "garbage")
"""Ways ``simulate_captures`` can spoil a capture: a white image, pure noise, no file, a non-PNG."""


@dataclass
class SimulationTruth:
    T_flange_camera: np.ndarray
    T_base_board: np.ndarray
    q: np.ndarray                  # (N, 6) true joint angles
    corrupted: dict[int, str]


class SimulatedCaptureRig:
    """The simulator as a live source: ``move(k)`` drives the robot to planned pose k, ``read()``
    renders what the camera sees, ``joints_at(stamp)`` reports the (noisy) encoder angles.
    Implements ``calibration.captures.CameraSource`` and ``JointSource``."""

    def __init__(self, scene: CalibrationScene, q_plan: np.ndarray, rng: np.random.Generator):
        self.scene = scene
        self.q_plan = q_plan
        self.rng = rng
        self.renderer = BoardRenderer(scene.config)
        self._k = 0
        self._stamp = 0.0

    def move(self, k: int) -> bool:
        if k >= len(self.q_plan):
            return False
        self._k = k
        self._stamp = 1.0 + 2.0 * k     # the robot takes ~2 s to move between views
        return True

    def read(self) -> tuple[np.ndarray, float]:
        T = self.scene.T_camera_board(self.q_plan[self._k])
        return self.renderer.render(T, self.rng), self._stamp

    def joints_at(self, stamp: float) -> np.ndarray:
        q = self.q_plan[self._k]
        sigma = self.scene.config.joint_noise
        return q + self.rng.normal(0.0, sigma, 6) if sigma > 0 else q.copy()


def simulate_captures(out: "str | Path", count: int, rng: np.random.Generator,
                      config: SimulationConfig | None = None, corrupt: "dict[int, str] | None" = None,
                      fk: Callable[[np.ndarray], np.ndarray] | None = None) -> SimulationTruth:
    """Write a capture folder (``calibration.captures``) of ``count`` simulated views.

    Parameters
    ----------
    out : folder to create. count : number of captures.
    rng : drives the poses, the image noise and the joint noise.
    corrupt : capture index -> one of ``CORRUPTIONS``, captures to spoil on purpose.
    fk : forward kinematics override (default: ``app.geometry.ur`` for ``config.robot``).

    Also writes ``camera.yaml`` (the true intrinsics, no distortion) and ``truth.yaml``.
    """
    import yaml

    from calibration.captures import CaptureWriter, collect_captures
    from calibration.intrinsics import CameraIntrinsics, write_camera_yaml

    config = config or SimulationConfig()
    corrupt = dict(corrupt or {})
    for k, kind in corrupt.items():
        if kind not in CORRUPTIONS:
            raise ValueError(f"unknown corruption {kind!r} for capture {k}; valid: {CORRUPTIONS}")
    out = Path(out)
    scene = make_scene(config, fk)
    q_plan = plan_captures(scene, count, rng)
    rig = SimulatedCaptureRig(scene, q_plan, rng)
    with CaptureWriter(out, robot=config.robot, board=parse_board_spec(config.board).to_string()) as w:
        collect_captures(rig, rig, w, count, trigger=rig.move)
    for k, kind in corrupt.items():
        path = out / "images" / f"{k:06d}.png"
        if kind == "missing":
            path.unlink()
        elif kind == "garbage":
            path.write_bytes(b"this is not a PNG file")
        else:
            import cv2

            img = np.full((config.height, config.width), 255, np.uint8) if kind == "blank" else \
                rng.integers(0, 256, (config.height, config.width), dtype=np.uint8)
            cv2.imwrite(str(path), img)
    write_camera_yaml(out / "camera.yaml",
                      CameraIntrinsics(config.K, np.zeros(5), config.width, config.height),
                      {"source": "calibration simulator (true intrinsics)"})
    truth = {
        "note": "simulator ground truth; readers of capture folders ignore this file",
        "hand_eye": config.T_flange_camera.tolist(),
        "T_base_board": scene.T_base_board.tolist(),
        "corrupted": {int(k): v for k, v in corrupt.items()},
        "noise": {"blur_sigma": config.blur_sigma, "pixel_noise": config.pixel_noise,
                  "joint_noise": config.joint_noise},
    }
    wrote(out / "truth.yaml")
    (out / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False, default_flow_style=None))
    return SimulationTruth(config.T_flange_camera.copy(), scene.T_base_board, q_plan, corrupt)


def noisy(config: SimulationConfig | None = None) -> SimulationConfig:
    """``config`` with the ``NOISY`` preset applied."""
    return replace(config or SimulationConfig(), **NOISY)
