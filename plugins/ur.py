"""Universal Robots arm as a joint source (``robot: ur``), through ur_rtde's RTDEReceiveInterface.

The controller streams ``timestamp`` (its own clock, s since it booted) and ``actual_q`` (rad) at
its rate (500 Hz on e-Series, 125 Hz on CB3). The plugin connects only to ``host``, the address
the session file names, on RTDE's port (30004, fixed by ur_rtde); it opens no other port (no
dashboard, no control interface: it never moves the robot).

Why a worker process: ur_rtde's Python binding holds the GIL while it connects and reads, and
its connect has no timeout, so a robot that does not answer would freeze the whole session (the
tracker included). The client runs in a child process (``spawn``) that polls the interface and
sends batches of ``(controller stamp, host arrival, q0..q5)`` through a pipe. In the session
process a thread maps controller time to the host clock (``plugins/_clock.py``: minimum-delay
offset, clock jumps detected and re-anchored) and pushes :class:`~app.interfaces.JointSamples`.

Faults: a stream that stops (no new controller timestamp for ``stale_s``) or a dropped connection
makes the worker drop the interface and connect again every ``reconnect_s``; a worker that hangs
(no message for ``hang_s``) is killed and started again. Each transition is a session event. NaN
joints are passed on; the session rejects and logs them.
"""
from __future__ import annotations

import ipaddress
import logging
import multiprocessing as mp
import re
import time

import numpy as np

from app.errors import ConfigError
from app.interfaces import JointSamples, SessionClock
from plugins._base import ThreadedSource
from plugins._clock import ClockMapper

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install ur-rtde  (or: pip install 'osteonav[hardware]')"
_HOSTNAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")


def _check_host(host) -> str:
    if not isinstance(host, str) or not host:
        raise ConfigError("robot.params.host", f"expected the robot's IP address or host name, got {host!r}")
    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        pass
    if not _HOSTNAME.match(host):
        raise ConfigError("robot.params.host", f"{host!r} is neither an IP address nor a valid host name")
    return host


def _worker(host: str, frequency: float, conn, stale_s: float, reconnect_s: float) -> None:
    """Child process: own the RTDE client, send ('samples', (N, 8) array) / status tuples."""
    try:
        import rtde_receive
    except ImportError as exc:
        conn.send(("fatal", f"ur_rtde is not installed ({exc}); {INSTALL_HINT}"))
        return
    iface = None
    last_ts = None
    last_new = time.monotonic()
    last_send = last_new
    batch: list[tuple] = []
    while True:
        if conn.poll():
            if conn.recv() == "stop":
                break
        now = time.monotonic()
        if iface is None:
            try:
                iface = rtde_receive.RTDEReceiveInterface(host, frequency, ["timestamp", "actual_q"])
                conn.send(("connected", f"RTDE stream from {host}:30004"))
                last_ts, last_new = None, time.monotonic()
            except Exception as exc:  # the binding raises RuntimeError; keep trying, never crash
                conn.send(("error", f"cannot connect to {host}:30004: {exc}"))
                iface = None
                time.sleep(reconnect_s)
                continue
        try:
            ts = iface.getTimestamp()
            if ts != last_ts:
                q = iface.getActualQ()
                ts2 = iface.getTimestamp()
                if ts2 == ts:
                    batch.append((ts, now, *q))
                    last_ts, last_new = ts, now
            elif now - last_new > stale_s or not iface.isConnected():
                raise ConnectionError("connection lost" if not iface.isConnected() else f"no new RTDE data for {now - last_new:.3f} s")
        except Exception as exc:
            if batch:
                conn.send(("samples", np.array(batch, float)))
                batch = []
            conn.send(("disconnected", f"{type(exc).__name__}: {exc}"))
            try:
                iface.disconnect()
            except Exception:
                pass
            iface = None
            time.sleep(reconnect_s)
            continue
        if batch and now - last_send >= 0.004:
            conn.send(("samples", np.array(batch, float)))
            batch, last_send = [], now
        elif now - last_send >= 0.1:
            conn.send(("alive", ""))
            last_send = now
        time.sleep(0.0002)
    if iface is not None:
        try:
            iface.disconnect()
        except Exception:
            pass


class URRobot(ThreadedSource):
    """Joint angles of a UR arm, streamed over RTDE by ur_rtde.

    Parameters
    ----------
    host : the robot's IP address or host name (required: the session file names the robot)
    frequency : RTDE output rate in Hz; -1 = the controller's rate (500 e-Series, 125 CB3)
    stale_s : no new sample for this long = disconnected
    reconnect_s : wait between connection attempts
    hang_s : a worker silent for this long is killed and restarted
    """

    kind, name = "robot", "ur"

    def __init__(self, host: str, frequency: float = -1.0, stale_s: float = 0.1, reconnect_s: float = 0.2,
                 hang_s: float = 3.0):
        super().__init__()
        self.host = _check_host(host)
        self.frequency = float(frequency)
        self.stale_s, self.reconnect_s, self.hang_s = float(stale_s), float(reconnect_s), float(hang_s)
        self.clock_mapper = ClockMapper()
        self._proc = None
        self._conn = None
        self.samples_received = 0
        self.connects = 0

    def open(self, clock: SessionClock, event) -> None:
        import importlib.util

        if importlib.util.find_spec("rtde_receive") is None:
            raise ConfigError("robot.plugin", f"the 'ur' robot plugin needs ur_rtde, which is not installed: {INSTALL_HINT}")
        self._bind(clock, event)

    def _spawn(self) -> None:
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=_worker, args=(self.host, self.frequency, child, self.stale_s, self.reconnect_s),
                                 name=f"ur-rtde-{self.host}", daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent

    def _kill(self) -> None:
        if self._proc is None:
            return
        try:
            self._conn.send("stop")
        except (OSError, ValueError):
            pass
        self._proc.join(1.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(1.0)
        self._conn.close()
        self._proc = None

    def _run(self) -> None:
        self._spawn()
        last_msg = time.monotonic()
        connected = False
        last_error = None
        try:
            while not self._stop.is_set():
                try:
                    ready = self._conn.poll(0.05)
                    msg = self._conn.recv() if ready else None
                except (EOFError, OSError):
                    msg, ready = ("worker_died", "the RTDE worker process exited"), True
                now = time.monotonic()
                if msg is None:
                    if now - last_msg > self.hang_s:
                        self._event("hang", f"RTDE worker silent for {now - last_msg:.1f} s: restarting it")
                        self._kill()
                        self._spawn()
                        last_msg, connected = time.monotonic(), False
                    continue
                last_msg = now
                tag, payload = msg
                if tag == "samples":
                    self._on_samples(payload)
                elif tag == "connected":
                    self.connects += 1
                    self.clock_mapper.reset()
                    connected, last_error = True, None
                    self._event("connected", payload)
                elif tag == "disconnected":
                    if connected:
                        self._event("disconnected", payload)
                    connected = False
                elif tag == "error":
                    if payload != last_error:
                        self._event("connect_failed", payload)
                    last_error = payload
                elif tag == "fatal":
                    self._event("error", payload)
                    return
                elif tag == "worker_died":
                    self._event("hang", payload + ": restarting it")
                    self._kill()
                    time.sleep(self.reconnect_s)
                    self._spawn()
                    last_msg, connected = time.monotonic(), False
        finally:
            self._kill()

    def _on_samples(self, rows: np.ndarray) -> None:
        host = np.empty(len(rows))
        for k, (ts, arrival) in enumerate(rows[:, :2]):
            host[k], jump = self.clock_mapper.map(float(ts), float(arrival))
            if jump is not None:
                self._event("clock_jump", f"controller clock jumped by {jump:+.3f} s; mapping re-anchored")
        self.samples_received += len(rows)
        self._push(JointSamples(host, rows[:, 2:8].copy()))
