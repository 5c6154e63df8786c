"""Session clocks for tests: time moves when the test (or the session's own sources) says so, never
with the machine's load.

:class:`ManualClock` jumps to whatever time a source sleeps until. :class:`LockstepClock`
(installed by :func:`lockstep_sessions`) also holds the camera until the live loop has processed
every frame it pushed, so a live session tracks every frame on any machine.
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
