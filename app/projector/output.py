"""Where projector images go: PNG files (headless) or a full-screen window on the projector's display.

- :class:`PngWriter`: ``DIR/projector_000123.png``, one file per frame id (headless, replay).
- :class:`ProjectorWindow`: a borderless full-screen window on a chosen screen, drawn with pyglet
  (imported only when a window is opened: ``pip install "pyglet>=2,<3"``). It has a **watchdog**:
  an image older than ``max_age_s`` of wall-clock time is replaced by the warning pattern, so a
  stalled pipeline never leaves a stale template on the bone.

The window cannot be tested without a display; opening it without pyglet or without a display
raises :class:`app.errors.GLError` with the fix.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from app.errors import GLError
from app.projector.view import MAX_AGE_S, warning_pattern

log = logging.getLogger(__name__)


class PngWriter:
    """Writes projector images as PNG files into a folder (created)."""

    def __init__(self, folder: "str | Path", prefix: str = "projector"):
        from app.outputs import wrote

        self.folder = Path(folder)
        wrote(self.folder, folder=True)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.prefix = prefix
        self.count = 0

    def write(self, frame_id: int, image: np.ndarray) -> Path:
        """Write (H, W, 3) or (H, W) uint8 ``image`` as ``<prefix>_<frame_id:06d>.png``; returns the path."""
        from PIL import Image

        from app.outputs import wrote

        path = self.folder / f"{self.prefix}_{int(frame_id):06d}.png"
        wrote(path)
        Image.fromarray(np.asarray(image, dtype=np.uint8)).save(path)
        self.count += 1
        return path


def _import_pyglet():
    try:
        import pyglet
    except ImportError as exc:
        raise GLError("the projector window needs pyglet: pip install 'pyglet>=2,<3' (or write the images "
                      "headless: 'window: false' with 'png_dir: DIR' in the session's projector output, or "
                      "osteonav replay TRIAL --out DIR --projector-images)") from exc
    return pyglet


class ProjectorWindow:
    """Full-screen window on screen ``screen`` showing the latest projector image.

    Call :meth:`show` with each new image and :meth:`poll` often (it dispatches window events and
    redraws; the watchdog blanks to the warning pattern when no image came for ``max_age_s``).
    Only the thread that created the window may use it.
    """

    def __init__(self, screen: int = -1, max_age_s: float = MAX_AGE_S, fullscreen: bool = True):
        pyglet = _import_pyglet()
        try:
            screens = pyglet.display.get_display().get_screens()
        except Exception as exc:  # pyglet raises several types when there is no display server
            raise GLError(f"no display for the projector window ({exc}); run headless instead") from exc
        if not screens:
            raise GLError("no screen found for the projector window")
        if not -len(screens) <= screen < len(screens):
            raise GLError(f"screen {screen} does not exist; {len(screens)} screens found (0..{len(screens) - 1})")
        self._pyglet = pyglet
        target = screens[screen]
        self.window = pyglet.window.Window(fullscreen=fullscreen, screen=target, caption="osteonav projector")
        self.window.set_mouse_visible(False)
        self.max_age_s = float(max_age_s)
        self._image: np.ndarray | None = None
        self._shown_at = -np.inf
        self._sprite = None
        self.window.on_draw = self._on_draw

    def show(self, image: np.ndarray) -> None:
        """Display (H, W, 3) uint8 ``image`` (row 0 at the top) from now on."""
        self._image = np.ascontiguousarray(image, dtype=np.uint8)
        self._shown_at = time.monotonic()
        self.poll()

    def current_image(self) -> np.ndarray:
        """What the window shows now: the latest image, or the warning pattern once it is too old."""
        w, h = self.window.width, self.window.height
        if self._image is None or time.monotonic() - self._shown_at > self.max_age_s:
            return warning_pattern(w, h, "NO IMAGE FROM THE TRACKER")
        return self._image

    def poll(self) -> None:
        self.window.switch_to()
        self.window.dispatch_events()
        self._on_draw()
        self.window.flip()

    def _on_draw(self) -> None:
        pyglet = self._pyglet
        img = self.current_image()
        h, w = img.shape[:2]
        data = pyglet.image.ImageData(w, h, "RGB", img[::-1].tobytes())  # pyglet's rows start at the bottom
        self.window.clear()
        data.blit(0, 0, width=self.window.width, height=self.window.height)

    def close(self) -> None:
        self.window.close()
