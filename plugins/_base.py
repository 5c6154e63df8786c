"""Plumbing shared by the source plugins: one background thread, a stop flag, fault events.

A source subclasses :class:`ThreadedSource` and implements ``_run`` (the thread's body), which
returns when ``self._stop`` is set and calls ``self._push`` / ``self._event``. Exceptions in
``_run`` are logged as an event, never raised into the loop. ``finished`` is set when a finite
source (a file, a recorded trial) has delivered everything.
"""
from __future__ import annotations

import logging
import threading
from typing import Callable

from app.interfaces import SessionClock

log = logging.getLogger(__name__)


class ThreadedSource:
    kind = "source"
    name = "source"

    def __init__(self):
        self._stop = threading.Event()
        self.finished = threading.Event()
        self._thread: threading.Thread | None = None
        self._push: Callable | None = None
        self._event_cb: Callable[[str, str, str], None] | None = None
        self.clock: SessionClock | None = None

    def _bind(self, clock: SessionClock, event) -> None:
        self.clock = clock
        self._event_cb = event

    def _event(self, kind: str, message: str) -> None:
        if self._event_cb is not None:
            self._event_cb(f"{self.kind}.{self.name}", kind, message)
        else:
            log.info("%s.%s %s: %s", self.kind, self.name, kind, message)

    def start(self, push: Callable) -> None:
        self._push = push
        self._stop.clear()
        self._thread = threading.Thread(target=self._guarded_run, name=f"{self.kind}-{self.name}", daemon=True)
        self._thread.start()

    def _guarded_run(self) -> None:
        try:
            self._run()
        except Exception as exc:  # a source's thread must never take the session down
            log.exception("%s.%s thread failed", self.kind, self.name)
            self._event("error", f"source thread stopped: {type(exc).__name__}: {exc}")
            self.finished.set()

    def _run(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("%s.%s thread did not stop within %.1f s", self.kind, self.name, timeout)

    def session_defaults(self) -> dict:
        return {}

    def _sleep_until(self, host_t: float) -> bool:
        """Sleep until host time ``host_t`` (on the session clock); False if stopped meanwhile."""
        return self.clock.wait_until(host_t, self._stop)
