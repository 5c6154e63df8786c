"""Eye-in-hand calibration from a capture folder: T_flange_camera, T_base_board, residuals.

Pipeline (``calibrate_capture_folder``):
1. For every capture: the flange pose ``T_base_flange = FK(q)`` (``app.geometry.ur``), and the board
   pose ``T_camera_board`` from the image (ChArUco corners + PnP, ``calibration.board``) or from
   the capture row. Captures without a usable board are reported and skipped.
2. ``check_conditioning`` warns when the flange rotations are too small or all about one axis:
   AX = XB fixes the rotation of X only from relative rotations about at least two non-parallel
   axes, and its translation error grows as the rotation angles shrink (Tsai & Lenz 1989).
3. Every method of ``calibration.solvers.HAND_EYE_METHODS`` solves AX = XB; each solution gets
   the board pose in the base as the mean of ``T_base_flange_i X T_camera_board_i``
   (translation mean, rotation projected onto SO(3)), and per-capture residuals:
   - ``rotation_deg``, ``translation_mm``: how far capture i's ``T_base_flange_i X T_camera_board_i``
     is from that mean (0 for perfect data);
   - ``reprojection_px``: RMS distance between the detected corners and the corners of the board
     at the mean pose projected through ``(T_base_flange_i X)^-1`` (images only).
   ``method="auto"`` picks the method with the smallest RMS reprojection error (or translation
   residual when no capture has an image).
4. ``solvers.solve_robot_world`` (AX = ZB) gives the board pose in the base directly; it is
   reported beside the AX = XB result.

Hand-eye YAML (``write_hand_eye_yaml``)::

    format: osteonav-hand-eye/1
    hand_eye: 4x4        # T_flange_camera: camera optical frame in the flange (tool0) frame, m;
                         # the same key and meaning as trial.yaml's hand_eye
    T_base_board: 4x4    # the board frame in the robot base frame (from the chosen method)
    method: park         # the method whose result is above (OpenCV's solver, calibration.solvers)
    robot: {model: ur5e}
    camera: {...}        # the intrinsics used (camera.yaml's block)
    residuals: {rotation_deg_rms, translation_mm_rms, reprojection_px_rms}
    methods: {tsai: {hand_eye, rotation_deg_rms, ..., differs_from_chosen_mm, _deg}, ...}
    robot_world: {method, hand_eye, T_base_board}
    captures: [{capture, rotation_deg, translation_mm, reprojection_px}, ...]   # used
    skipped: [{capture, reason}]
    warnings: [...]
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibration import solvers
from calibration.board import DEFAULT_BOARD_SPEC, BoardDetector, Detection, board_pose
from app.outputs import wrote

log = logging.getLogger(__name__)

HAND_EYE_FORMAT = "osteonav-hand-eye/1"
MIN_CAPTURES = 3
MIN_ROTATION_DEG = 10.0
"""Largest pairwise flange rotation below which the problem is called ill-posed."""
MIN_AXIS_SPREAD = 0.02
"""Second eigenvalue of the rotation-axis scatter (of 1) below which the axes are 'one axis'."""
MAX_REPROJECTION_PX = 3.0
"""A capture whose own PnP fit is worse than this (RMS px) is skipped as a bad detection."""


@dataclass
class Observation:
    """One usable capture: joints, flange pose, board pose (and its detection when from an image)."""

    capture: int
    q: np.ndarray
    T_base_flange: np.ndarray
    T_camera_board: np.ndarray
    detection: Detection | None = None
    image: np.ndarray | None = None


@dataclass
class MethodResult:
    method: str
    T_flange_camera: np.ndarray
    T_base_board: np.ndarray
    rotation_deg: np.ndarray         # (N,) per capture
    translation_mm: np.ndarray       # (N,)
    reprojection_px: np.ndarray      # (N,) NaN where the capture had no image

    def summary(self) -> dict:
        rp = self.reprojection_px[np.isfinite(self.reprojection_px)]
        return {"rotation_deg_rms": _rms(self.rotation_deg), "translation_mm_rms": _rms(self.translation_mm),
                "reprojection_px_rms": _rms(rp) if rp.size else None}

    def score(self) -> float:
        rp = self.reprojection_px[np.isfinite(self.reprojection_px)]
        return _rms(rp) if rp.size else _rms(self.translation_mm)


@dataclass
class HandEyeResult:
    chosen: MethodResult
    methods: dict[str, MethodResult]
    robot_world: dict
    observations: list[Observation]
    skipped: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def _rms(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def _rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angles (deg) of rotation matrices (..., 3, 3)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _project_to_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def mean_pose(T: np.ndarray) -> np.ndarray:
    """Mean of poses (N, 4, 4): translation mean, rotation = chordal L2 mean (SVD projection)."""
    out = np.eye(4)
    out[:3, :3] = _project_to_so3(T[:, :3, :3].sum(axis=0))
    out[:3, 3] = T[:, :3, 3].mean(axis=0)
    return out


def check_conditioning(T_base_flange: np.ndarray, min_rotation_deg: float = MIN_ROTATION_DEG,
                       min_axis_spread: float = MIN_AXIS_SPREAD) -> list[str]:
    """Warnings (strings) when the captures' rotations cannot pin down the hand-eye transform.

    Parameters
    ----------
    T_base_flange : (N, 4, 4) flange poses.

    Checks the largest pairwise relative rotation (too small: translation badly determined) and
    the spread of the relative rotations' axes (eigenvalues of the scatter of unit axes weighted
    by sin^2 of half the angle; all about one axis: the rotation about it is undetermined).
    """
    from scipy.spatial.transform import Rotation

    warnings = []
    n = len(T_base_flange)
    if n < MIN_CAPTURES:
        return [f"only {n} captures; at least {MIN_CAPTURES} (better 10-20) are needed"]
    i, j = np.triu_indices(n, k=1)
    R_rel = np.swapaxes(T_base_flange[j, :3, :3], -1, -2) @ T_base_flange[i, :3, :3]
    rotvec = Rotation.from_matrix(R_rel).as_rotvec()
    angles = np.degrees(np.linalg.norm(rotvec, axis=1))
    if angles.max() < min_rotation_deg:
        warnings.append(
            f"captures' rotations too small: the largest relative flange rotation is "
            f"{angles.max():.1f} deg (< {min_rotation_deg:g}); rotate the wrist by 20-40 deg "
            f"between captures")
    w = np.sin(np.radians(angles) / 2.0) ** 2
    keep = angles > 1.0
    if keep.sum() >= 1:
        axes = rotvec[keep] / np.linalg.norm(rotvec[keep], axis=1, keepdims=True)
        S = (axes * w[keep, None]).T @ axes / w[keep].sum()
        ev = np.sort(np.linalg.eigvalsh(S))[::-1]
        if ev[1] < min_axis_spread:
            warnings.append(
                f"captures' rotations too similar: all relative rotations are about nearly one axis "
                f"(axis spread {ev[1]:.3f} < {min_axis_spread:g}); add captures rotated about other "
                f"axes (tilt the camera as well as rolling it)")
    elif n >= MIN_CAPTURES:
        warnings.append("captures' rotations too small: no two captures differ by more than 1 deg")
    return warnings


def evaluate(method: str, T_flange_camera: np.ndarray, obs: list[Observation], K: np.ndarray,
             dist: np.ndarray | None) -> MethodResult:
    """Board pose in the base and per-capture residuals for one hand-eye solution (module doc)."""
    import cv2

    Tbf = np.stack([o.T_base_flange for o in obs])
    Tcb = np.stack([o.T_camera_board for o in obs])
    T_base_board_i = Tbf @ T_flange_camera @ Tcb
    T_base_board = mean_pose(T_base_board_i)
    dR = np.swapaxes(T_base_board[:3, :3], -1, -2) @ T_base_board_i[:, :3, :3]
    rot = _rotation_angle_deg(dR)
    trans = 1000.0 * np.linalg.norm(T_base_board_i[:, :3, 3] - T_base_board[:3, 3], axis=1)
    reproj = np.full(len(obs), np.nan)
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    for k, o in enumerate(obs):
        if o.detection is None:
            continue
        T_camera_board = np.linalg.inv(o.T_base_flange @ T_flange_camera) @ T_base_board
        rvec = cv2.Rodrigues(T_camera_board[:3, :3])[0]
        proj, _ = cv2.projectPoints(o.detection.points_board.reshape(-1, 1, 3), rvec,
                                    T_camera_board[:3, 3], K, d)
        reproj[k] = _rms(np.linalg.norm(proj.reshape(-1, 2) - o.detection.corners_px, axis=1))
    return MethodResult(method, T_flange_camera, T_base_board, rot, trans, reproj)


def calibrate_hand_eye(obs: list[Observation], K: np.ndarray, dist: np.ndarray | None = None,
                       method: str = "auto") -> HandEyeResult:
    """Solve T_flange_camera with every method, choose one, and solve AX = ZB too.

    Parameters
    ----------
    obs : usable captures (at least ``MIN_CAPTURES``).
    K : (3, 3) intrinsics (pixels); dist : OpenCV distortion or None.
    method : ``"auto"`` or one of ``solvers.HAND_EYE_METHODS``.
    """
    if len(obs) < MIN_CAPTURES:
        raise ValueError(f"only {len(obs)} usable captures; hand-eye calibration needs at least "
                         f"{MIN_CAPTURES} (10-20 recommended)")
    if method != "auto" and method not in solvers.HAND_EYE_METHODS:
        raise ValueError(f"unknown method {method!r}; valid: auto, {', '.join(solvers.HAND_EYE_METHODS)}")
    Tbf = np.stack([o.T_base_flange for o in obs])
    Tcb = np.stack([o.T_camera_board for o in obs])
    warnings = check_conditioning(Tbf)
    for w in warnings:
        log.warning("%s", w)
    results = {}
    for m in solvers.HAND_EYE_METHODS:
        try:
            X = solvers.solve_hand_eye(Tbf, Tcb, m)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.warning("method %s failed: %s", m, exc)
            continue
        if not np.isfinite(X).all():
            log.warning("method %s returned a non-finite result", m)
            continue
        results[m] = evaluate(m, X, obs, K, dist)
    if not results:
        raise ValueError("every hand-eye method failed; the captures are degenerate")
    if method == "auto":
        chosen = min(results.values(), key=MethodResult.score)
    elif method in results:
        chosen = results[method]
    else:
        raise ValueError(f"method {method} failed on these captures; try another or --method auto")
    rw = {}
    best_rw = None
    for m in solvers.ROBOT_WORLD_METHODS:
        try:
            X, T_base_board = solvers.solve_robot_world(Tbf, Tcb, m)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.warning("robot-world method %s failed: %s", m, exc)
            continue
        r = evaluate(m, X, obs, K, dist)
        if best_rw is None or r.score() < best_rw[2].score():
            best_rw = (m, (X, T_base_board), r)
    if best_rw is not None:
        m, (X, T_base_board), r = best_rw
        rw = {"method": m, "hand_eye": X, "T_base_board": T_base_board, **r.summary()}
    return HandEyeResult(chosen, results, rw, obs, [], warnings)


def observations_from_folder(root: "str | Path", K: np.ndarray, dist: np.ndarray | None,
                             board: str | None = None, robot: dict | None = None,
                             keep_images: bool = False, fk=None
                             ) -> tuple[list[Observation], list[dict], dict]:
    """Read a capture folder and turn each usable capture into an Observation.

    ``fk`` (q (6,) -> T_base_flange (4, 4)) overrides ``app.geometry.ur`` for the folder's robot.
    Returns (observations, skipped [{capture, reason}], robot block used).
    """
    import cv2

    from calibration.captures import read_captures

    cs = read_captures(root)
    robot = robot or cs.robot
    if fk is None:
        from app.geometry.ur import dh_from_config, forward_kinematics

        dh = dh_from_config(robot)
        fk = lambda q: forward_kinematics(dh, q)  # noqa: E731
    detector = BoardDetector(board or cs.board or DEFAULT_BOARD_SPEC)
    obs, skipped = [], []
    for c in cs.captures:
        T_base_flange = np.asarray(fk(c.q), dtype=np.float64)
        if c.T_camera_board is not None and c.image_path is None:
            obs.append(Observation(c.index, c.q, T_base_flange, c.T_camera_board))
            continue
        if c.image_path is None or not c.image_path.exists():
            skipped.append({"capture": c.index, "reason": f"image images/{c.name}.png is missing"})
            continue
        image = cv2.imread(str(c.image_path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            skipped.append({"capture": c.index, "reason": f"images/{c.name}.png cannot be read as an image"})
            continue
        det, why = detector.detect(image)
        if det is None:
            skipped.append({"capture": c.index, "reason": f"no usable board: {why}"})
            continue
        try:
            T_camera_board, errors = board_pose(det, K, dist)
        except ValueError as exc:
            skipped.append({"capture": c.index, "reason": str(exc)})
            continue
        if _rms(errors) > MAX_REPROJECTION_PX:
            skipped.append({"capture": c.index, "reason": f"board pose fits badly ({_rms(errors):.2f} px RMS)"})
            continue
        obs.append(Observation(c.index, c.q, T_base_flange, T_camera_board, det,
                               image if keep_images else None))
    for s in skipped:
        log.warning("skipping capture %d: %s", s["capture"], s["reason"])
    return obs, skipped, robot


def _mat(T: np.ndarray) -> list:
    return [[float(v) for v in row] for row in np.asarray(T)]


def _num(x):
    return None if x is None or not np.isfinite(x) else float(x)


def result_to_dict(result: HandEyeResult, robot: dict | None = None, camera: dict | None = None) -> dict:
    """The hand-eye YAML's content (module docstring)."""
    from scipy.spatial.transform import Rotation

    c = result.chosen
    methods = {}
    for m, r in result.methods.items():
        dR = c.T_flange_camera[:3, :3].T @ r.T_flange_camera[:3, :3]
        methods[m] = {"hand_eye": _mat(r.T_flange_camera),
                      **{k: _num(v) for k, v in r.summary().items()},
                      "differs_from_chosen_mm": float(1000 * np.linalg.norm(
                          r.T_flange_camera[:3, 3] - c.T_flange_camera[:3, 3])),
                      "differs_from_chosen_deg": float(np.degrees(np.linalg.norm(
                          Rotation.from_matrix(dR).as_rotvec())))}
    data = {
        "format": HAND_EYE_FORMAT,
        "hand_eye": _mat(c.T_flange_camera),
        "T_base_board": _mat(c.T_base_board),
        "method": c.method,
    }
    if robot:
        data["robot"] = robot
    if camera:
        data["camera"] = camera
    data["residuals"] = {k: _num(v) for k, v in c.summary().items()}
    data["methods"] = methods
    if result.robot_world:
        rw = result.robot_world
        data["robot_world"] = {"method": rw["method"], "hand_eye": _mat(rw["hand_eye"]),
                               "T_base_board": _mat(rw["T_base_board"]),
                               **{k: _num(rw[k]) for k in ("rotation_deg_rms", "translation_mm_rms",
                                                           "reprojection_px_rms")}}
    data["captures"] = [{"capture": int(o.capture), "rotation_deg": float(c.rotation_deg[k]),
                         "translation_mm": float(c.translation_mm[k]),
                         "reprojection_px": _num(c.reprojection_px[k])}
                        for k, o in enumerate(result.observations)]
    data["skipped"] = result.skipped
    data["warnings"] = result.warnings
    return data


def write_hand_eye_yaml(path: "str | Path", data: dict) -> None:
    import yaml

    wrote(path)
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False, default_flow_style=None))


def read_hand_eye_yaml(path: "str | Path") -> np.ndarray:
    """T_flange_camera (4, 4) from a hand-eye YAML (or any YAML with a trial-style hand_eye key)."""
    import yaml

    from app.errors import ConfigError

    data = yaml.safe_load(Path(path).read_text())
    T = np.asarray((data or {}).get("hand_eye"), dtype=np.float64) if isinstance(data, dict) else None
    if T is None or T.shape != (4, 4) or not np.isfinite(T).all():
        raise ConfigError("hand_eye", "expected a 4x4 matrix", str(path))
    return T
