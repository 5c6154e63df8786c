"""The session file: parsing, validation, and what the sources fill in (see :mod:`app.session`).

:func:`load_session` / :func:`parse_session` turn a session file into a :class:`SessionConfig`;
every error names the dotted key and the allowed values. Relative paths resolve against the
session file. :func:`resolve_session` completes a config with what the sources offer
(calibration, robot model, mesh, initial pose of a recorded or simulated trial).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from app import plugins_registry as registry
from app.errors import ConfigError
from app.geometry.camera import PinholeCamera

FORMAT = "osteonav-session/1"
TOP_KEYS = ("format", "camera", "robot", "tracker", "calibration", "bone", "outputs", "record", "out", "loop")
INPUT_PATH_PARAMS = ("trial", "recording", "mesh", "config")
OUTPUT_PATH_PARAMS = ("trial_dir", "path", "dir")   # resolved against the session file too


@dataclass
class PluginSpec:
    kind: str
    name: str
    params: dict = field(default_factory=dict)
    key: str = ""


RENAMED_LOOP = {   # loop keys of earlier session files: what replaced them
    "robot_lost_s": "removed (issue 32: one missing-pose clock): the status is lost after the tracker's "
                    "recovery.after_uncertain_s (1 s by default) without a camera pose; set it in the tracker's "
                    "config (tracker.params.config) and remove this key",
}


@dataclass
class LoopConfig:
    """Loop timing (seconds) and queue sizes."""

    stall_timeout_s: float = 0.5      # no frame for this long: the camera is stalled (status lost)
    robot_wait_s: float = 0.05        # wait this long for joints covering a frame's stamp
    max_joint_gap_s: float = 0.05     # joint samples further apart than this do not interpolate
    duration_s: float | None = None   # stop after this long (None: until stopped)
    tracker_queue: int = 2            # frames waiting for the tracker (newest kept)
    joint_buffer_s: float = 10.0      # joint history kept for interpolation
    event_repeat_s: float = 1.0       # the same event from the same source is logged once per this
    replay_rate: float = 1.0          # recorded/simulated sources play at this speed (0.25: a quarter)


@dataclass
class SessionConfig:
    path: Path | None
    camera: PluginSpec
    robot: PluginSpec
    tracker: PluginSpec | None
    outputs: list[PluginSpec]
    robot_model: dict | None = None
    hand_eye: np.ndarray | None = None
    intrinsics: PinholeCamera | None = None
    mesh: Path | None = None
    initial_pose: np.ndarray | None = None
    point_prior: np.ndarray | None = None
    pointed_pixel: tuple[float, float] | None = None
    pointer: dict | None = None
    record: Path | None = None
    out: Path | None = None
    loop: LoopConfig = field(default_factory=LoopConfig)


def _allowed(key: str, value: Any, allowed, src: str | None = None) -> None:
    if value not in allowed:
        raise ConfigError(key, f"got {value!r}; allowed: {', '.join(map(str, allowed))}", src)


def _mapping(key: str, value: Any, src: str) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(key, f"expected a mapping, got {type(value).__name__} {value!r}", src)
    return value


def _resolve(base: Path, value: str | Path | None) -> Path | None:
    if value is None:
        return None
    p = Path(str(value)).expanduser()
    return p if p.is_absolute() else (base / p)


def _matrix4(key: str, value: Any, base: Path, src: str) -> np.ndarray | None:
    """A 4x4 rigid transform given inline or as a file (YAML: a 4x4, or a mapping with ``key``'s name)."""
    if value is None:
        return None
    if isinstance(value, (str, Path)):
        path = _resolve(base, value)
        if not path.is_file():
            raise ConfigError(key, f"file not found: {path}", src)
        if path.suffix in (".txt", ".csv"):
            value = np.loadtxt(path, delimiter="," if path.suffix == ".csv" else None).tolist()
        else:
            loaded = yaml.safe_load(path.read_text())
            if isinstance(loaded, dict):
                names = [key.split(".")[-1], "hand_eye", "T_flange_camera", "initial_pose", "T_base_bone", "T"]
                found = next((loaded[n] for n in names if n in loaded), None)
                if found is None:
                    raise ConfigError(key, f"{path} holds none of the keys {', '.join(names)}", src)
                loaded = found
            value = loaded
    try:
        T = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(key, f"expected a 4x4 matrix of numbers, got {value!r}", src) from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ConfigError(key, f"expected a finite 4x4 matrix, got shape {T.shape}", src)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1]) or np.linalg.det(R) < 0:
        raise ConfigError(key, "not a rigid transform (rotation not orthonormal, or last row not 0 0 0 1)", src)
    return T


def _point3(key: str, value: Any, src: str) -> np.ndarray | None:
    """A point in the base frame (m), inline as [x, y, z]: ``bone.point_prior``, a point on the bone
    (the tracker's recovery starts its one-point initialiser there, app/filter/recovery.py)."""
    if value is None:
        return None
    ok = isinstance(value, (list, tuple)) and len(value) == 3 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    p = np.asarray(value, dtype=float) if ok else None
    if p is None or not np.all(np.isfinite(p)):
        raise ConfigError(key, f"expected a point on the bone in the base frame, metres: [x, y, z] (3 finite "
                          f"numbers, e.g. [0.61, -0.12, 0.05]), got {value!r}", src)
    return p


def _pixel2(key: str, value: Any, src: str) -> tuple[float, float] | None:
    """``bone.pointed_pixel``: a pixel (u, v) of the full-resolution depth image of the first usable
    frame, column then row, pixel centres at integers (app/tracking/start.py's PointedPixel); that it
    lies inside the image is checked when the camera has said its size (:func:`check_pointed_pixel`)."""
    if value is None:
        return None
    ok = isinstance(value, (list, tuple)) and len(value) == 2 and all(_is_number(v) for v in value)
    uv = np.asarray(value, dtype=float) if ok else None
    if uv is None or not np.all(np.isfinite(uv)) or np.any(uv < 0):
        raise ConfigError(key, f"expected a pixel of the depth image: [u, v] (2 numbers >= 0, column then row, "
                          f"full resolution, e.g. [424, 240]), got {value!r}", src)
    return float(uv[0]), float(uv[1])


POINTER_KEYS = ("marker_id", "marker_length_m", "tip_offset_m", "dictionary", "stream")


def _pointer(key: str, value: Any, src: str) -> dict | None:
    """``bone.pointer``: a pointer tool whose tip starts the tracker (app/tracking/pointer.py): its ArUco
    marker (``marker_id`` >= 0, ``marker_length_m``, the printed square's side in metres, ``dictionary``,
    default DICT_4X4_50), the tip in the marker frame (``tip_offset_m``: [x, y, z], metres) and the
    camera stream it is seen in (``stream``: ir, the default, or color)."""
    if value is None:
        return None
    block = _mapping(key, value, src)
    for k in block:
        _allowed(f"{key}.{k}", k, POINTER_KEYS, src)
    for k in ("marker_id", "marker_length_m", "tip_offset_m"):
        if k not in block:
            raise ConfigError(f"{key}.{k}", "missing: a pointer names its marker_id, marker_length_m and "
                              "tip_offset_m", src)
    marker_id = block["marker_id"]
    if not isinstance(marker_id, int) or isinstance(marker_id, bool) or marker_id < 0:
        raise ConfigError(f"{key}.marker_id", f"expected the marker's id, an integer >= 0, got {marker_id!r}", src)
    length = block["marker_length_m"]
    if not _is_number(length) or not 0 < length < 0.5:
        raise ConfigError(f"{key}.marker_length_m", f"expected the printed square's side in metres, 0 < L < 0.5 "
                          f"(e.g. 0.03), got {length!r}", src)
    tip = block["tip_offset_m"]
    ok = isinstance(tip, (list, tuple)) and len(tip) == 3 and all(_is_number(v) for v in tip)
    if not ok or not np.all(np.isfinite(tip)) or np.linalg.norm(tip) >= 0.5:
        raise ConfigError(f"{key}.tip_offset_m", f"expected the tip in the marker frame, metres: [x, y, z] (3 finite "
                          f"numbers, less than 0.5 m from the marker's centre, e.g. [0, -0.12, 0]), got {tip!r}", src)
    dictionary = block.get("dictionary", "DICT_4X4_50")
    try:
        from app.marker.aruco import dictionary as aruco_dictionary

        aruco_dictionary(str(dictionary))
    except ValueError as exc:
        raise ConfigError(f"{key}.dictionary", str(exc), src) from None
    stream = block.get("stream", "ir")
    _allowed(f"{key}.stream", stream, ("ir", "color"), src)
    return {"marker_id": marker_id, "marker_length_m": float(length), "tip_offset_m": [float(v) for v in tip],
            "dictionary": str(dictionary), "stream": stream}


def check_pointed_pixel(pixel: tuple[float, float] | None, camera: PinholeCamera, src: str | None = None) -> None:
    """``bone.pointed_pixel`` inside the camera's ``width`` x ``height`` depth image, or a ConfigError
    naming the key, the image's size and the fix."""
    if pixel is None:
        return
    u, v = pixel
    if not (u <= camera.width - 1 and v <= camera.height - 1):
        raise ConfigError("bone.pointed_pixel", f"[{u:g}, {v:g}] lies outside the camera's {camera.width}x"
                          f"{camera.height} depth image: give 0 <= u <= {camera.width - 1} (column) and "
                          f"0 <= v <= {camera.height - 1} (row), at the depth image's full resolution", src)


def _plugin(kind: str, value: Any, base: Path, src: str, default: str | None = None) -> PluginSpec:
    key = kind
    block = {"plugin": default} if value is None and default else _mapping(key, value, src)
    for k in block:
        _allowed(f"{key}.{k}", k, ("plugin", "params", "model", "dh") if kind == "robot" else ("plugin", "params"), src)
    name = block.get("plugin")
    if name is None:
        raise ConfigError(f"{key}.plugin", f"missing; allowed: {', '.join(registry.available(kind))}", src)
    _allowed(f"{key}.plugin", name, registry.available(kind), src)
    params = dict(_mapping(f"{key}.params", block.get("params"), src))
    for k, v in params.items():
        if k in INPUT_PATH_PARAMS + OUTPUT_PATH_PARAMS and isinstance(v, str):
            params[k] = str(_resolve(base, v))
    return PluginSpec(kind, name, params, key)


def _simulation_params(spec: PluginSpec, src: str) -> None:
    """A simulated source's ``scenario``, ``seconds`` and ``seed``, checked before anything is simulated."""
    from app.sim.scenarios import SCENARIOS

    params, key = spec.params, f"{spec.key}.params"
    if "scenario" in params:
        _allowed(f"{key}.scenario", params["scenario"], tuple(SCENARIOS), src)
    seconds = params.get("seconds")
    if seconds is not None and (not _is_number(seconds) or not 0 < seconds < float("inf")):
        raise ConfigError(f"{key}.seconds", f"expected a duration in seconds > 0 (or null: the scenario's), got "
                          f"{seconds!r}", src)
    seed = params.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"{key}.seed", f"expected an integer >= 0, got {seed!r}", src)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def load_session(path: str | Path, overrides: dict | None = None) -> SessionConfig:
    """Read and validate a session file; ``overrides`` (top-level keys) replace the file's values."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("--config", f"session file not found: {path}")
    src = str(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError("(file)", f"not valid YAML: {exc}", src) from None
    if not isinstance(raw, dict):
        raise ConfigError("(file)", "expected a mapping at the top level", src)
    raw.update(overrides or {})
    return parse_session(raw, path.parent, src, path)


def parse_session(raw: dict, base: Path, src: str = "(session)", path: Path | None = None) -> SessionConfig:
    for k in raw:
        _allowed(k, k, TOP_KEYS, src)
    if raw.get("format", FORMAT) != FORMAT:
        raise ConfigError("format", f"got {raw['format']!r}; allowed: {FORMAT}", src)
    for k in ("camera", "robot"):
        if k not in raw:
            raise ConfigError(k, f"missing; a session names its {k} plugin ({', '.join(registry.available(k))})", src)
    camera = _plugin("camera", raw["camera"], base, src)
    robot = _plugin("robot", raw["robot"], base, src)
    for spec in (camera, robot):
        if spec.name == "simulated":
            _simulation_params(spec, src)
    robot_block = raw["robot"] or {}
    robot_model = None
    if "model" in robot_block or "dh" in robot_block:
        from app.geometry.ur import dh_from_config

        robot_model = {k: robot_block[k] for k in ("model", "dh") if k in robot_block}
        try:
            dh_from_config(robot_model)
        except (ValueError, KeyError) as exc:
            raise ConfigError("robot.model", str(exc), src) from None
    tracker_raw = raw.get("tracker")
    tracker = None if tracker_raw is False else _plugin("tracker", tracker_raw, base, src, "particle_filter")
    outputs_raw = raw.get("outputs") or []
    if not isinstance(outputs_raw, list):
        raise ConfigError("outputs", "expected a list of {plugin, params}", src)
    outputs = []
    for i, o in enumerate(outputs_raw):
        spec = _plugin("output", o, base, src)
        spec.key = f"outputs[{i}]"
        outputs.append(spec)
    calib = _mapping("calibration", raw.get("calibration"), src)
    for k in calib:
        _allowed(f"calibration.{k}", k, ("hand_eye", "intrinsics"), src)
    intrinsics = _intrinsics(calib.get("intrinsics"), base, src)
    bone = _mapping("bone", raw.get("bone"), src)
    for k in bone:
        _allowed(f"bone.{k}", k, ("mesh", "initial_pose", "point_prior", "pointed_pixel", "pointer"), src)
    starts = [k for k in ("initial_pose", "point_prior", "pointed_pixel", "pointer") if bone.get(k) is not None]
    for live in ("pointed_pixel", "pointer"):
        if live in starts and len(starts) > 1:
            other = next(k for k in starts if k != live)
            raise ConfigError(f"bone.{live}", f"a live point starts the tracker on its own: give bone.{live} or "
                              f"bone.{other}, not both", src)
    mesh = _resolve(base, bone.get("mesh"))
    if mesh is not None and not mesh.is_file():
        raise ConfigError("bone.mesh", f"file not found: {mesh}", src)
    loop = _loop_config(_mapping("loop", raw.get("loop"), src), src)
    return SessionConfig(
        path=path, camera=camera, robot=robot, tracker=tracker, outputs=outputs, robot_model=robot_model,
        hand_eye=_matrix4("calibration.hand_eye", calib.get("hand_eye"), base, src), intrinsics=intrinsics,
        mesh=mesh, initial_pose=_matrix4("bone.initial_pose", bone.get("initial_pose"), base, src),
        point_prior=_point3("bone.point_prior", bone.get("point_prior"), src),
        pointed_pixel=_pixel2("bone.pointed_pixel", bone.get("pointed_pixel"), src),
        pointer=_pointer("bone.pointer", bone.get("pointer"), src),
        record=_resolve(base, raw.get("record")), out=_resolve(base, raw.get("out")), loop=loop,
    )


def _intrinsics(value: Any, base: Path, src: str) -> PinholeCamera | None:
    """``calibration.intrinsics``: inline (width, height, K) or a YAML file (its ``camera`` block)."""
    if value is None:
        return None
    if isinstance(value, str):
        p = _resolve(base, value)
        if not p.is_file():
            raise ConfigError("calibration.intrinsics", f"file not found: {p}", src)
        value = yaml.safe_load(p.read_text())
        value = value.get("camera", value) if isinstance(value, dict) else value
    try:
        return PinholeCamera.from_dict(value)
    except (TypeError, ValueError, KeyError) as exc:
        raise ConfigError("calibration.intrinsics", f"expected width, height and K (3x3): {exc}", src) from None


def _loop_config(loop_raw: dict, src: str) -> LoopConfig:
    """``loop``: LoopConfig's fields, each a finite positive number (or null)."""
    loop = LoopConfig()
    for old, why in RENAMED_LOOP.items():
        if old in loop_raw:
            raise ConfigError(f"loop.{old}", why, src)
    for k, v in loop_raw.items():
        _allowed(f"loop.{k}", k, tuple(LoopConfig.__dataclass_fields__), src)
        if v is not None and (not _is_number(v) or not 0 < v < float("inf")):
            raise ConfigError(f"loop.{k}", f"expected a finite number > 0 (or null), got {v!r}", src)
        setattr(loop, k, v)
    return loop


def resolve_session(config: SessionConfig, camera_model: PinholeCamera, defaults: dict) -> dict:
    """Calibration, robot model, mesh, initial pose and point prior: the file's, else the sources'. A
    live point (``bone.pointed_pixel``, ``bone.pointer``) replaces the sources' initial pose and point
    prior (the file's start is the live point; a simulated or recorded trial's own start is not used);
    the pointed pixel is checked against the camera's image size."""
    from app.geometry.ur import dh_from_config

    robot = config.robot_model or defaults.get("robot")
    if robot is None:
        raise ConfigError("robot.model", "missing: name the robot model (ur3e, ur5e, ur10e, ur16e, ...) or give dh")
    T_flange_camera = config.hand_eye if config.hand_eye is not None else defaults.get("T_flange_camera")
    if T_flange_camera is None:
        raise ConfigError("calibration.hand_eye", "missing: the 4x4 camera pose in the flange frame (a file or inline)")
    mesh = config.mesh or defaults.get("mesh")
    initial_pose = config.initial_pose if config.initial_pose is not None else defaults.get("initial_pose")
    point_prior = config.point_prior if config.point_prior is not None else defaults.get("point_prior")
    camera = config.intrinsics or camera_model
    check_pointed_pixel(config.pointed_pixel, camera, str(config.path) if config.path else None)
    if config.pointed_pixel is not None or config.pointer is not None:
        initial_pose = point_prior = None
    return {"camera": camera, "robot": robot, "dh": dh_from_config(robot),
            "T_flange_camera": np.asarray(T_flange_camera, float), "mesh_path": Path(mesh) if mesh else None,
            "initial_pose": initial_pose, "point_prior": point_prior, "pointed_pixel": config.pointed_pixel,
            "pointer": config.pointer}
