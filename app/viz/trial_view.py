"""Log a whole recorded trial to rerun (what ``osteonav view`` shows)."""
from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np

from app.geometry.ur import forward_kinematics
from app.viz.rerun_log import RerunLog

log = logging.getLogger(__name__)


def read_occlusion(trial_dir: Path) -> dict[int, float]:
    """Frame -> occlusion fraction from a simulator's ``simulation.csv`` (empty if absent)."""
    path = Path(trial_dir) / "simulation.csv"
    if not path.exists():
        return {}
    with open(path) as f:
        return {int(row["frame"]): float(row["occlusion"]) for row in csv.DictReader(f)}


def viewer_executable() -> Path:
    """The rerun viewer to spawn: on PATH, else beside this Python (a venv's bin). OsteonavError when
    there is none, or no display to show it on (no DISPLAY / WAYLAND_DISPLAY on Linux), naming --rrd."""
    import os
    import shutil
    import sys

    from app.errors import OsteonavError

    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise OsteonavError("no display (DISPLAY and WAYLAND_DISPLAY are unset), so the viewer cannot open here; "
                            "write a recording instead: osteonav view TRIAL --rrd trial.rrd")
    found = shutil.which("rerun")
    beside = Path(sys.executable).parent / "rerun"
    if found is None and not beside.is_file():
        raise OsteonavError(f"the rerun viewer was not found (not on PATH, not in {beside.parent}); install rerun-sdk "
                            f"or write a recording instead: osteonav view TRIAL --rrd trial.rrd")
    return Path(found) if found else beside


VIEWER_START_S = 3.0
"""A viewer still running this long after its start is taken as up (one without a display exits at once)."""


def _spawn(port: int = 9876, start_s: float = VIEWER_START_S) -> RerunLog:
    """A recording streamed to a newly started viewer (:func:`viewer_executable`).

    The viewer is started here rather than by ``rr.spawn`` so that one that exits at once (no usable
    display) is an error with the fix, not a logger blocking on a connection that never comes.
    """
    import socket
    import subprocess
    import tempfile
    import time

    import rerun as rr

    from app.errors import OsteonavError
    from app.viz.rerun_log import blueprint

    url = f"rerun+http://127.0.0.1:{port}/proxy"
    with socket.socket() as probe:   # a viewer already listening: log to it, as rr.spawn would
        probe.settimeout(0.5)
        if probe.connect_ex(("127.0.0.1", port)) == 0:
            rec = rr.RecordingStream("osteonav")
            rec.connect_grpc(url, default_blueprint=blueprint())
            return RerunLog(rec)
    with tempfile.TemporaryFile() as log_file:   # a file, not a pipe: the viewer may write after we stop reading
        proc = subprocess.Popen([str(viewer_executable()), "--port", str(port)], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=log_file, start_new_session=True)
        deadline = time.monotonic() + start_s
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        if proc.returncode is not None:
            log_file.seek(0)
            lines = log_file.read().decode(errors="replace").strip().splitlines() or ["(no message)"]
            reason = lines[-1].rsplit(": ", 1)[-1][:160]   # the viewer's last message, without its source path
            raise OsteonavError(f"the rerun viewer exited at once (code {proc.returncode}: {reason}); "
                                f"without a usable display write a recording instead: osteonav view TRIAL --rrd "
                                f"trial.rrd")
    rec = rr.RecordingStream("osteonav")
    rec.connect_grpc(url, default_blueprint=blueprint())
    return RerunLog(rec)


def log_trial(trial_dir: str | Path, save: str | Path | None = None, every: int = 1) -> int:
    """Log the trial at ``trial_dir`` to a .rrd file (``save``) or a spawned viewer; return frames logged."""
    from app.trial.reader import open_trial

    reader = open_trial(trial_dir)
    sink = RerunLog.to_file(save) if save else _spawn()
    mesh = reader.load_mesh()
    sink.log_static_scene(reader.meta.camera, np.asarray(mesh.vertices), np.asarray(mesh.faces),
                          with_groundtruth=reader.groundtruth is not None)
    sink.log_image_streams(reader.meta.streams)
    T_base_camera, valid = reader.camera_poses()
    q_joints = reader.joints
    T_base_flange_path = forward_kinematics(reader.meta.dh, q_joints[:: max(1, len(q_joints) // 2000)])
    sink.log_flange_path(T_base_flange_path[:, :3, 3])
    occlusion = read_occlusion(Path(trial_dir))
    T_flange_camera = reader.meta.T_flange_camera
    T_camera_flange = np.linalg.inv(T_flange_camera)
    n = 0
    for frame in reader.iter_frames():
        i = frame.index
        sink.set_frame(frame.frame_id, frame.stamp)
        pose_ok = bool(valid[i])
        depth = frame.depth_m if i % every == 0 else None
        sink.log_camera(T_base_camera[i] @ T_camera_flange if pose_ok else None,
                        T_base_camera[i] if pose_ok else None, depth)
        if depth is not None:
            sink.log_images(frame.infrared, frame.color)
        if reader.groundtruth is not None:
            sink.log_bone("groundtruth", reader.groundtruth[i])
        if frame.frame_id in occlusion:
            sink.log_scalar("occlusion", occlusion[frame.frame_id])
        n += 1
    sink.close()
    return n
