"""Reading a recorded trial (shared/RECORDING_FORMAT.md): cheap checks at once, depth images lazily.

Import as ``from app.trial.reader import open_trial``::

    reader = open_trial("trials/sim01")
    T_base_camera, valid = reader.camera_poses()        # (N, 4, 4), (N,) bool
    for frame in reader.iter_frames():                   # Frame(index, frame_id, stamp, depth_m, infrared, color)
        ...

Opening validates everything that costs no image decoding: ``trial.yaml`` (:func:`load_meta`),
``frames.csv`` (header, integer frame ids and finite stamps, both strictly increasing),
``joints.csv`` (header ``stamp,q0..q5``, finite values, stamps strictly increasing),
``groundtruth.txt`` when present (one row per frame, stamps equal within ``STAMP_ATOL``, unit
quaternions), that every listed PNG exists (depth and, in a version 1.1 trial, each declared image
stream's), and that the mesh file exists. Depth PNGs are decoded on demand and must be 16-bit,
single channel, of the camera's size; infrared PNGs 8-bit grey of the depth size; colour PNGs
8-bit RGB of the colour camera's size (returned RGB). Every error is a
:class:`app.errors.TrialFormatError` naming the file and the line or frame.

Interrupted trials: a writer keeps the marker ``.recording-in-progress`` while it records. When a
reader finds it, the recording was killed: an unterminated last CSV line is dropped, frames
without a PNG or without a ground-truth row are dropped, ``interrupted`` is True and a warning says
how many frames are readable. Without the marker each of these is an error.

Camera poses: the joint angles are interpolated linearly at each frame's stamp
(:func:`app.geometry.ur.interpolate_joints`), then ``T_base_camera = FK(q) @ T_flange_camera``.
A frame outside the joint samples' span has no pose: it is flagged invalid (NaN pose) and counted
in a warning, never extrapolated.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.errors import TrialFormatError
from app.geometry.ur import forward_kinematics, interpolate_joints
from app.trial.meta import (DEPTH_DIR, FRAMES_FILE, GROUNDTRUTH_FILE, JOINTS_FILE, MARKER_FILE, META_FILE, TrialMeta,
                            depth_png_name, image_png_name, load_meta)
from app.trial.tum import read_tum
from app.trial.writer import FRAMES_HEADER, JOINTS_HEADER, png_to_depth

log = logging.getLogger(__name__)

STAMP_ATOL = 1e-6  # groundtruth.txt stamps vs frames.csv stamps (both written with >= 6 decimals), s


@dataclass(frozen=True)
class Frame:
    """One depth frame of a trial.

    index : position in the trial (0 .. N-1), the row of ``camera_poses()`` and ``groundtruth``
    frame_id : the camera's frame counter (names ``depth/{frame_id:06d}.png``)
    stamp : capture time, s, on the joints' clock
    depth_m : (H, W) float32 depth along the optical axis, metres; 0 = no measurement
    infrared : (H, W) uint8 left-imager image (format 1.1, ``ir/``), or None when the trial has none
    color : (Hc, Wc, 3) uint8 RGB (format 1.1, ``color/``), or None when the trial has none
    """

    index: int
    frame_id: int
    stamp: float
    depth_m: np.ndarray
    infrared: np.ndarray | None = None
    color: np.ndarray | None = None


def open_trial(path: str | Path) -> "TrialReader":
    """Open and validate the trial directory at ``path`` (see :class:`TrialReader`)."""
    return TrialReader(path)


class TrialReader:
    """A recorded trial, validated on opening; depth images are read on demand (see the module docstring)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_dir():
            raise TrialFormatError(self.path, "not a trial directory (it does not exist or is a file)")
        self.interrupted = (self.path / MARKER_FILE).exists()
        self.meta: TrialMeta = load_meta(self.path / META_FILE)
        frame_ids, stamps = self._read_frames()
        self.joint_stamps, self.joints = self._read_joints()
        groundtruth = self._read_groundtruth(frame_ids, stamps)
        n_listed = len(frame_ids)
        keep = self._png_present(frame_ids)
        if groundtruth is not None:
            keep[len(groundtruth):] = False   # only when interrupted: checked in _read_groundtruth
            groundtruth = groundtruth[keep[: len(groundtruth)]]
        self.frame_ids = frame_ids[keep]
        self.stamps = stamps[keep]
        self.groundtruth = groundtruth
        for arr in (self.frame_ids, self.stamps, self.joint_stamps, self.joints) + ((groundtruth,) if groundtruth is not None else ()):
            arr.setflags(write=False)
        if self.interrupted:
            log.warning("%s: the recording was interrupted (%s present): %d of %d listed frames readable",
                        self.path, MARKER_FILE, len(self.frame_ids), n_listed)
        if len(self.frame_ids) == 0:
            raise TrialFormatError(self.path / FRAMES_FILE, "no readable frames in this trial")
        if not self.mesh_path.is_file():
            raise TrialFormatError(self.path / META_FILE, f"mesh file {self.mesh_path} not found", "key 'mesh'")
        self._camera_poses = None

    # ------------------------------------------------------------ CSV files

    def _csv_rows(self, name: str, header: str) -> list[tuple[int, list[str]]]:
        """(line number, fields) of the data rows of ``name`` after checking its header."""
        path = self.path / name
        if not path.is_file():
            raise TrialFormatError(path, f"missing: every trial needs {name} (RECORDING_FORMAT.md)")
        text = path.read_text()
        lines = text.split("\n")
        if text.endswith("\n"):
            lines = lines[:-1]
        elif self.interrupted and lines:
            log.warning("%s: dropped the unterminated last line %r of the interrupted recording", path, lines[-1])
            lines = lines[:-1]
        elif len(lines) > 1:   # the writer ends every row with a newline: a file cut mid-line is truncated
            raise TrialFormatError(path, f"the last line {lines[-1]!r} has no line end: the file was cut short "
                                   f"(copy it again from the recording)", f"line {len(lines)}")
        if not lines:
            if self.interrupted:
                return []
            raise TrialFormatError(path, f"empty: expected the header '{header}'", "line 1")
        found = [f.strip() for f in lines[0].split(",")]
        if found != header.split(","):
            raise TrialFormatError(path, f"expected the header '{header}', got '{lines[0].strip()}'", "line 1")
        return [(i, [f.strip() for f in line.split(",")]) for i, line in enumerate(lines[1:], start=2) if line.strip()]

    def _read_frames(self) -> tuple[np.ndarray, np.ndarray]:
        path = self.path / FRAMES_FILE
        ids, stamps = [], []
        for lineno, fields in self._csv_rows(FRAMES_FILE, FRAMES_HEADER):
            where = f"line {lineno}"
            if len(fields) != 2:
                raise TrialFormatError(path, f"expected 2 values 'frame,stamp', got {len(fields)}", where)
            try:
                frame_id = int(fields[0])
            except ValueError:
                raise TrialFormatError(path, f"frame must be an integer, got {fields[0]!r}", where) from None
            try:
                stamp = float(fields[1])
            except ValueError:
                raise TrialFormatError(path, f"stamp must be a number, got {fields[1]!r}", where) from None
            if frame_id < 0:
                raise TrialFormatError(path, f"frame must be non-negative, got {frame_id}", where)
            if not np.isfinite(stamp):
                raise TrialFormatError(path, f"stamp must be finite, got {fields[1]!r}", where)
            if ids and frame_id <= ids[-1]:
                raise TrialFormatError(path, f"frame ids must increase strictly, got {frame_id} after {ids[-1]}", where)
            if stamps and stamp <= stamps[-1]:
                raise TrialFormatError(path, f"stamps must increase strictly, got {fields[1]} after {stamps[-1]!r}", where)
            ids.append(frame_id)
            stamps.append(stamp)
        return np.array(ids, dtype=np.int64), np.array(stamps, dtype=float)

    def _read_joints(self) -> tuple[np.ndarray, np.ndarray]:
        path = self.path / JOINTS_FILE
        rows = self._csv_rows(JOINTS_FILE, JOINTS_HEADER)
        for lineno, fields in rows:
            if len(fields) != 7:
                raise TrialFormatError(path, f"expected 7 values 'stamp,q0,...,q5', got {len(fields)}", f"line {lineno}")
        try:
            values = np.array([fields for _, fields in rows], dtype=float).reshape(-1, 7)
        except ValueError:
            for lineno, fields in rows:  # find the offending line
                for f in fields:
                    try:
                        float(f)
                    except ValueError:
                        raise TrialFormatError(path, f"expected numbers, got {f!r}", f"line {lineno}") from None
            raise
        bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
        if len(bad):
            raise TrialFormatError(path, f"values must be finite, got {','.join(rows[bad[0]][1])}", f"line {rows[bad[0]][0]}")
        back = np.flatnonzero(np.diff(values[:, 0]) <= 0)
        if len(back):
            k = back[0] + 1
            raise TrialFormatError(path, f"stamps must increase strictly, got {rows[k][1][0]} after {rows[k - 1][1][0]}",
                                   f"line {rows[k][0]}")
        return values[:, 0].copy(), values[:, 1:].copy()

    def _read_groundtruth(self, frame_ids: np.ndarray, stamps: np.ndarray) -> np.ndarray | None:
        path = self.path / GROUNDTRUTH_FILE
        if not path.is_file():
            return None
        gt_stamps, T = read_tum(path, allow_truncated_last_line=self.interrupted)
        n = len(frame_ids)
        if len(gt_stamps) > n or (len(gt_stamps) < n and not self.interrupted):
            raise TrialFormatError(path, f"expected one pose per frame: {len(gt_stamps)} poses for {n} frames in {FRAMES_FILE}")
        mismatch = np.flatnonzero(np.abs(gt_stamps - stamps[: len(gt_stamps)]) > STAMP_ATOL)
        if len(mismatch):
            k = mismatch[0]
            raise TrialFormatError(path, f"stamp {gt_stamps[k]!r} differs from {FRAMES_FILE}'s {stamps[k]!r}",
                                   f"pose {k + 1}, frame {frame_ids[k]}")
        return T

    def _png_present(self, frame_ids: np.ndarray) -> np.ndarray:
        """(N,) bool: every PNG of the frame exists (depth, then each declared image stream's)."""
        present = np.ones(len(frame_ids), dtype=bool)
        streams = [(DEPTH_DIR, "depth")] + [(self.meta.stream_dirs[n], n) for n in self.meta.streams.names]
        for directory, what in streams:
            folder = self.path / directory
            names = set(os.listdir(folder)) if folder.is_dir() else set()
            here = np.array([f"{int(f):06d}.png" in names for f in frame_ids], dtype=bool)
            if not self.interrupted and not here.all():
                k = int(np.flatnonzero(~here)[0])
                raise TrialFormatError(self.path / image_png_name(directory, frame_ids[k]),
                                       f"missing: {FRAMES_FILE} lists frame {frame_ids[k]} but its {what} PNG does "
                                       "not exist", f"frame {frame_ids[k]}")
            present &= here
        return present

    # ------------------------------------------------------------ depth

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __repr__(self) -> str:
        return f"TrialReader({str(self.path)!r}, {len(self)} frames{', interrupted' if self.interrupted else ''})"

    def read_depth(self, index: int) -> np.ndarray:
        """Depth (H, W) float32 metres of frame ``index`` (0 .. N-1); 0 = no measurement."""
        return png_to_depth(self.read_depth_png(index), self.meta.depth_scale)

    def read_depth_png(self, index: int) -> np.ndarray:
        """The depth PNG of frame ``index`` as stored: (H, W) uint16 in units of ``depth_scale`` mm, checked."""
        import cv2

        frame_id = int(self.frame_ids[index])
        path = self.path / depth_png_name(frame_id)
        where = f"frame {frame_id}"
        if not path.is_file():
            raise TrialFormatError(path, "missing: the depth PNG of a listed frame", where)
        png = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if png is None:
            raise TrialFormatError(path, "cannot be read as a PNG image", where)
        channels = 1 if png.ndim == 2 else png.shape[2]
        if png.dtype != np.uint16 or channels != 1:
            raise TrialFormatError(path, f"expected a 16-bit single-channel PNG, got {png.dtype} with {channels} channel(s)",
                                   where)
        expected = (self.meta.camera.height, self.meta.camera.width)
        if png.shape != expected:
            raise TrialFormatError(path, f"expected {expected[1]}x{expected[0]} pixels (camera width x height in "
                                   f"{META_FILE}), got {png.shape[1]}x{png.shape[0]}", where)
        return png

    def _read_image(self, index: int, stream: str, dtype, channels: int, size: tuple[int, int]) -> np.ndarray:
        """An image stream's PNG of frame ``index`` as stored, checked for dtype, channels and (width, height)."""
        import cv2

        frame_id = int(self.frame_ids[index])
        path = self.path / image_png_name(self.meta.stream_dirs[stream], frame_id)
        where = f"frame {frame_id}"
        png = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
        if png is None:
            raise TrialFormatError(path, "missing or not a PNG image: the " + stream + " image of a listed frame", where)
        found = 1 if png.ndim == 2 else png.shape[2]
        if png.dtype != dtype or found != channels:
            raise TrialFormatError(path, f"expected an {8 * np.dtype(dtype).itemsize}-bit PNG with {channels} "
                                   f"channel(s), got {png.dtype} with {found}", where)
        if (png.shape[1], png.shape[0]) != size:
            raise TrialFormatError(path, f"expected {size[0]}x{size[1]} pixels ({META_FILE}), got "
                                   f"{png.shape[1]}x{png.shape[0]}", where)
        return png

    def read_infrared(self, index: int) -> np.ndarray | None:
        """Infrared (H, W) uint8 of frame ``index``, or None when the trial has no infrared stream."""
        if self.meta.streams.infrared is None:
            return None
        return self._read_image(index, "ir", np.uint8, 1, (self.meta.camera.width, self.meta.camera.height))

    def read_color(self, index: int) -> np.ndarray | None:
        """Colour (Hc, Wc, 3) uint8 RGB of frame ``index``, or None when the trial has no colour stream."""
        color = self.meta.streams.color
        if color is None:
            return None
        bgr = self._read_image(index, "color", np.uint8, 3, (color.camera.width, color.camera.height))
        return np.ascontiguousarray(bgr[..., ::-1])

    def iter_frames(self):
        """Yield every readable :class:`Frame` in order, decoding one frame's PNGs at a time."""
        for i in range(len(self.frame_ids)):
            yield Frame(i, int(self.frame_ids[i]), float(self.stamps[i]), self.read_depth(i), self.read_infrared(i),
                        self.read_color(i))

    # ------------------------------------------------------------ mesh and poses

    @property
    def mesh_path(self) -> Path:
        """The bone mesh named in trial.yaml, resolved against the trial directory."""
        mesh = Path(self.meta.mesh)
        return mesh if mesh.is_absolute() else (self.path / mesh)

    def load_mesh(self):
        """The bone mesh as a ``trimesh.Trimesh`` (metres, bone frame); :class:`app.errors.MeshError` if unusable."""
        from app.mesh import load_mesh

        return load_mesh(self.mesh_path)

    def camera_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """``(T_base_camera (N, 4, 4), valid (N,) bool)`` at each frame's stamp; invalid rows are NaN.

        T_base_camera = FK(q(stamp)) @ T_flange_camera, q interpolated linearly in the joint samples.
        """
        if self._camera_poses is None:
            q, valid = interpolate_joints(self.joint_stamps, self.joints, self.stamps)
            T = np.full((len(self.stamps), 4, 4), np.nan)
            if valid.any():
                T[valid] = forward_kinematics(self.meta.dh, q[valid]) @ self.meta.T_flange_camera
            if not valid.all():
                log.warning("%s: %d of %d frames lie outside the joint samples' span [%s, %s]: no camera pose for them",
                            self.path, int((~valid).sum()), len(valid),
                            f"{self.joint_stamps[0]:.6f}" if len(self.joint_stamps) else "-",
                            f"{self.joint_stamps[-1]:.6f}" if len(self.joint_stamps) else "-")
            T.setflags(write=False)
            valid.setflags(write=False)
            self._camera_poses = (T, valid)
        return self._camera_poses
