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


def log_trial(trial_dir: str | Path, save: str | Path | None = None, every: int = 1) -> int:
    """Log the trial at ``trial_dir`` to a .rrd file (``save``) or a spawned viewer; return frames logged."""
    from app.trial.reader import open_trial

    reader = open_trial(trial_dir)
    sink = RerunLog.to_file(save) if save else RerunLog.spawn()
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
