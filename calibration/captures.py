"""Hand-eye capture folders: the format, a reader, a writer, and live collection.

A *capture* is what the camera saw of the calibration board (an image, or the board pose already
measured) together with the robot's joint angles at that moment.

Capture folder, version 1
-------------------------
::

    DIR/
      capture.yaml    optional metadata:
                        format: osteonav-captures/1
                        robot: {model: ur5e}        # as trial.yaml's robot block (model or dh)
                        board: charuco:7x5:0.04:0.03:DICT_5X5_100   # board SPEC (calibration.board)
      captures.csv    one row per capture (required), header:
                        capture,stamp,q0,q1,q2,q3,q4,q5
                      optionally followed by the board pose in the camera optical frame, when it
                      was measured without an image (rotation vector in rad, translation in m):
                        board_rx,board_ry,board_rz,board_tx,board_ty,board_tz
                      (empty cells where a row has an image instead)
      images/000000.png   the camera image of capture 0 (8-bit grey or colour), named by the
                          capture column as {capture:06d}.png
      camera.yaml     optional intrinsics, as written by `osteonav calibrate intrinsics`
                      (a ``camera: {width, height, K, dist}`` block, as in trial.yaml plus dist)
      truth.yaml      written by the simulator only: the true hand_eye and T_base_board

Joint angles are radians (UR order, base to wrist 3), stamps seconds. Readers ignore other files.
A row whose image is missing, unreadable or has no usable board is reported and skipped by the
hand-eye command; it is not an error.

Live collection
---------------
``collect_captures(camera, robot, writer, count, trigger)`` reads a frame from a camera
(``camera.read() -> (image, stamp)``), asks the robot for its joints at that stamp
(``robot.joints_at(stamp) -> (6,)``) and writes both, ``count`` times, calling ``trigger(k)``
before each one (e.g. to wait for the operator to move the robot and press Enter, or to move the
simulated robot). The simulator's ``SimulatedCaptureRig`` implements both protocols.
"""
from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol
from app.outputs import wrote

import numpy as np

log = logging.getLogger(__name__)

FORMAT = "osteonav-captures/1"
JOINT_COLUMNS = [f"q{i}" for i in range(6)]
POSE_COLUMNS = ["board_rx", "board_ry", "board_rz", "board_tx", "board_ty", "board_tz"]


class CameraSource(Protocol):
    def read(self) -> tuple[np.ndarray, float]:
        """Next image (H, W) or (H, W, 3) uint8, and its stamp in seconds."""


class JointSource(Protocol):
    def joints_at(self, stamp: float) -> np.ndarray:
        """(6,) float64 joint angles in radians at ``stamp`` (seconds, the camera's clock)."""


@dataclass
class Capture:
    """One capture row. ``T_camera_board`` is set only when the row carries the board pose."""

    index: int
    stamp: float
    q: np.ndarray
    image_path: Path | None = None
    T_camera_board: np.ndarray | None = None

    @property
    def name(self) -> str:
        return f"{self.index:06d}"


@dataclass
class CaptureSet:
    root: Path
    captures: list[Capture]
    robot: dict = field(default_factory=lambda: {"model": "ur5e"})
    board: str | None = None


def _pose_from_rotvec(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    import cv2

    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(r, dtype=np.float64).reshape(3, 1))[0]
    T[:3, 3] = t
    return T


def _rotvec_from_pose(T: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(T[:3, :3], dtype=np.float64))[0].ravel()


def read_captures(root: "str | Path") -> CaptureSet:
    """Read a capture folder (see the module docstring).

    Raises
    ------
    TrialFormatError : captures.csv missing, a column missing, or a malformed number.
    """
    import yaml

    from app.errors import TrialFormatError

    root = Path(root)
    csv_path = root / "captures.csv"
    if not csv_path.is_file():
        raise TrialFormatError(csv_path, "missing: a capture folder needs captures.csv "
                               "(see `osteonav calibrate simulate` for an example)")
    meta = {}
    meta_path = root / "capture.yaml"
    if meta_path.is_file():
        meta = yaml.safe_load(meta_path.read_text()) or {}
        if not isinstance(meta, dict):
            raise TrialFormatError(meta_path, "expected a mapping")
    with csv_path.open(newline="") as f:
        reader = csv.DictReader(f)
        header = reader.fieldnames or []
        missing = [c for c in ["capture", "stamp", *JOINT_COLUMNS] if c not in header]
        if missing:
            raise TrialFormatError(csv_path, f"missing columns {missing}; header is {header}",
                                   "line 1")
        has_pose = all(c in header for c in POSE_COLUMNS)
        captures = []
        for line, row in enumerate(reader, start=2):
            try:
                index = int(row["capture"])
                stamp = float(row["stamp"])
                q = np.array([float(row[c]) for c in JOINT_COLUMNS])
                T = None
                if has_pose and all((row.get(c) or "").strip() for c in POSE_COLUMNS):
                    v = np.array([float(row[c]) for c in POSE_COLUMNS])
                    T = _pose_from_rotvec(v[:3], v[3:])
            except (TypeError, ValueError) as exc:
                raise TrialFormatError(csv_path, f"malformed number ({exc})", f"line {line}") from None
            if not np.isfinite(q).all():
                raise TrialFormatError(csv_path, "joint angles must be finite", f"line {line}")
            image = root / "images" / f"{index:06d}.png"
            captures.append(Capture(index, stamp, q, image if image.exists() or T is None else None, T))
    robot = meta.get("robot") or {"model": "ur5e"}
    return CaptureSet(root, captures, robot=robot, board=meta.get("board"))


class CaptureWriter:
    """Writes a capture folder incrementally; ``close()`` (or the context manager) finishes it."""

    def __init__(self, root: "str | Path", robot: dict | None = None, board: str | None = None):
        import yaml

        self.root = Path(root)
        wrote(self.root / "images", folder=True)
        (self.root / "images").mkdir(parents=True, exist_ok=True)
        meta = {"format": FORMAT, "robot": robot or {"model": "ur5e"}}
        if board:
            meta["board"] = board
        wrote(self.root / "capture.yaml")
        (self.root / "capture.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
        wrote(self.root / "captures.csv")
        self._file = (self.root / "captures.csv").open("w", newline="")
        self._csv = csv.writer(self._file)
        self._csv.writerow(["capture", "stamp", *JOINT_COLUMNS, *POSE_COLUMNS])
        self.count = 0

    def add(self, stamp: float, q: np.ndarray, image: np.ndarray | None = None,
            T_camera_board: np.ndarray | None = None) -> int:
        """Append one capture: an image, a board pose, or both. Returns its index."""
        import cv2

        if image is None and T_camera_board is None:
            raise ValueError("a capture needs an image or a board pose")
        index = self.count
        if image is not None:
            wrote(self.root / "images" / f"{index:06d}.png")
            cv2.imwrite(str(self.root / "images" / f"{index:06d}.png"), image)
        pose = [""] * 6
        if T_camera_board is not None:
            pose = [f"{v:.9f}" for v in (*_rotvec_from_pose(T_camera_board), *T_camera_board[:3, 3])]
        self._csv.writerow([index, f"{stamp:.6f}", *(f"{v:.9f}" for v in np.ravel(q)), *pose])
        self._file.flush()
        self.count += 1
        return index

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> "CaptureWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def collect_captures(camera: CameraSource, robot: JointSource, writer: CaptureWriter, count: int,
                     trigger: Callable[[int], bool] | None = None) -> int:
    """Collect ``count`` captures live (see the module docstring).

    ``trigger(k)`` runs before capture k; returning False stops early. Returns the number written.
    """
    for k in range(count):
        if trigger is not None and trigger(k) is False:
            break
        image, stamp = camera.read()
        q = np.asarray(robot.joints_at(stamp), dtype=np.float64)
        writer.add(stamp, q, image=image)
        log.debug("capture %d at %.3f s, q = %s", k, stamp, np.array2string(q, precision=3))
    return writer.count
