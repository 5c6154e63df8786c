"""The simulated operating-room scene: bone, soft tissue, table, robot motion, occluders.

Frames: the robot base frame (z up) holds the table and the patient; the bone frame is the mesh's
own frame; soft tissue is built in the bone frame and moves with it. The camera rides on the UR5e
flange through ``T_flange_camera``. The robot's joints follow smooth sinusoids around ``q0`` so the
camera sweeps a few centimetres while keeping the bone in view; the bone is placed 0.42 m in front
of the camera's start pose, crest towards the lens.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from app.geometry import quaternion as quat
from app.geometry import se3
from app.geometry.ur import DHParameters, forward_kinematics

# UR5e joint configuration with the flange pointing down over the table (radians).
Q0_UR5E = np.array([0.0, -1.75, 1.9, -1.72, -1.5708, 0.0])
JOINT_AMPLITUDE = np.array([0.05, 0.035, 0.04, 0.05, 0.05, 0.08])   # rad
JOINT_FREQUENCY = np.array([0.11, 0.17, 0.13, 0.19, 0.15, 0.09])    # Hz
JOINT_PHASE = np.array([0.0, 1.1, 2.3, 0.7, 1.9, 2.9])
T_FLANGE_CAMERA = np.array([
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.05],
    [0.0, 0.0, 1.0, 0.03],
    [0.0, 0.0, 0.0, 1.0],
])
CAMERA_TO_BONE_M = 0.42
TISSUE_PROTRUSION_M = 0.010   # how far the crest stands out of the soft tissue
TISSUE_SLOPE = 0.6            # m of drop per m of horizontal distance from the crest


def minimum_jerk(tau: np.ndarray) -> np.ndarray:
    """s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 on [0, 1], clamped outside (peak speed 1.875)."""
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2)


def joint_trajectory(t: np.ndarray, q0: np.ndarray = Q0_UR5E) -> np.ndarray:
    """Joint angles (K, 6) at times ``t`` (K,), radians: q0 + A sin(2 pi f t + phi)."""
    t = np.asarray(t, dtype=float)[:, None]
    return q0 + JOINT_AMPLITUDE * np.sin(2.0 * np.pi * JOINT_FREQUENCY * t + JOINT_PHASE)


def initial_bone_pose(dh: DHParameters, T_flange_camera: np.ndarray, rng: np.random.Generator,
                      distance_m: float = CAMERA_TO_BONE_M, yaw_deg: float = 0.0) -> np.ndarray:
    """T_base_bone at t = 0: ``distance_m`` in front of the camera, bone z (crest up) towards the lens,
    turned ``yaw_deg`` about bone z (180: seen from the other side), tilted a little."""
    T_base_camera = forward_kinematics(dh, joint_trajectory(np.zeros(1))[0]) @ T_flange_camera
    z_camera = T_base_camera[:3, 2]
    p_base_bone = T_base_camera[:3, 3] + distance_m * z_camera
    # bone z axis opposite the optical axis; bone x roughly along the camera's x
    z_bone = -z_camera
    x_bone = T_base_camera[:3, 0] - z_bone * (T_base_camera[:3, 0] @ z_bone)
    x_bone /= np.linalg.norm(x_bone)
    R = np.column_stack([x_bone, np.cross(z_bone, x_bone), z_bone])
    R = R @ quat.to_matrix(quat.exp_map(np.array([0.0, 0.0, np.deg2rad(yaw_deg)])))
    tilt = quat.to_matrix(quat.exp_map(rng.normal(0.0, np.deg2rad(8.0), 3)))
    return se3.make_pose(R @ tilt, p_base_bone)


def bone_trajectory(t: np.ndarray, T_base_bone0: np.ndarray, moves) -> np.ndarray:
    """T_base_bone (K, 4, 4) at times ``t`` under minimum-jerk moves (start, duration, dp, rotvec)."""
    t = np.asarray(t, dtype=float)
    dp = np.zeros((len(t), 3))
    R = np.broadcast_to(np.eye(3), (len(t), 3, 3)).copy()
    for start, duration, translation, rotvec in moves:
        s = minimum_jerk((t - start) / duration)[:, None]
        dp += s * np.asarray(translation)
        R = quat.to_matrix(quat.exp_map(s * np.asarray(rotvec))) @ R
    T = np.broadcast_to(np.eye(4), (len(t), 4, 4)).copy()
    T[:, :3, :3] = R @ T_base_bone0[:3, :3]
    T[:, :3, 3] = T_base_bone0[:3, 3] + dp
    return T


def soft_tissue_mesh(bone: trimesh.Trimesh, rng: np.random.Generator, margin: float = 0.06,
                     resolution: float = 0.003, protrusion: float = TISSUE_PROTRUSION_M) -> trimesh.Trimesh:
    """A heightfield of soft tissue in the bone frame from which only the crest's top protrudes.

    Height at (x, y): max over bone surface samples of z_i - protrusion - slope * |xy - xy_i|
    (a tent envelope just below the crest, falling away from it), floored at the bone's lowest z.
    """
    samples, _ = trimesh.sample.sample_surface(bone, 4000, seed=int(rng.integers(1 << 31)))
    lo, hi = bone.bounds
    xs = np.arange(lo[0] - margin, hi[0] + margin + resolution, resolution)
    ys = np.arange(lo[1] - margin, hi[1] + margin + resolution, resolution)
    gx, gy = np.meshgrid(xs, ys)
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    height = np.full(len(grid), lo[2] - 0.01)
    for chunk in np.array_split(np.arange(len(samples)), 8):
        d = np.linalg.norm(grid[:, None, :] - samples[None, chunk, :2], axis=2)
        height = np.maximum(height, (samples[chunk, 2][None, :] - protrusion - TISSUE_SLOPE * d).max(axis=1))
    vertices = np.column_stack([grid, height])
    ny, nx = gx.shape
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    return trimesh.Trimesh(vertices, faces, process=False)


def table_mesh(size: float = 2.0) -> trimesh.Trimesh:
    """A square table top (z = 0 plane of its own frame)."""
    h = size / 2
    v = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], dtype=float)
    return trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)


def hand_mesh() -> trimesh.Trimesh:
    """A flat hand-like occluder: a rounded box 20 x 12 x 3 cm (camera-aligned when placed)."""
    box = trimesh.creation.box(extents=(0.20, 0.12, 0.03))
    return box.subdivide().subdivide()


def instrument_mesh() -> trimesh.Trimesh:
    """A surgical instrument: a cylinder 8 mm in diameter, 22 cm long, along its own x axis."""
    cyl = trimesh.creation.cylinder(radius=0.004, height=0.22, sections=24)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    return cyl


@dataclass
class Occluders:
    """Poses of the occluders in the camera frame for one frame (None = not in the scene)."""

    T_camera_hand: np.ndarray | None
    T_camera_instrument: np.ndarray | None


def hand_pose_for_fraction(u_edge: float, v_centre: float, fx: float, fy: float, cx: float, cy: float,
                           depth: float = 0.30, half_thickness: float = 0.015) -> np.ndarray:
    """T_camera_hand with the hand's silhouette edge on image column ``u_edge``, centred at ``depth`` m.

    The box's right face spans depths ``depth +- half_thickness``; its silhouette is the face's
    nearer edge when it lies right of the optical axis (x > 0 projects further out when closer)
    and the farther edge otherwise, so the edge is placed at that depth.
    """
    x_near = (u_edge - cx) * (depth - half_thickness) / fx
    x_edge = x_near if x_near > 0 else (u_edge - cx) * (depth + half_thickness) / fx
    y_c = (v_centre - cy) * depth / fy
    T = np.eye(4)
    T[:3, 3] = (x_edge - 0.10, y_c, depth)
    return T


def instrument_pose(t: float, depth: float = 0.33) -> np.ndarray:
    """T_camera_instrument: sweeps diagonally across the view with a period of 4 s."""
    phase = (t % 4.0) / 4.0
    T = np.eye(4)
    angle = 0.6
    T[:3, :3] = quat.to_matrix(quat.exp_map(np.array([0.0, 0.0, angle])))
    T[:3, 3] = (-0.12 + 0.24 * phase, 0.04 * np.sin(2 * np.pi * phase), depth)
    return T
