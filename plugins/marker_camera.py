"""The marker simulator's camera as a session camera (``camera: marker_simulated``).

Publication C's grey camera looking at the ArUco box (:class:`app.marker.simulator.MarkerSimulator`,
the same scene, seed and rendering as ``osteonav bench-marker``) delivered as the session's camera
frames: each frame's ``infrared`` is the simulator's 8-bit image at its time (an IR imager with the
emitter off), ``depth_m`` is empty (zeros: no measurement; the marker tracker does not use depth),
at ``camera_fps``. Frame k has simulation time k / fps, pushed at the host time the session's
replay anchor gives it, so ``tracker: marker_imu`` with ``images: ir`` reads the camera's images
like on a real rig while its simulated IMU runs on the same time.
"""
from __future__ import annotations

import numpy as np

from app.geometry.camera import PinholeCamera
from app.image_streams import ImageStreams, InfraredStream
from app.interfaces import DepthFrame, SessionClock
from plugins._base import ThreadedSource


class MarkerSimulatedCamera(ThreadedSource):
    kind, name = "camera", "marker_simulated"

    def __init__(self, seconds: float = 30.0, seed: int = 0, dictionary: str = "DICT_4X4_50", marker_id: int = 7,
                 marker_length_m: float = 0.04, camera_fps: float = 10.0):
        from app.marker.simulator import MarkerScenario, MarkerSimulator

        super().__init__()
        self.sim = MarkerSimulator(MarkerScenario(seconds=600.0, seed=seed, dictionary=dictionary, marker_id=marker_id,
                                                  marker_length_m=marker_length_m, camera_fps=camera_fps))
        self.seconds, self.fps = float(seconds), float(camera_fps)
        self.rng = np.random.default_rng(seed)
        sc = self.sim.sc
        self.camera = PinholeCamera(self.sim.K, sc.width, sc.height)

    def open(self, clock: SessionClock, event) -> PinholeCamera:
        self._bind(clock, event)
        return self.camera

    def session_defaults(self) -> dict:
        return {"camera": self.camera, "image_streams": ImageStreams(InfraredStream(emitter=False))}

    def _run(self) -> None:
        empty = np.zeros((self.camera.height, self.camera.width), np.float32)
        for k in range(int(self.seconds * self.fps)):
            t = k / self.fps
            host_t = float(self.clock.replay_to_host(t, 0.0))
            if not self._sleep_until(host_t):
                return
            image = self.sim.image(min(t, self.sim.sc.seconds - 1.0), self.rng)
            self._push(DepthFrame(k, host_t, empty, self.clock.now(), infrared=image))
        self._event("end", f"end of the simulated marker sequence ({self.seconds:.1f} s)")
        self.finished.set()
