"""Writing a recorded trial (shared/RECORDING_FORMAT.md) so that a kill at any moment leaves it readable.

Import as ``from app.trial.writer import TrialWriter``::

    with TrialWriter(out_dir, meta, mesh_source="bone.ply") as w:
        w.write_joints(t_robot, q_robot)            # (M,), (M, 6): any number of calls
        w.write_frame(frame_id, stamp, depth_m)     # (H, W) float32 metres, 0 or NaN = no measurement
        w.write_frame(frame_id, stamp, depth_m, infrared=ir, color=rgb)   # format 1.1: meta.streams declares them
        w.write_groundtruth(stamp, T_base_bone)     # optional, one per frame, same stamps

Order of work, which is what makes a killed recording readable:

1. the marker ``.recording-in-progress`` is created first and removed last (by :meth:`close`);
   a reader that finds it knows the trial was interrupted and tolerates a truncated last line;
2. ``trial.yaml`` is written atomically (temporary file + ``os.replace``), then the mesh;
3. each depth PNG, and each image stream's PNG (``ir/``, ``color/``: format 1.1), is written
   completely (temporary file + rename) *before* its ``frames.csv`` row, and every CSV row is
   flushed as it is written, so every listed frame has all its PNGs.

Depth is stored as uint16 ``round(depth_mm / depth_scale)``, clipped to [0, 65535]; NaN, negative
and zero depths become 0 (no measurement). With ``depth_scale`` = 0.1 mm this spans 6.5 m.
"""
from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np

from app.errors import TrialFormatError
from app.image_streams import check_frame_images
from app.outputs import wrote
from app.trial.meta import (DEPTH_DIR, FRAMES_FILE, GROUNDTRUTH_FILE, JOINTS_FILE, MARKER_FILE, META_FILE, TrialMeta,
                            depth_png_name, dump_meta, image_png_name)
from app.trial.tum import TUM_HEADER, format_tum_row

log = logging.getLogger(__name__)

FRAMES_HEADER = "frame,stamp"
JOINTS_HEADER = "stamp," + ",".join(f"q{i}" for i in range(6))
PNG_MAX = 65535


def depth_to_png(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """uint16 PNG values ``round(depth_mm / depth_scale)`` for depth (H, W) metres; invalid -> 0, clipped."""
    depth = np.asarray(depth_m, dtype=np.float64)
    units = depth * (1000.0 / depth_scale)
    units = np.where(np.isfinite(units) & (units > 0), units, 0.0)
    return np.clip(np.rint(units), 0, PNG_MAX).astype(np.uint16)


def png_to_depth(png: np.ndarray, depth_scale: float) -> np.ndarray:
    """Depth (H, W) float32 metres from uint16 PNG values; 0 stays 0 (no measurement)."""
    return (png.astype(np.float64) * (depth_scale * 1e-3)).astype(np.float32)


class TrialWriter:
    """Write one trial directory; a context manager (see the module docstring).

    Parameters
    ----------
    path : the trial directory (created; an existing trial there is an error unless ``overwrite``)
    meta : TrialMeta, written to trial.yaml
    mesh_source : path of the mesh file to copy to ``path / meta.mesh``, or a ``trimesh.Trimesh`` to
        export there; None when the mesh is already there or ``meta.mesh`` is absolute
    overwrite : replace an existing trial's files (other files in the directory are left alone)
    """

    def __init__(self, path: str | Path, meta: TrialMeta, mesh_source=None, overwrite: bool = False):
        self.path = Path(path)
        self.meta = meta
        self._shape = (meta.camera.height, meta.camera.width)
        self._frame_stamps: list[float] = []
        self._last_frame_id: int | None = None
        self._last_joint_stamp = -np.inf
        self._n_groundtruth = 0
        self._n_clipped = 0
        self._closed = False
        self._gt_file = None
        self._prepare_directory(overwrite)
        for name in (MARKER_FILE, META_FILE, META_FILE + ".tmp", FRAMES_FILE, JOINTS_FILE):
            wrote(self.path / name)
        (self.path / MARKER_FILE).write_text("osteonav: recording in progress; removed when the writer closes\n")
        dump_meta(meta, self.path / META_FILE)
        self._write_mesh(mesh_source)
        self._frames_file = open(self.path / FRAMES_FILE, "w")
        self._frames_file.write(FRAMES_HEADER + "\n")
        self._frames_file.flush()
        self._joints_file = open(self.path / JOINTS_FILE, "w")
        self._joints_file.write(JOINTS_HEADER + "\n")
        self._joints_file.flush()

    # ------------------------------------------------------------ setup

    def _prepare_directory(self, overwrite: bool) -> None:
        trial_files = [self.path / n for n in (META_FILE, FRAMES_FILE, JOINTS_FILE, GROUNDTRUTH_FILE, MARKER_FILE)]
        image_dirs = [DEPTH_DIR] + [self.meta.stream_dirs[n] for n in self.meta.streams.names]
        if any(p.exists() for p in trial_files) or (self.path / DEPTH_DIR).exists():
            if not overwrite:
                raise TrialFormatError(self.path, "already holds a trial; choose another directory or overwrite it "
                                       "(overwrite=True, --overwrite)")
            old_dirs = self._old_stream_dirs()
            for p in trial_files:
                p.unlink(missing_ok=True)
            for d in set(image_dirs) | old_dirs:   # the replaced trial's image streams go with it
                shutil.rmtree(self.path / d, ignore_errors=True)
        for d in image_dirs:
            wrote(self.path / d, folder=True)
            (self.path / d).mkdir(parents=True, exist_ok=True)

    def _old_stream_dirs(self) -> set[str]:
        """The image-stream directories the trial being overwritten declares (none if unreadable)."""
        from app.trial.meta import load_meta

        try:
            old = load_meta(self.path / META_FILE)
        except TrialFormatError:
            return set()
        return {old.stream_dirs[n] for n in old.streams.names}

    def _write_mesh(self, mesh_source) -> None:
        if mesh_source is None:
            return
        mesh_name = Path(self.meta.mesh)
        if mesh_name.is_absolute():
            log.debug("trial mesh %s is absolute: not copied", mesh_name)
            return
        dest = self.path / mesh_name
        wrote(dest.parent, folder=True)
        dest.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(mesh_source, (str, os.PathLike)):
            source = Path(mesh_source)
            if not source.is_file():
                raise FileNotFoundError(f"mesh source {source} not found")
            if dest.exists() and dest.resolve() == source.resolve():
                return
            tmp = dest.with_name(dest.name + ".tmp")
            wrote(dest)
            wrote(tmp)
            shutil.copyfile(source, tmp)
        else:  # a trimesh.Trimesh
            tmp = dest.with_name(".tmp-" + dest.name)   # trimesh picks the format from the suffix
            wrote(dest)
            wrote(tmp)
            mesh_source.export(tmp)
        os.replace(tmp, dest)

    # ------------------------------------------------------------ streams

    def write_frame(self, frame_id: int, stamp: float, depth_m: np.ndarray, infrared: np.ndarray | None = None,
                    color: np.ndarray | None = None) -> None:
        """Write ``depth/{frame_id:06d}.png`` and the image streams' PNGs, then its ``frames.csv`` row.

        frame_id : int, the camera's counter, strictly increasing
        stamp : float, capture time (s), strictly increasing, on the joints' clock
        depth_m : (H, W) depth in metres along the optical axis; 0, NaN or negative = no measurement
        infrared : (H, W) uint8, required when ``meta.streams.infrared`` is declared, else ignored
        color : (Hc, Wc, 3) uint8 RGB, required when ``meta.streams.color`` is declared, else ignored
        """
        self._check_open()
        frame_id = int(frame_id)
        stamp = float(stamp)
        if self._last_frame_id is not None and frame_id <= self._last_frame_id:
            raise ValueError(f"frame ids must increase: got {frame_id} after {self._last_frame_id}")
        if frame_id < 0:
            raise ValueError(f"frame ids must be non-negative, got {frame_id}")
        if not np.isfinite(stamp) or (self._frame_stamps and stamp <= self._frame_stamps[-1]):
            raise ValueError(f"frame stamps must be finite and increase strictly: got {stamp!r} after "
                             f"{self._frame_stamps[-1] if self._frame_stamps else None!r}")
        depth_m = np.asarray(depth_m)
        if depth_m.shape != self._shape:
            raise ValueError(f"depth image of frame {frame_id} has shape {depth_m.shape}, "
                             f"expected {self._shape} (camera height, width)")
        check_frame_images(self.meta.streams, self._shape, infrared, color, f"frame {frame_id}")
        png = depth_to_png(depth_m, self.meta.depth_scale)
        n_clipped = int(np.count_nonzero(png == PNG_MAX))
        if n_clipped and not self._n_clipped:
            log.warning("depth beyond %.2f m clipped to the PNG's range (depth_scale %g mm)",
                        PNG_MAX * self.meta.depth_scale * 1e-3, self.meta.depth_scale)
        self._n_clipped += n_clipped
        self._write_png(self.path / depth_png_name(frame_id), png)
        if self.meta.streams.infrared is not None:
            self._write_png(self.path / image_png_name(self.meta.stream_dirs["ir"], frame_id), np.asarray(infrared))
        if self.meta.streams.color is not None:   # PNG channel order is RGB; OpenCV encodes BGR
            self._write_png(self.path / image_png_name(self.meta.stream_dirs["color"], frame_id),
                            np.ascontiguousarray(np.asarray(color)[..., ::-1]))
        self._frames_file.write(f"{frame_id},{stamp:.9f}\n")
        self._frames_file.flush()
        self._frame_stamps.append(stamp)
        self._last_frame_id = frame_id

    @staticmethod
    def _write_png(dest: Path, png: np.ndarray) -> None:
        import cv2

        ok, encoded = cv2.imencode(".png", png)
        if not ok:
            raise OSError(f"cannot encode {dest} as PNG")
        tmp = dest.with_name(dest.name + ".tmp")
        wrote(dest)
        wrote(tmp)
        tmp.write_bytes(encoded.tobytes())
        os.replace(tmp, dest)

    def write_joints(self, stamps, q) -> None:
        """Append joint samples: ``stamps`` scalar or (M,) seconds, ``q`` (6,) or (M, 6) radians, finite."""
        self._check_open()
        stamps = np.atleast_1d(np.asarray(stamps, dtype=float))
        q = np.asarray(q, dtype=float)
        q = q[None] if q.ndim == 1 else q
        if stamps.ndim != 1 or q.shape != (len(stamps), 6):
            raise ValueError(f"write_joints: expected stamps (M,) and q (M, 6), got {stamps.shape} and {q.shape}")
        if len(stamps) == 0:
            return
        if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(q))):
            raise ValueError("write_joints: stamps and joint angles must be finite (drop NaN samples before writing)")
        if stamps[0] <= self._last_joint_stamp or np.any(np.diff(stamps) <= 0):
            raise ValueError(f"write_joints: stamps must increase strictly (last written {self._last_joint_stamp!r}, "
                             f"got {stamps[0]!r} .. {stamps[-1]!r})")
        rows = [f"{t:.9f}," + ",".join(repr(float(v)) for v in row) + "\n" for t, row in zip(stamps, q)]
        self._joints_file.write("".join(rows))
        self._joints_file.flush()
        self._last_joint_stamp = float(stamps[-1])

    def write_groundtruth(self, stamp: float, T_base_bone: np.ndarray) -> None:
        """Append the true bone pose (4, 4) in the base frame for the next frame without one (same stamp)."""
        self._check_open()
        k = self._n_groundtruth
        if k >= len(self._frame_stamps):
            raise ValueError(f"write_groundtruth: {k + 1} poses for {len(self._frame_stamps)} frames; "
                             "write the frame first (one pose per frame)")
        if abs(float(stamp) - self._frame_stamps[k]) > 1e-9:
            raise ValueError(f"write_groundtruth: stamp {stamp!r} differs from frame {k}'s {self._frame_stamps[k]!r}")
        if self._gt_file is None:
            wrote(self.path / GROUNDTRUTH_FILE)
            self._gt_file = open(self.path / GROUNDTRUTH_FILE, "w")
            self._gt_file.write(TUM_HEADER + "\n")
        self._gt_file.write(format_tum_row(self._frame_stamps[k], T_base_bone))
        self._gt_file.flush()
        self._n_groundtruth += 1

    # ------------------------------------------------------------ closing

    @property
    def n_frames(self) -> int:
        return len(self._frame_stamps)

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"TrialWriter for {self.path} is closed")

    def _close_files(self) -> None:
        for f in (self._frames_file, self._joints_file, self._gt_file):
            if f is not None and not f.closed:
                f.close()

    def note(self, key: str, value) -> None:
        """Set trial.yaml's top-level ``key`` (one the format does not define: ``TrialMeta.extra``) and
        rewrite trial.yaml atomically; an OSError (a full disk) leaves the earlier trial.yaml."""
        self.meta.extra[key] = value
        dump_meta(self.meta, self.path / META_FILE)

    def close(self, complete: bool = True) -> None:
        """Flush and close the files, then remove the marker: the trial is complete. With
        ``complete=False`` (frames were lost) the marker stays: readers see an interrupted trial."""
        if self._closed:
            return
        self._closed = True
        self._close_files()
        if not complete:
            log.warning("%s: %d frames written, frames were lost: left marked as interrupted", self.path,
                        len(self._frame_stamps))
            return
        if self._gt_file is not None and self._n_groundtruth != len(self._frame_stamps):
            log.warning("%s: %d ground-truth poses for %d frames; readers will reject groundtruth.txt",
                        self.path, self._n_groundtruth, len(self._frame_stamps))
        if self._n_clipped:
            log.warning("%s: %d depth pixels clipped to the PNG's range", self.path, self._n_clipped)
        (self.path / MARKER_FILE).unlink(missing_ok=True)
        log.info("wrote trial %s: %d frames", self.path, len(self._frame_stamps))

    def __enter__(self) -> "TrialWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:  # keep the marker: readers treat what was written as an interrupted trial
            self._closed = True
            self._close_files()
            log.warning("%s: recording stopped by %s after %d frames; left marked as interrupted",
                        self.path, exc_type.__name__, len(self._frame_stamps))
