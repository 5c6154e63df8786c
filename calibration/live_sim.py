"""A simulated live calibration rig: a robot that rests at planned poses, and what its camera records.

:class:`RestMoveTrajectory` holds the joints at each planned configuration for ``rest_s`` and moves
between consecutive ones in ``move_s`` with a minimum-jerk profile
(``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5``, Flash & Hogan 1985), as an operator jogging the
robot from view to view would. Called with an ``anchor`` it is a function of the host's monotonic
clock (``q(time.monotonic() - anchor)``), the same in every process: the RTDE test server
(``plugins.rtde_server``, a child process) then plays it in step with a RealSense recording played
through a session clock whose replay anchor is ``anchor``.

:func:`write_ir_recording` renders the board (:class:`calibration.simulator.BoardRenderer`) in the
left imager at every frame of the trajectory and writes depth + infrared (emitter off) with the
RealSense SDK's software device (:func:`plugins.realsense.write_recording`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class RestMoveTrajectory:
    q_plan: np.ndarray          # (N, 6) rad
    rest_s: float = 1.2
    move_s: float = 0.6
    anchor: float | None = None  # host monotonic time of trajectory time 0 (for the RTDE server)

    @property
    def duration(self) -> float:
        return len(self.q_plan) * self.rest_s + (len(self.q_plan) - 1) * self.move_s

    def at(self, s: float) -> np.ndarray:
        """Joint angles (6,) at trajectory time ``s`` (held before 0 and after the end)."""
        period = self.rest_s + self.move_s
        s = float(np.clip(s, 0.0, self.duration))
        k = min(int(s // period), len(self.q_plan) - 1)
        local = s - k * period
        if local <= self.rest_s or k + 1 >= len(self.q_plan):
            return np.array(self.q_plan[k], dtype=float)
        tau = (local - self.rest_s) / self.move_s
        blend = 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5
        return (1 - blend) * self.q_plan[k] + blend * self.q_plan[k + 1]

    def __call__(self, controller_t: float) -> np.ndarray:
        """The RTDE server's ``joints(t)``: by the host clock when anchored, else by the controller's."""
        return self.at(time.monotonic() - self.anchor if self.anchor is not None else controller_t)


def write_ir_recording(path: str | Path, scene, trajectory: RestMoveTrajectory, fps: int = 15,
                       rng: np.random.Generator | None = None) -> tuple[Path, np.ndarray]:
    """Render the board at every frame of ``trajectory`` and write a RealSense recording (depth + IR).

    Frame k has stamp k / fps (s, trajectory time). Returns (path, stamps).
    """
    from app.geometry.camera import PinholeCamera
    from calibration.simulator import BoardRenderer
    from plugins.realsense import write_recording

    cfg = scene.config
    renderer = BoardRenderer(cfg)
    stamps = np.arange(0.0, trajectory.duration + 0.5 / fps, 1.0 / fps)
    ir = np.stack([renderer.render(scene.T_camera_board(trajectory.at(s)), rng) for s in stamps])
    depth = np.full((len(stamps), cfg.height, cfg.width), 4500, np.uint16)   # 0.45 m: the board's distance
    camera = PinholeCamera(cfg.K, cfg.width, cfg.height)
    return write_recording(path, depth, stamps, camera, 1e-4, fps=fps, infrared=ir, emitter=False), stamps
