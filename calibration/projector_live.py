"""Live projector calibration capture: the Gray-code sequence shown in the projector window, each
pattern's camera image recorded, into the capture folder of :mod:`calibration.projector`.

For each board pose (the operator places the board, or moves the robot carrying camera and
projector, and presses Enter; or, with ``auto``, when the white-lit board is seen and its corners
stand still), :class:`PatternSequencer` shows every pattern of :func:`calibration.graycode.patterns`
in order and keeps, for each, the first camera frame stamped at least ``latency_s`` after the
pattern was shown plus ``settle_frames`` more frames (a projector and a camera exposure are not
instantaneous; a frame that straddles two patterns would decode wrong). The board must not move
during a sequence: the white frame shown again at the end must find its corners where the first
one did (``still_px``), else the pose is discarded and said so.

Sources are small protocols so that the same code runs on the projector window + a session camera
and on the simulated rig of the tests:

- ``display.show(image (ph, pw) or (ph, pw, 3) uint8) -> float``: show it from now on; returns the
  host time it was shown (``ProjectorWindow`` for the real projector: :class:`WindowDisplay`);
- ``next_frame() -> (stamp, grey image (H, W) uint8)``: the camera's next frame (blocking).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from calibration.graycode import patterns
from app.outputs import wrote

log = logging.getLogger(__name__)


class PatternSequencer:
    """Show the Gray-code patterns one by one and record the camera image of each (module docstring)."""

    def __init__(self, display, next_frame, projector_size: tuple[int, int], latency_s: float = 0.1,
                 settle_frames: int = 1, detector=None, still_px: float = 1.0):
        self.display, self.next_frame = display, next_frame
        self.patterns = patterns(*projector_size)
        self.latency_s, self.settle_frames = float(latency_s), int(settle_frames)
        self.detector, self.still_px = detector, float(still_px)

    def _image_after(self, shown_at: float) -> np.ndarray:
        while True:
            stamp, image = self.next_frame()
            if stamp >= shown_at + self.latency_s:
                break
        for _ in range(self.settle_frames):
            stamp, image = self.next_frame()
        return image

    def capture_pose(self) -> tuple[np.ndarray | None, str]:
        """(P, H, W) uint8 images in pattern order, or (None, why the pose was discarded)."""
        stack = [self._image_after(self.display.show(p)) for p in self.patterns]
        white_again = self._image_after(self.display.show(self.patterns[0]))
        self.display.show(self.patterns[0])
        if self.detector is not None:
            from calibration.live import corners_still

            first, _ = self.detector.detect(stack[0])
            last, _ = self.detector.detect(white_again)
            if first is None:
                return None, "no board in the white-lit image"
            if not corners_still(first, last, self.still_px):
                return None, "the board (or the rig) moved during the sequence"
        return np.stack(stack), ""


def capture_poses(sequencer: PatternSequencer, out: str | Path, poses: int, wait_for_pose, projector_size,
                  board: str, camera_intrinsics, report=print) -> int:
    """Record ``poses`` board poses into the capture folder ``out``; returns how many were kept.

    wait_for_pose(k) -> bool : blocks until pose k is placed (False stops early).
    """
    import yaml
    from PIL import Image

    from calibration.board import parse_board_spec
    from calibration.intrinsics import write_camera_yaml

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    kept = 0
    meta = {"projector": {"width": int(projector_size[0]), "height": int(projector_size[1])},
            "board": parse_board_spec(board).to_string(), "poses": 0, "order": "gray-code"}
    write_camera_yaml(out / "camera.yaml", camera_intrinsics, {"source": "the session camera"})
    attempt = 0
    while kept < poses and wait_for_pose(kept):
        stack, why = sequencer.capture_pose()
        attempt += 1
        if stack is None:
            report(f"pose attempt {attempt} discarded: {why}; place the board again")
            continue
        folder = out / f"pose_{kept:03d}"
        wrote(folder, folder=True)
        folder.mkdir(exist_ok=True)
        for i, image in enumerate(stack):
            wrote(folder / f"pattern_{i:03d}.png")
            Image.fromarray(image).save(folder / f"pattern_{i:03d}.png", compress_level=1)
        kept += 1
        meta["poses"] = kept
        wrote(out / "projector_capture.yaml")
        (out / "projector_capture.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
        report(f"pose {kept}/{poses}: {len(stack)} pattern images")
    return kept


class WindowDisplay:
    """The projector's full-screen window (:class:`app.projector.output.ProjectorWindow`) as a display.

    The window's watchdog is set far beyond a sequence's length: a pattern stays up until the next.
    """

    def __init__(self, screen: int = -1):
        import time

        from app.projector.output import ProjectorWindow

        self._time = time
        self.window = ProjectorWindow(screen=screen, max_age_s=3600.0)

    def show(self, image: np.ndarray) -> float:
        rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
        self.window.show(rgb)
        return self._time.monotonic()

    def poll(self) -> None:
        self.window.poll()

    def close(self) -> None:
        self.window.close()


class SimulatedProjectorRig:
    """A simulated camera + projector looking at a board (:class:`calibration.projector.ProjectorSimulation`).

    ``show`` changes what the projector casts; ``next_frame`` renders the camera image of the board
    at the current pose under the pattern shown at least ``latency_s`` before the frame (frames
    every ``1 / fps`` s of simulated time, which is also the ``stamp``: nothing here waits).
    ``place(k)`` moves the board to pose k.
    """

    def __init__(self, sim, board_poses: list[np.ndarray], rng: np.random.Generator, fps: float = 30.0,
                 latency_s: float = 0.05):
        self.sim, self.poses, self.rng = sim, board_poses, rng
        self.fps, self.latency_s = float(fps), float(latency_s)
        self.t = 0.0
        self.shown: list[tuple[float, np.ndarray]] = [(-1.0, np.zeros(sim.projector_size[::-1], np.uint8))]
        self._render = None

    def place(self, k: int) -> bool:
        if k >= len(self.poses):
            return False
        self._render = self.sim.pattern_renderer(self.poses[k])
        return True

    def show(self, image: np.ndarray) -> float:
        self.shown.append((self.t, np.asarray(image)))
        return self.t

    def next_frame(self) -> tuple[float, np.ndarray]:
        self.t += 1.0 / self.fps
        lit = [img for t, img in self.shown if t <= self.t - self.latency_s][-1]   # what the projector casts now
        return self.t, self._render(lit, self.rng)


def run_live_projector_capture(session: str | Path, out: str | Path, poses: int, screen: int = -1, which: str = "ir",
                               board: str | None = None, report=print) -> int:
    """``osteonav calibrate projector --live``: the session's camera, the projector window on ``screen``,
    Enter on the terminal for each board pose. Needs a display (pyglet); not exercised by the tests,
    which run :func:`capture_poses` on :class:`SimulatedProjectorRig` instead."""
    import sys

    from app.interfaces import DropOldestQueue, SessionClock
    from app.session import load_session
    from calibration.board import DEFAULT_BOARD_SPEC, BoardDetector
    from calibration.live_session import _check_stream, _image_of, _intrinsics, _open_sources

    config = load_session(session, {"tracker": False, "outputs": [], "record": None, "out": None})
    camera, robot, camera_model = _open_sources(config, SessionClock())
    streams = camera.session_defaults().get("image_streams")
    _check_stream(which, streams, str(session))
    display = WindowDisplay(screen)
    frames = DropOldestQueue(8)
    camera.start(frames.put)

    def next_frame():
        while True:
            display.poll()
            frame = frames.get(timeout=0.05)
            image = None if frame is None else _image_of(frame, which)
            if image is not None:
                return frame.stamp, image

    def wait_for_pose(k: int) -> bool:
        report(f"place the board for pose {k + 1}/{poses} in the projector's light and press Enter (q + Enter stops)")
        line = sys.stdin.readline()
        return bool(line) and line.strip().lower() != "q"

    size = (display.window.window.width, display.window.window.height)
    spec = board or DEFAULT_BOARD_SPEC
    sequencer = PatternSequencer(display, next_frame, size, detector=BoardDetector(spec))
    try:
        return capture_poses(sequencer, out, poses, wait_for_pose, size, spec, _intrinsics(which, camera_model, streams),
                             report=report)
    finally:
        camera.stop()
        display.close()
