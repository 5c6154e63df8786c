"""Rerun logging of the marker + IMU tracker (``tracker: marker_imu``).

Import as ``from app.marker.rerun_log import MarkerRerunLog``.

Entities (under ``marker/``, beside the session's ``world/`` and ``plots/``):

- ``marker/image``: the grey camera image (``rr.Image``), with ``marker/image/roi`` the searched
  region (``rr.Boxes2D``, x0 y0 x1 y1 in pixels; cleared when the whole image was searched) and
  ``marker/image/corners`` the detected corners as a closed ``rr.LineStrips2D`` (cleared when not
  found); the image is logged every ``image_every``-th call (the boxes every call);
- ``marker/orientation/{fused,marker,imu}``: ``rr.Transform3D`` rotations (quaternions as xyzw at
  this boundary): the fused R_C_M, the detection's R_C_M, the IMU's R_W_M = R_W_S X;
- ``plots/marker/{inclination_deg,anteversion_deg}`` scalars, and ``plots/marker/path``
  (0 roi, 1 full, 2 none) with the path as text in ``plots/marker/path_text``.

The recording: a path (its own ``.rrd`` file), or the active one (``rr.get_data_recording()``:
the thread's or the global recording) when there is one. :func:`open_log` returns None when
there is none, or when rerun cannot be set up: logging never fails the session (errors while
logging are logged once and turn logging off).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from app.geometry import quaternion as quat

log = logging.getLogger(__name__)

ROOT = "marker"
IMAGE = "marker/image"
ROI = "marker/image/roi"
CORNERS = "marker/image/corners"
ORIENTATION = "marker/orientation"
PLOTS = "plots/marker"
PATH_CODE = {"roi": 0, "full": 1, "none": 2}


def open_log(target, image_every: int = 1) -> "MarkerRerunLog | None":
    """A logger for ``target``: a path (str/Path: a new ``.rrd`` file), 'auto' or True (the active
    recording, if any), or None/False/'off' (no logging). None when there is nothing to log to."""
    if target is None or target is False or (isinstance(target, str) and target.lower() in ("off", "none", "")):
        return None
    try:
        import rerun as rr

        if target is True or (isinstance(target, str) and target.lower() == "auto"):
            rec = rr.get_data_recording()
            if rec is None:
                log.debug("no active rerun recording: the marker tracker does not log to rerun")
                return None
            return MarkerRerunLog(rec, owned=False, image_every=image_every)
        rec = rr.RecordingStream("osteonav")
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(target))
        return MarkerRerunLog(rec, owned=True, image_every=image_every)
    except Exception as exc:   # rerun missing or a sink that cannot be opened: track without logging
        log.warning("marker tracker: no rerun logging (%s: %s)", type(exc).__name__, exc)
        return None


def _rotation(R: np.ndarray):
    import rerun as rr

    return rr.Transform3D(quaternion=rr.Quaternion(xyzw=quat.to_xyzw(quat.from_matrix(np.asarray(R, float)))))


class MarkerRerunLog:
    """One recording stream; :meth:`log_step` per processed image."""

    def __init__(self, recording, owned: bool = False, image_every: int = 1):
        self.rec, self.owned, self.image_every = recording, owned, max(int(image_every), 1)
        self._n = 0
        self.enabled = True

    def log_step(self, stamp: float, gray: np.ndarray | None, path: str, roi=None, corners=None,
                 q_C_M_fused=None, q_C_M_marker=None, R_W_M_imu=None, inclination=None, anteversion=None,
                 frame_id: int | None = None) -> None:
        """Log one step. stamp : s (timeline ``stamp``); gray : (H, W) uint8; path : 'roi'|'full'|'none';
        roi : (x0, y0, x1, y1) px or None; corners : (4, 2) px or None; q_* : (4,) (w, x, y, z) or None;
        R_W_M_imu : (3, 3) or None; inclination, anteversion : radians or None."""
        if not self.enabled:
            return
        try:
            self._log(stamp, gray, path, roi, corners, q_C_M_fused, q_C_M_marker, R_W_M_imu, inclination,
                      anteversion, frame_id)
        except Exception as exc:
            log.warning("marker tracker: rerun logging failed, turned off (%s: %s)", type(exc).__name__, exc)
            self.enabled = False
        self._n += 1

    def _log(self, stamp, gray, path, roi, corners, q_fused, q_marker, R_W_M_imu, inclination, anteversion,
             frame_id) -> None:
        import rerun as rr

        rec = self.rec
        rec.set_time("stamp", duration=float(stamp))
        if frame_id is not None:
            rec.set_time("frame", sequence=int(frame_id))
        if gray is not None and self._n % self.image_every == 0:
            rec.log(IMAGE, rr.Image(np.asarray(gray)))
        if roi is not None:
            x0, y0, x1, y1 = (float(v) for v in roi)
            rec.log(ROI, rr.Boxes2D(array=[[x0, y0, x1, y1]], array_format=rr.Box2DFormat.XYXY,
                                    colors=(255, 200, 0), labels="search region"))
        else:
            rec.log(ROI, rr.Clear(recursive=False))
        if corners is not None:
            c = np.asarray(corners, float).reshape(4, 2)
            rec.log(CORNERS, rr.LineStrips2D([np.vstack([c, c[:1]])], colors=(0, 255, 120), labels=path))
        else:
            rec.log(CORNERS, rr.Clear(recursive=False))
        for name, R in (("fused", None if q_fused is None else quat.to_matrix(q_fused)),
                        ("marker", None if q_marker is None else quat.to_matrix(q_marker)),
                        ("imu", R_W_M_imu)):
            if R is not None:
                rec.log(f"{ORIENTATION}/{name}", _rotation(R))
        rec.log(f"{PLOTS}/path", rr.Scalars(float(PATH_CODE.get(path, 2))))
        rec.log(f"{PLOTS}/path_text", rr.TextLog(path))
        for name, value in (("inclination_deg", inclination), ("anteversion_deg", anteversion)):
            if value is not None and np.isfinite(value):
                rec.log(f"{PLOTS}/{name}", rr.Scalars(float(np.rad2deg(value))))

    def close(self) -> None:
        """Flush; a recording this logger opened (a file) is also disconnected."""
        try:
            self.rec.flush()
            if self.owned:
                self.rec.disconnect()
        except Exception as exc:
            log.warning("marker tracker: closing the rerun recording failed (%s: %s)", type(exc).__name__, exc)
