"""A trial's metadata, ``trial.yaml`` (shared/RECORDING_FORMAT.md, "trial.yaml"), read and written.

Import as ``from app.trial.meta import TrialMeta, load_meta, dump_meta``.

``load_meta`` validates at the boundary: the format string (version 1 or 1.1), the camera (K finite 3x3 with last row
(0, 0, 1), positive size, positive ``depth_scale``), the robot (exactly one of ``model`` / ``dh``),
the hand-eye ``T_flange_camera`` (rigid 4x4), the mesh name and the optional ``initial_pose``
(rigid 4x4) and ``point_prior`` (3 finite numbers). Every error is a
:class:`app.errors.TrialFormatError` naming the file and the key. Top-level keys the format does
not define are kept in ``TrialMeta.extra`` and written back. Version 1.1's optional ``infrared`` and
``color`` blocks become ``TrialMeta.streams`` (:class:`app.image_streams.ImageStreams`); a meta
without image streams is written as version 1, one with them as 1.1.

YAML 1.1 (PyYAML) reads ``1e-05`` (no decimal point) as a string; the reader converts such strings
wherever a number is expected, and the writer always writes a decimal point (``1.0e-05``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from app.errors import TrialFormatError
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.geometry.ur import DHParameters, dh_from_config
from app.image_streams import ColorStream, ImageStreams, InfraredStream

FORMAT = "osteonav-trial/1"
FORMAT_1_1 = "osteonav-trial/1.1"   # version 1 plus optional image streams (infrared, colour)
FORMATS = (FORMAT, FORMAT_1_1)
META_FILE = "trial.yaml"
FRAMES_FILE = "frames.csv"
JOINTS_FILE = "joints.csv"
GROUNDTRUTH_FILE = "groundtruth.txt"
DEPTH_DIR = "depth"
IR_DIR = "ir"          # the names this project writes; a 1.1 trial.yaml names its own ('dir')
COLOR_DIR = "color"
# present while a writer is recording; left behind by a killed recorder (the trial is interrupted)
MARKER_FILE = ".recording-in-progress"
POSE_ATOL = 1e-5  # rigidity tolerance for poses typed into trial.yaml (R^T R = I, det R = 1)

KNOWN_KEYS = ("format", "camera", "robot", "hand_eye", "mesh", "initial_pose", "point_prior")
STREAM_KEYS = ("infrared", "color")   # version 1.1 only


def depth_png_name(frame_id: int) -> str:
    """``depth/{frame:06d}.png``, relative to the trial directory."""
    return f"{DEPTH_DIR}/{int(frame_id):06d}.png"


def image_png_name(directory: str, frame_id: int) -> str:
    """``{directory}/{frame:06d}.png`` (an image stream's PNG), relative to the trial directory."""
    return f"{directory}/{int(frame_id):06d}.png"


@dataclass
class TrialMeta:
    """The contents of trial.yaml.

    camera : PinholeCamera, the depth camera (K in pixels, width x height of every PNG)
    depth_scale : float, millimetres per PNG unit (depth_mm = PNG value * depth_scale)
    robot : dict, the ``robot`` block as in the file (``{'model': NAME}`` or ``{'dh': {a, d, alpha}}``)
    dh : DHParameters of that robot
    T_flange_camera : (4, 4) float64, camera optical frame in the flange frame (hand-eye), metres
    mesh : str, bone mesh file, relative to the trial directory or absolute; metres, the bone frame
    initial_pose : (4, 4) float64 coarse T_base_bone, or None
    point_prior : (3,) float64 a point on the bone surface in the base frame (metres), or None
    extra : dict, top-level keys the format does not define (kept, written back)
    streams : ImageStreams, the optional infrared / colour streams (format 1.1); empty = version 1
    stream_dirs : dict stream name ('ir', 'color') -> directory relative to the trial ('dir' in trial.yaml)
    """

    camera: PinholeCamera
    depth_scale: float
    robot: dict
    dh: DHParameters
    T_flange_camera: np.ndarray
    mesh: str
    initial_pose: np.ndarray | None = None
    point_prior: np.ndarray | None = None
    extra: dict = field(default_factory=dict)
    streams: ImageStreams = field(default_factory=ImageStreams)
    stream_dirs: dict = field(default_factory=dict)

    def __post_init__(self):
        self.streams = self.streams or ImageStreams()
        self.stream_dirs = {**{"ir": IR_DIR, "color": COLOR_DIR}, **dict(self.stream_dirs or {})}
        self.depth_scale = float(self.depth_scale)
        self.T_flange_camera = np.asarray(self.T_flange_camera, dtype=float)
        self.mesh = str(self.mesh)
        if self.initial_pose is not None:
            self.initial_pose = np.asarray(self.initial_pose, dtype=float)
        if self.point_prior is not None:
            self.point_prior = np.asarray(self.point_prior, dtype=float).reshape(3)
        self.robot = dict(self.robot) if self.robot else {}
        self.extra = dict(self.extra or {})


# ---------------------------------------------------------------- reading

def load_meta(path: str | Path) -> TrialMeta:
    """Read and validate ``trial.yaml`` at ``path``; raise :class:`TrialFormatError` naming the key."""
    path = Path(path)
    if not path.is_file():
        raise TrialFormatError(path, f"missing: every trial needs {META_FILE} (RECORDING_FORMAT.md)")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc)
        raise TrialFormatError(path, f"not valid YAML: {problem}", where) from exc
    except UnicodeDecodeError as exc:
        raise TrialFormatError(path, "not a text file") from exc
    return parse_meta(data, path)


def parse_meta(data, source: str | Path = META_FILE) -> TrialMeta:
    """A validated :class:`TrialMeta` from trial.yaml's parsed mapping (``source`` names it in errors)."""
    if not isinstance(data, dict):
        raise TrialFormatError(source, f"expected a mapping of keys (format, camera, robot, ...), got {type(data).__name__}")

    def err(key: str, message: str) -> TrialFormatError:
        return TrialFormatError(source, message, f"key '{key}'")

    def need(mapping: dict, key: str, dotted: str):
        if key not in mapping or mapping[key] is None:
            raise err(dotted, "missing (RECORDING_FORMAT.md lists it as required)")
        return mapping[key]

    fmt = need(data, "format", "format")
    if fmt not in FORMATS:
        raise err("format", f"expected '{FORMAT}' or '{FORMAT_1_1}', got {fmt!r}: not an osteonav trial of "
                  "a version this reader knows")

    cam = need(data, "camera", "camera")
    if not isinstance(cam, dict):
        raise err("camera", f"expected a mapping (width, height, K, depth_scale), got {cam!r}")
    size = {k: _positive_int(need(cam, k, f"camera.{k}"), f"camera.{k}", err) for k in ("width", "height")}
    K = _matrix(need(cam, "K", "camera.K"), (3, 3), "camera.K", err)
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-12):
        raise err("camera.K", f"last row must be [0, 0, 1], got {K[2].tolist()}")
    try:
        camera = PinholeCamera(K, size["width"], size["height"])
    except ValueError as exc:
        raise err("camera.K", str(exc)) from exc
    depth_scale = _number(need(cam, "depth_scale", "camera.depth_scale"), "camera.depth_scale", err)
    if not depth_scale > 0:
        raise err("camera.depth_scale", f"must be positive (millimetres per PNG unit), got {depth_scale}")

    robot = need(data, "robot", "robot")
    if not isinstance(robot, dict):
        raise err("robot", f"expected a mapping with 'model' or 'dh', got {robot!r}")
    if ("model" in robot) == ("dh" in robot):
        raise err("robot", "give exactly one of 'model' (e.g. ur5e) or 'dh' (a, d, alpha), "
                  f"got {'both' if 'model' in robot else 'neither'}")
    robot = dict(robot)
    if "dh" in robot:
        block = robot["dh"]
        if not isinstance(block, dict):
            raise err("robot.dh", f"expected a mapping {{a, d, alpha}}, got {block!r}")
        missing = [k for k in ("a", "d", "alpha") if k not in block]
        if missing:
            raise err("robot.dh", f"lacks {', '.join(missing)}: give a, d (metres) and alpha (radians), 6 numbers each")
        robot["dh"] = {**block, **{k: [_number(v, f"robot.dh.{k}", err) for v in _list(block[k], f"robot.dh.{k}", err)]
                                   for k in ("a", "d", "alpha")}}
    try:
        dh = dh_from_config(robot)
    except ValueError as exc:
        raise err("robot.dh" if "dh" in robot else "robot.model", str(exc)) from exc

    T_flange_camera = _pose(need(data, "hand_eye", "hand_eye"), "hand_eye", err)
    mesh = need(data, "mesh", "mesh")
    if not isinstance(mesh, str) or not mesh.strip():
        raise err("mesh", f"expected a file name (relative to the trial directory), got {mesh!r}")

    initial_pose = data.get("initial_pose")
    if initial_pose is not None:
        initial_pose = _pose(initial_pose, "initial_pose", err)
    point_prior = data.get("point_prior")
    if point_prior is not None:
        point_prior = _matrix(point_prior, (3,), "point_prior", err)

    streams, dirs = (ImageStreams(), {}) if fmt == FORMAT else _parse_streams(data, camera, err)
    own = KNOWN_KEYS + (STREAM_KEYS if fmt == FORMAT_1_1 else ())
    extra = {k: v for k, v in data.items() if k not in own}
    return TrialMeta(camera=camera, depth_scale=depth_scale, robot=robot, dh=dh, T_flange_camera=T_flange_camera,
                     mesh=mesh, initial_pose=initial_pose, point_prior=point_prior, extra=extra, streams=streams,
                     stream_dirs=dirs)


def _stream_dir(block: dict, key: str, err) -> str:
    value = block.get("dir")
    if not isinstance(value, str) or not value.strip() or value.strip() in (DEPTH_DIR, ".", ".."):
        raise err(f"{key}.dir", f"expected a directory name relative to the trial (e.g. 'ir'), got {value!r}")
    return value.strip().rstrip("/")


def _parse_streams(data: dict, depth_camera: PinholeCamera, err) -> tuple[ImageStreams, dict]:
    """The ``infrared`` and ``color`` blocks of a version 1.1 trial.yaml (RECORDING_FORMAT.md, version 1.1)."""
    infrared = color = None
    dirs = {}
    ir = data.get("infrared")
    if ir is not None:
        if not isinstance(ir, dict):
            raise err("infrared", f"expected a mapping (dir, emitter), got {ir!r}")
        dirs["ir"] = _stream_dir(ir, "infrared", err)
        emitter = ir.get("emitter", True)
        if not isinstance(emitter, bool):
            raise err("infrared.emitter", f"expected true or false, got {emitter!r}")
        infrared = InfraredStream(emitter=emitter)
    c = data.get("color")
    if c is not None:
        if not isinstance(c, dict):
            raise err("color", f"expected a mapping (dir, aligned_to_depth, width, height, K, ...), got {c!r}")
        dirs["color"] = _stream_dir(c, "color", err)
        aligned = c.get("aligned_to_depth", False)
        if not isinstance(aligned, bool):
            raise err("color.aligned_to_depth", f"expected true or false, got {aligned!r}")
        if aligned:
            color = ColorStream(depth_camera, aligned_to_depth=True)
        else:
            color = _parse_color_camera(c, err)
    if dirs.get("ir") is not None and dirs.get("ir") == dirs.get("color"):
        raise err("color.dir", f"the infrared and colour streams both name the directory '{dirs['ir']}'")
    return ImageStreams(infrared, color), dirs


def _parse_color_camera(c: dict, err) -> ColorStream:
    for key in ("width", "height", "K", "T_depth_color"):
        if c.get(key) is None:
            raise err(f"color.{key}", "missing: an unaligned colour stream needs width, height, K and T_depth_color "
                      "(or aligned_to_depth: true)")
    size = {k: _positive_int(c[k], f"color.{k}", err) for k in ("width", "height")}
    K = _matrix(c["K"], (3, 3), "color.K", err)
    try:
        camera = PinholeCamera(K, size["width"], size["height"])
    except ValueError as exc:
        raise err("color.K", str(exc)) from exc
    distortion = _matrix(c.get("distortion", [0.0] * 5), (5,), "color.distortion", err)
    return ColorStream(camera, distortion, _pose(c["T_depth_color"], "color.T_depth_color", err), aligned_to_depth=False)


def _number(value, key: str, err) -> float:
    """A finite float from a YAML scalar; strings such as '1e-05' (YAML 1.1) are converted."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise err(key, f"expected a number, got {value!r}")
    try:
        out = float(value)
    except ValueError:
        raise err(key, f"expected a number, got {value!r}") from None
    if not np.isfinite(out):
        raise err(key, f"expected a finite number, got {value!r}")
    return out


def _positive_int(value, key: str, err) -> int:
    number = _number(value, key, err)
    if number != int(number) or number <= 0:
        raise err(key, f"expected a positive integer, got {value!r}")
    return int(number)


def _list(value, key: str, err) -> list:
    if not isinstance(value, (list, tuple)):
        raise err(key, f"expected a list, got {value!r}")
    return list(value)


def _matrix(value, shape: tuple, key: str, err) -> np.ndarray:
    """A finite float array of ``shape`` from nested YAML lists."""
    rows = _list(value, key, err)
    if len(shape) == 1:
        if len(rows) != shape[0]:
            raise err(key, f"expected {shape[0]} numbers, got {len(rows)}")
        return np.array([_number(v, key, err) for v in rows])
    if len(rows) != shape[0]:
        raise err(key, f"expected a {shape[0]}x{shape[1]} matrix ({shape[0]} rows), got {len(rows)} rows")
    return np.stack([_matrix(r, shape[1:], key, err) for r in rows])


def _pose(value, key: str, err) -> np.ndarray:
    T = _matrix(value, (4, 4), key, err)
    if not se3.is_rigid(T, atol=POSE_ATOL):
        R = T[:3, :3]
        raise err(key, "expected a rigid 4x4 pose (orthonormal R, det R = 1, last row [0, 0, 0, 1]); got "
                  f"|R^T R - I| = {np.abs(R.T @ R - np.eye(3)).max():.2g}, det R = {np.linalg.det(R):.6g}, "
                  f"last row {T[3].tolist()}")
    return T


# ---------------------------------------------------------------- writing

class _Dumper(yaml.SafeDumper):
    """SafeDumper whose floats always carry a decimal point (``1.0e-05``): YAML 1.1 reads ``1e-05`` as a string."""


def _represent_float(dumper: yaml.SafeDumper, value) -> yaml.ScalarNode:
    value = float(value)
    if not np.isfinite(value):
        text = ".nan" if np.isnan(value) else (".inf" if value > 0 else "-.inf")
    else:
        text = repr(value).lower()
        if "e" in text and "." not in text.split("e")[0]:
            text = text.replace("e", ".0e", 1)
        if "e" in text and text.split("e")[1][0] not in "+-":   # YAML 1.1 floats need the exponent's sign
            text = text.replace("e", "e+", 1)
    return dumper.represent_scalar("tag:yaml.org,2002:float", text)


_Dumper.add_representer(float, _represent_float)
_Dumper.add_multi_representer(np.floating, _represent_float)
_Dumper.add_multi_representer(np.integer, lambda d, v: d.represent_int(int(v)))
_Dumper.add_representer(np.ndarray, lambda d, v: d.represent_list(v.tolist()))


def meta_to_dict(meta: TrialMeta) -> dict:
    """trial.yaml's mapping for ``meta`` (plain Python types, the format's key order, then ``extra``)."""
    robot = {k: v for k, v in meta.robot.items()}
    if ("model" in robot) == ("dh" in robot):   # no usable block given: write the DH table itself
        robot = {k: v for k, v in robot.items() if k not in ("model", "dh")}
        robot["dh"] = meta.dh.to_dict()
    camera = meta.camera.to_dict()
    data = {
        "format": FORMAT_1_1 if meta.streams else FORMAT,
        "camera": {"width": camera["width"], "height": camera["height"],
                   "K": [[float(x) for x in row] for row in camera["K"]], "depth_scale": float(meta.depth_scale)},
        "robot": robot,
        "hand_eye": np.asarray(meta.T_flange_camera, dtype=float).tolist(),
        "mesh": str(meta.mesh),
    }
    if meta.initial_pose is not None:
        data["initial_pose"] = np.asarray(meta.initial_pose, dtype=float).tolist()
    if meta.point_prior is not None:
        data["point_prior"] = np.asarray(meta.point_prior, dtype=float).reshape(3).tolist()
    data.update(_streams_to_dict(meta))
    for k, v in meta.extra.items():
        if k in KNOWN_KEYS or (meta.streams and k in STREAM_KEYS):
            raise ValueError(f"TrialMeta.extra must not hold the format's own key '{k}'")
        data[k] = v
    return data


def _streams_to_dict(meta: TrialMeta) -> dict:
    """The version 1.1 ``infrared`` and ``color`` blocks of ``meta`` (empty when it has no image stream)."""
    out = {}
    streams = meta.streams
    if streams.infrared is not None:
        out["infrared"] = {"dir": meta.stream_dirs["ir"], "emitter": bool(streams.infrared.emitter)}
    if streams.color is not None:
        c = streams.color
        block = {"dir": meta.stream_dirs["color"], "aligned_to_depth": bool(c.aligned_to_depth)}
        if not c.aligned_to_depth:
            block.update(width=c.camera.width, height=c.camera.height,
                         K=[[float(x) for x in row] for row in c.camera.K],
                         distortion=[float(x) for x in c.distortion], T_depth_color=c.T_depth_color.tolist())
        out["color"] = block
    return out


def dump_meta(meta: TrialMeta, path: str | Path) -> None:
    """Write ``meta`` to ``path`` atomically (a temporary file, then ``os.replace``).

    The mapping is validated with the reader's own rules first, so a writer never leaves a
    trial.yaml that :func:`load_meta` rejects.
    """
    path = Path(path)
    text = yaml.dump(meta_to_dict(meta), Dumper=_Dumper, sort_keys=False, default_flow_style=None, width=120)
    parse_meta(yaml.safe_load(text), path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
