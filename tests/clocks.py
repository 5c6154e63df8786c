"""Session clocks for tests: time moves when the test (or the session's own sources) says so, never
with the machine's load.

:class:`ManualClock` jumps to whatever time a source sleeps until. :class:`LockstepClock`
(installed by :func:`lockstep_sessions`) also holds the camera until the live loop has processed
every frame it pushed, so a live session tracks every frame on any machine. :class:`PacedClock`
(installed by :func:`paced_sessions`) lets a slow test tracker's work move the time while the
sources go on as on a second core, so a session drops frames exactly as the counts say.
"""
from __future__ import annotations

import threading

from app.interfaces import SessionClock


class ManualClock(SessionClock):
    """A session clock that advances only when told to; sleeping jumps to the wake-up time."""

    def __init__(self, start: float = 1000.0, lead_in_s: float = 0.2):
        self.t = start
        super().__init__(lead_in_s=lead_in_s, now=lambda: self.t)

    def advance(self, dt: float) -> None:
        self.t += dt

    def wait_until(self, t: float, stop: threading.Event) -> bool:
        if stop.is_set():
            return False
        self.t = max(self.t, t)
        return True


class LockstepClock(ManualClock):
    """The live loop in lock step with its sources.

    A source's sleep until ``t`` returns once the loop has processed every frame pushed so far; the
    clock then jumps to ``t + lead_s``. So the tracker's work takes no session time and the camera
    never falls behind its schedule (it pushes every frame, and the loop processes each one), and a
    robot that streams what is due by the clock (``plugins.trial_player.RecordedRobot``) has its
    samples ``lead_s`` past each frame's stamp, which the frame's camera pose needs. ``lead_s`` must
    stay under one camera period (else the camera would skip to a later frame).
    """

    def __init__(self, lead_s: float = 0.005, **kwargs):
        super().__init__(**kwargs)
        self.lead_s = lead_s
        self.pending = 0                      # frames pushed and not yet processed by the loop
        self.frames_pushed = 0
        self._cond = threading.Condition()

    def frame_pushed(self) -> None:
        with self._cond:
            self.pending += 1
            self.frames_pushed += 1

    def frame_done(self) -> None:
        with self._cond:
            self.pending -= 1
            self._cond.notify_all()

    def wait_until(self, t: float, stop: threading.Event) -> bool:
        with self._cond:
            while self.pending > 0 and not stop.is_set():
                self._cond.wait(0.05)
            if stop.is_set():
                return False
            self.t = max(self.t, t + self.lead_s)
            return True


def lockstep_sessions(monkeypatch, **kwargs) -> list[LockstepClock]:
    """Every live session started after this call runs on a fresh :class:`LockstepClock` (returned
    in the list as they are made): the session's clock, the bus's accepted frames and the loop's
    processed ones are hooked, nothing else of the session changes."""
    from app.session import bus, loop

    clocks: list[LockstepClock] = []

    def make_clock(replay_rate: float = 1.0) -> LockstepClock:   # as LiveLoop makes its SessionClock
        clock = LockstepClock(**kwargs)
        clock.replay_rate = float(replay_rate)
        clocks.append(clock)
        return clock

    push_frame, process = bus.Bus.push_frame, loop.LiveLoop.process

    def counted_push_frame(self, frame) -> None:
        accepted = self.counts["frames_accepted"]
        push_frame(self, frame)
        if self.counts["frames_accepted"] > accepted:   # queued for the loop (rejected ones are not)
            clocks[-1].frame_pushed()

    def counted_process(self, frame, t_pop) -> None:
        try:
            process(self, frame, t_pop)
        finally:
            self.clock.frame_done()

    monkeypatch.setattr(loop, "SessionClock", make_clock)
    monkeypatch.setattr(bus.Bus, "push_frame", counted_push_frame)
    monkeypatch.setattr(loop.LiveLoop, "process", counted_process)
    return clocks


class PacedClock(ManualClock):
    """Time passes while the tracker works and while the loop waits for a frame, never with the load.

    A slow tracker under test calls :meth:`work` (its time on the clock). A source's sleep
    (``wait_until``, also a read that takes time) jumps the clock only while the loop waits for a
    frame with none queued, and then only the earliest sleeper's, and no more once a source has ended
    (a recording played through: the loop ends); else it waits for the tracker's time to reach its
    wake-up. :meth:`work` returns once every source has done what was due and
    sleeps past the new time, so what the sources push during the tracker's work is queued when the
    loop looks again. Installed by :func:`paced_sessions`.
    """

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.loop_waiting = False            # the loop waits for a frame, none queued since it began
        self._cond = threading.Condition()
        self._sleepers: dict[threading.Thread, float | None] = {}   # source thread -> wake-up (None: awake)

    def _all_asleep_past(self, t: float) -> bool:
        return all(wake is not None and wake > t for th, wake in self._sleepers.items() if th.is_alive())

    def wait_until(self, t: float, stop: threading.Event) -> bool:
        me = threading.current_thread()
        with self._cond:
            self._sleepers[me] = t
            self._cond.notify_all()
            try:
                while self.t < t:
                    if stop.is_set():
                        return False
                    live = [w for th, w in self._sleepers.items() if th.is_alive()]
                    ended = len(live) < len(self._sleepers)     # a finite source is done: the loop stops next
                    if self.loop_waiting and not ended and all(w is not None for w in live) and t <= min(live):
                        self.t = t
                        break
                    self._cond.wait(0.005)
                return True
            finally:
                self._sleepers[me] = None
                self._cond.notify_all()

    def work(self, dt: float, timeout: float = 10.0) -> None:
        """The tracker's ``dt`` seconds. The clock moves on from one source's wake-up to the next within
        them, each source doing what fell due (as on a second core) before it moves again."""
        import time

        deadline = time.monotonic() + timeout
        with self._cond:
            end = self.t + dt
            while True:
                while not self._all_asleep_past(self.t) and time.monotonic() < deadline:
                    self._cond.wait(0.005)
                wakes = [w for th, w in self._sleepers.items() if th.is_alive() and w is not None]
                if self.t >= end or time.monotonic() >= deadline:
                    return
                self.t = min([end, *wakes])
                self._cond.notify_all()

    def set_loop_waiting(self, waiting: bool) -> None:
        with self._cond:
            self.loop_waiting = waiting
            self._cond.notify_all()


def paced_sessions(monkeypatch) -> list[PacedClock]:
    """Every live session started after this call runs on a fresh :class:`PacedClock` (returned in the
    list as they are made): the session's clock and the bus's frame queue (which tells the clock when
    the loop waits for a frame) are hooked, nothing else of the session changes."""
    from app.interfaces import DropOldestQueue
    from app.session import bus, loop

    clocks: list[PacedClock] = []

    def make_clock(replay_rate: float = 1.0) -> PacedClock:   # as LiveLoop makes its SessionClock
        clock = PacedClock()
        clock.replay_rate = float(replay_rate)
        clocks.append(clock)
        return clock

    class PacedQueue(DropOldestQueue):
        """Tells the clock when the loop waits with nothing queued (under the queue's own lock, so a
        frame queued meanwhile ends the wait for the clock too)."""

        def get_latest(self, timeout: float | None = None):
            with self._cond:
                clocks[-1].set_loop_waiting(not self._items)
                try:
                    return super().get_latest(timeout)
                finally:
                    clocks[-1].set_loop_waiting(False)

        def put(self, item) -> None:
            with self._cond:
                clocks[-1].set_loop_waiting(False)
                super().put(item)

    class PacedBus(bus.Bus):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.frames = PacedQueue(self.frames._maxlen)

    monkeypatch.setattr(loop, "SessionClock", make_clock)
    monkeypatch.setattr(loop, "Bus", PacedBus)
    return clocks
