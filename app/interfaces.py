"""What the live loop expects of its sources, tracker and sinks (Protocols), and the data they pass.

One clock: every stamp a source hands over is in seconds on the host's monotonic clock
(``time.monotonic()``, the same in every process of the machine). A source with its own clock (a
camera's hardware timestamps, a robot controller's time) maps it to the host clock before
pushing (``plugins/_clock.py``); a source that replays recorded time maps it through the session's
shared replay anchor (:meth:`SessionClock.replay_to_host`), so that two replayed sources that
recorded on one clock stay aligned.

Sources run their own background threads and push through callbacks that never block
(:class:`DropOldestQueue` behind them). The loop thread pops, interpolates, tracks, and hands the
result to the sinks, which must return at once (they queue and drop, and count what they drop).

Import as ``from app.interfaces import DepthFrame, JointSamples, CameraSource, ...``.
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from app.geometry.camera import PinholeCamera

KINDS = ("camera", "robot", "tracker", "output")
STATUSES = ("ok", "uncertain", "lost")


@dataclass(frozen=True)
class DepthFrame:
    """One depth image, with the camera's infrared and colour images of the same instant when it delivers them.

    frame_id : the camera's frame counter (increasing, gaps where frames were dropped)
    stamp : capture time, s, host monotonic clock
    depth_m : (H, W) float32 depth in metres along the optical axis, 0 = no measurement
    arrival : host time the frame reached the session, s (for latency accounting)
    infrared : (H, W) uint8, the left imager, which is the depth frame itself (same K), or None
    color : (Hc, Wc, 3) uint8 RGB in the colour camera's own frame (its K, distortion and
        T_depth_color: :class:`app.image_streams.ColorStream`, from the camera's
        ``session_defaults()['image_streams']``), or None
    """

    frame_id: int
    stamp: float
    depth_m: np.ndarray
    arrival: float
    infrared: np.ndarray | None = None
    color: np.ndarray | None = None


@dataclass(frozen=True)
class JointSamples:
    """Joint encoder samples: stamps (N,) s on the host clock, q (N, 6) radians."""

    stamps: np.ndarray
    q: np.ndarray


@dataclass(frozen=True)
class SessionEvent:
    """Something that happened: ``kind`` (e.g. ``camera.stall``), when (host s) and a sentence."""

    stamp: float
    source: str
    kind: str
    message: str


@dataclass
class Estimate:
    """The loop's output for one frame (or for a tick without frames when a source is lost).

    T_base_bone : (4, 4) bone pose in the robot base frame, or None
    status : 'ok' | 'uncertain' | 'lost'; the projector shows the template only when 'ok'
    latency_s : frame capture to estimate, s (None for a tick without a frame)
    """

    stamp: float
    frame_id: int | None
    T_base_bone: np.ndarray | None
    status: str
    T_base_camera: np.ndarray | None = None
    latency_s: float | None = None
    reasons: tuple[str, ...] = ()
    diagnostics: dict = field(default_factory=dict)

    @property
    def show_template(self) -> bool:
        return self.status == "ok" and self.T_base_bone is not None


class SessionClock:
    """The host clock and the anchor that maps replayed (recorded) time onto it.

    ``replay_to_host(t)`` maps a recorded stamp to ``host_anchor + (t - origin)``: the origin and the
    host anchor (the host time of that first call plus ``lead_in_s``) are fixed by the first call
    from any source, so recorded sources that shared one clock when recorded stay aligned when
    replayed, and their stamps are on the session's clock however long the sources took to open
    (a simulated trial may be simulated first).

    ``replay_rate`` < 1 plays recorded time slower than real time (0.25: a quarter of the speed),
    for a loop that must see most frames on a slow machine; ``now`` may be injected (tests drive
    the loop with a manual clock); by default it is ``time.monotonic``.
    """

    def __init__(self, lead_in_s: float = 0.2, now: Callable[[], float] | None = None, replay_rate: float = 1.0):
        self._now = now or time.monotonic
        self.t0 = self._now()
        self.lead_in_s = lead_in_s
        self.replay_rate = float(replay_rate)
        self._origin: float | None = None
        self._host_anchor: float | None = None
        self._lock = threading.Lock()

    def now(self) -> float:
        return self._now()

    def wait_until(self, t: float, stop: threading.Event) -> bool:
        """Block until this clock reads ``t`` (True) or ``stop`` is set (False); sources sleep here,
        so a test's clock can make their time pass without waiting."""
        while not stop.is_set():
            delay = t - self.now()
            if delay <= 0:
                return True
            stop.wait(min(delay, 0.05))
        return False

    def replay_origin(self, t_first: float) -> float:
        with self._lock:
            if self._origin is None:
                self._origin = float(t_first)
                self._host_anchor = self._now() + self.lead_in_s
            return self._origin

    def replay_to_host(self, t: np.ndarray | float, t_first: float | None = None) -> np.ndarray | float:
        origin = self.replay_origin(t if t_first is None else t_first) if self._origin is None else self._origin
        return self._host_anchor + (np.asarray(t, dtype=float) - origin) / self.replay_rate


EventSink = Callable[[str, str, str], None]  # (source, kind, message)


@runtime_checkable
class CameraSource(Protocol):
    """A depth camera plugin (kind ``camera``).

    ``open`` connects (or opens the file) and returns the full-resolution intrinsics; ``start``
    runs a background thread that calls ``push(frame)`` per frame and ``event(...)`` on faults,
    reconnecting on its own; ``stop`` joins it. ``session_defaults`` may offer calibration, mesh
    and initial pose (a recorded or simulated trial knows them), else returns {}.
    """

    name: str

    def open(self, clock: SessionClock, event: EventSink) -> PinholeCamera: ...

    def start(self, push: Callable[[DepthFrame], None]) -> None: ...

    def stop(self) -> None: ...

    def session_defaults(self) -> dict: ...


@runtime_checkable
class RobotSource(Protocol):
    """A robot plugin (kind ``robot``): pushes :class:`JointSamples` from a background thread."""

    name: str

    def open(self, clock: SessionClock, event: EventSink) -> None: ...

    def start(self, push: Callable[[JointSamples], None]) -> None: ...

    def stop(self) -> None: ...

    def session_defaults(self) -> dict: ...


@runtime_checkable
class TrackerResult(Protocol):
    """What every tracker returns per frame: the pose and the status (the typed part of the contract).

    T_base_bone : (4, 4) the bone in the robot base frame; status : 'ok' | 'uncertain' | 'lost'.
    Trackers add their own fields (the particle filter's spreads, ESS, refinement fitness; ICP's
    fitness): :func:`result_scalars` lists the numeric ones for the logs.
    """

    T_base_bone: np.ndarray
    status: str


@runtime_checkable
class Tracker(Protocol):
    """A tracker plugin (kind ``tracker``), created and used on the loop thread only (GL).

    ``process`` gets the whole frame (depth, stamp, and the infrared / colour images when the camera
    delivers them) and the camera's pose at its stamp (None when unknown). ``description`` is one line
    naming the tracker and where it runs (summaries, logs); ``particle_positions`` the (N, 3) points to
    draw in the log (the particles; the pose's origin for a tracker without them).
    """

    description: str

    def start(self, T_base_bone: np.ndarray) -> None: ...

    def process(self, frame: DepthFrame, T_base_camera: np.ndarray | None) -> TrackerResult: ...

    def particle_positions(self) -> np.ndarray: ...

    def mean_timings_ms(self) -> dict[str, float]: ...

    def release(self) -> None: ...


def result_scalars(result) -> dict[str, float]:
    """Every numeric (int, float, bool) dataclass field of a tracker result, by name, as float.

    New fields are picked up without a change here (e.g. a recovery's ``reinitialised``).
    """
    import dataclasses

    if not dataclasses.is_dataclass(result):
        return {}
    out = {}
    for f in dataclasses.fields(result):
        value = getattr(result, f.name)
        if isinstance(value, (bool, int, float, np.floating, np.integer)) and not isinstance(value, str):
            out[f.name] = float(value)
    return out


@runtime_checkable
class Output(Protocol):
    """A sink plugin (kind ``output``). Every method returns at once (queue and drop, never block)."""

    def open(self, context: dict) -> None: ...

    def on_frame(self, frame: DepthFrame) -> None: ...

    def on_joints(self, samples: JointSamples) -> None: ...

    def on_estimate(self, estimate: Estimate) -> None: ...

    def on_event(self, event: SessionEvent) -> None: ...

    def close(self) -> dict: ...


class DropOldestQueue:
    """A bounded FIFO whose ``put`` never blocks: when full, the oldest item goes and is counted.

    ``maxlen`` bounds the items. ``max_bytes`` (with ``nbytes``, an item's size in bytes) also bounds
    what the held items weigh: an item that would take the total past it drops the oldest items that
    weigh something (items of size 0, e.g. joint batches, stay) until it fits, each counted in
    ``dropped``. An item heavier than ``max_bytes`` alone is still taken (it is then the only weighty
    one). ``nbytes_held`` is the current total.
    """

    def __init__(self, maxlen: int, max_bytes: int | None = None, nbytes=None):
        if maxlen < 1:
            raise ValueError(f"maxlen must be >= 1, got {maxlen}")
        if (max_bytes is None) != (nbytes is None):
            raise ValueError("max_bytes and nbytes go together")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self._items: collections.deque = collections.deque()
        self._sizes: collections.deque = collections.deque()   # each item's nbytes (0 without a budget)
        self._maxlen = maxlen
        self._max_bytes, self._nbytes = max_bytes, nbytes
        self.nbytes_held = 0
        self._cond = threading.Condition()
        self.dropped = 0
        self.put_count = 0

    def put(self, item) -> None:
        size = int(self._nbytes(item)) if self._nbytes is not None else 0
        with self._cond:
            if len(self._items) >= self._maxlen:
                self._pop(0)
                self.dropped += 1
            if self._max_bytes is not None and size:
                while self.nbytes_held + size > self._max_bytes and self.nbytes_held:
                    self._pop(next(i for i, s in enumerate(self._sizes) if s))   # the oldest weighty item
                    self.dropped += 1
            self._items.append(item)
            self._sizes.append(size)
            self.nbytes_held += size
            self.put_count += 1
            self._cond.notify()

    def _pop(self, i: int):
        """Remove and return the item at index ``i`` (0: the oldest); the lock is held."""
        if i == 0:
            self.nbytes_held -= self._sizes.popleft()
            return self._items.popleft()
        self.nbytes_held -= self._sizes[i]
        del self._sizes[i]
        item = self._items[i]
        del self._items[i]
        return item

    def get(self, timeout: float | None = None):
        """The oldest item, or None after ``timeout`` seconds without one."""
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            return self._pop(0) if self._items else None

    def get_latest(self, timeout: float | None = None):
        """The newest item (older ones are discarded and counted as dropped), or None."""
        with self._cond:
            if not self._items:
                self._cond.wait(timeout)
            if not self._items:
                return None
            item = self._items.pop()
            self.dropped += len(self._items)
            self._clear()
            return item

    def drain(self) -> list:
        with self._cond:
            items = list(self._items)
            self._clear()
            return items

    def _clear(self) -> None:
        self._items.clear()
        self._sizes.clear()
        self.nbytes_held = 0

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)
