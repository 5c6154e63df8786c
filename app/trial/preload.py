"""A trial's first frames decoded once, ahead of a real-time player, within a memory budget.

A live camera hands the host frames it has already made: the RealSense computes depth on the
device, and the host copies it. A recorded trial played as a live camera (plugins/trial_player.py)
instead decodes one depth PNG per frame: about 4 ms of a core at 640x480, so at 90 frames/s close
to half of one of the sandbox's two cores, taken from the tracker it feeds (BENCHMARKS.md,
"The live session"). :func:`preload` decodes the frames once, before the session's clock starts,
into memory as stored (uint16 depth, uint8 images) and the player then converts a frame per push
(the same :func:`app.trial.writer.png_to_depth`, so a played frame is bit-identical to a read
one). Only as many frames as fit ``budget_mb`` are kept, from the first; the others are decoded
when played, as before. A frame that cannot be read ends the preload there: the player meets the
same error at that frame, when it is due, as it would without one (nothing is raised earlier).

Usage::

    reader = preload(open_trial(path), budget_mb=512)    # .count frames in memory, .megabytes
    depth_m = reader.read_depth(i)                        # same array values as the trial's reader
"""
from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from app.trial.writer import png_to_depth

log = logging.getLogger(__name__)


def frame_bytes(meta) -> int:
    """Bytes one frame takes as stored: uint16 depth, uint8 infrared, uint8 RGB colour when present."""
    n = 2 * meta.camera.width * meta.camera.height
    if meta.streams.infrared is not None:
        n += meta.camera.width * meta.camera.height
    if meta.streams.color is not None:
        n += 3 * meta.streams.color.camera.width * meta.streams.color.camera.height
    return n


class PreloadedReader:
    """``reader`` with its first ``count`` frames held decoded; every other attribute is the reader's."""

    def __init__(self, reader, depth: list, infrared: list, color: list):
        self._reader = reader
        self._depth, self._infrared, self._color = depth, infrared, color
        self.count = len(depth)
        self.megabytes = sum(a.nbytes for a in depth + infrared + color if a is not None) / 2**20

    def __getattr__(self, name):
        return getattr(self._reader, name)

    def read_depth(self, index: int) -> np.ndarray:
        if index < self.count:
            return png_to_depth(self._depth[index], self._reader.meta.depth_scale)
        return self._reader.read_depth(index)

    def read_infrared(self, index: int):
        return self._infrared[index] if index < self.count else self._reader.read_infrared(index)

    def read_color(self, index: int):
        return self._color[index] if index < self.count else self._reader.read_color(index)


def preload(reader, budget_mb: float, workers: int = 2) -> "PreloadedReader | object":
    """``reader`` with as many of its first frames decoded as fit ``budget_mb`` (0: ``reader`` itself).

    The decodes run on ``workers`` threads (OpenCV's PNG decoder releases the GIL). Decoding stops at
    the first frame that cannot be read (a missing or corrupt PNG); that frame and the later ones are
    read when played, so their error surfaces there, as without a preload.
    """
    fit = int(budget_mb * 2**20 // max(frame_bytes(reader.meta), 1)) if budget_mb > 0 else 0
    count = min(fit, len(reader.frame_ids))
    if count == 0:
        return reader
    with ThreadPoolExecutor(max_workers=max(int(workers), 1), thread_name_prefix="preload") as pool:
        decoded = list(pool.map(lambda i: _decode(reader, i), range(count)))
    good = next((i for i, d in enumerate(decoded) if d is None), count)
    depth, infrared, color = ([d[k] for d in decoded[:good]] for k in range(3))
    out = PreloadedReader(reader, depth, infrared, color)
    if good < count:
        log.warning("preload stopped at frame index %d of %s (unreadable); it is read when played", good, reader.path)
    log.info("preloaded %d of %d frames of %s (%.0f MB of a %.0f MB budget)", out.count, len(reader.frame_ids),
             reader.path, out.megabytes, budget_mb)
    return out


def _decode(reader, index: int):
    """(depth PNG, infrared, colour) of frame ``index``, or None when any of them cannot be read."""
    from app.errors import TrialFormatError

    try:
        return reader.read_depth_png(index), reader.read_infrared(index), reader.read_color(index)
    except (TrialFormatError, OSError):
        return None
