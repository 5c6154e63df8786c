"""A small RTDE server: enough of Universal Robots' Real-Time Data Exchange protocol for a client.

What it is for: testing the ``ur`` robot plugin (and demonstrating a session) without a robot. The
real ``ur_rtde`` client (``RTDEReceiveInterface``) connects to it, negotiates, subscribes and
streams joint angles exactly as it would from a controller.

The protocol subset (UR's "Real-Time Data Exchange (RTDE) Guide", protocol version 2), every
message framed as ``>HB`` (size of the whole package in bytes including this 3-byte header, type):

- ``V`` (86) request protocol version: payload ``>H`` version; reply ``>B`` accepted (only 2).
- ``v`` (118) get URControl version: reply ``>IIII`` major, minor, bugfix, build (5.x: e-Series).
- ``O`` (79) setup outputs: payload ``>d`` frequency + comma-separated variable names; reply
  ``>B`` recipe id + comma-separated types (``NOT_FOUND`` for an unknown name, then the
  recipe id is 0 and the recipe is refused).
- ``I`` (73) setup inputs: accepted and answered with the types (nothing reads the inputs).
- ``S`` (83) start / ``P`` (80) pause: reply ``>B`` accepted; while started, ``U`` (85) data
  packages (``>B`` recipe id + the values, big-endian) go out at the recipe's frequency.
- ``M`` (77) text messages are read and ignored.

The controller clock: ``timestamp`` is the time since the server started (s), as on a controller;
``actual_q``/``target_q`` come from ``joints(t)`` (a callable of that time, (6,) radians).

Faults for tests: ``drop_clients(pause_s)`` closes every connection and refuses new ones for
``pause_s`` seconds (a robot that disconnects), ``set_nan(True)`` sends NaN joints, and
``jump_clock(seconds)`` moves the controller clock.

The RTDE port is fixed in ur_rtde's receive interface (30004), so a test server takes a free
loopback address instead of a free port (Linux routes all of 127.0.0.0/8 to the loopback device):
:func:`free_loopback_host`.
"""
from __future__ import annotations

import logging
import math
import random
import socket
import struct
import threading
import time
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

RTDE_PORT = 30004
PROTOCOL_VERSION = 2

REQUEST_PROTOCOL_VERSION = 86
GET_URCONTROL_VERSION = 118
TEXT_MESSAGE = 77
DATA_PACKAGE = 85
SETUP_OUTPUTS = 79
SETUP_INPUTS = 73
START = 83
PAUSE = 80

# RTDE type name -> struct format (big-endian, no header)
TYPE_FORMATS = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}

_VECTOR6D = ("target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
             "joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose "
             "target_TCP_speed joint_temperatures actual_joint_voltage ft_raw_wrench payload_inertia "
             "actual_current_window tcp_offset actual_current_as_torque").split()
_DOUBLE = ("timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum actual_main_voltage "
           "actual_robot_voltage actual_robot_current standard_analog_input0 standard_analog_input1 "
           "standard_analog_output0 standard_analog_output1 tool_analog_input0 tool_analog_input1 "
           "tool_output_current payload tool_temperature").split()
_INT32 = "robot_mode safety_mode safety_status tool_output_voltage".split()
_UINT32 = "runtime_state robot_status_bits safety_status_bits tool_mode script_control_line analog_io_types".split()
_UINT64 = "actual_digital_input_bits actual_digital_output_bits".split()
_VECTOR3D = "actual_tool_accelerometer payload_cog elbow_position elbow_velocity".split()

VARIABLE_TYPES: dict[str, str] = {}
VARIABLE_TYPES.update({n: "VECTOR6D" for n in _VECTOR6D})
VARIABLE_TYPES.update({n: "DOUBLE" for n in _DOUBLE})
VARIABLE_TYPES.update({n: "INT32" for n in _INT32})
VARIABLE_TYPES.update({n: "UINT32" for n in _UINT32})
VARIABLE_TYPES.update({n: "UINT64" for n in _UINT64})
VARIABLE_TYPES.update({n: "VECTOR3D" for n in _VECTOR3D})
VARIABLE_TYPES["joint_mode"] = "VECTOR6INT32"
for _i in range(48):
    VARIABLE_TYPES[f"output_int_register_{_i}"] = "INT32"
    VARIABLE_TYPES[f"output_double_register_{_i}"] = "DOUBLE"
    VARIABLE_TYPES[f"input_int_register_{_i}"] = "INT32"
    VARIABLE_TYPES[f"input_double_register_{_i}"] = "DOUBLE"
for _i in range(64, 128):
    VARIABLE_TYPES[f"output_bit_register_{_i}"] = "BOOL"
    VARIABLE_TYPES[f"input_bit_register_{_i}"] = "BOOL"

ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NORMAL = 1


def free_loopback_host(port: int = RTDE_PORT, rng: random.Random | None = None, tries: int = 50) -> str:
    """A loopback address ``127.x.y.z`` on which ``port`` is free (ur_rtde's port cannot be changed)."""
    rng = rng or random.Random()
    candidates = ["127.0.0.1"] + [f"127.{rng.randint(1, 254)}.{rng.randint(1, 254)}.{rng.randint(2, 254)}"
                                  for _ in range(tries)]
    for host in candidates:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return host
    raise OSError(f"no free loopback address for port {port} after {tries} tries")


def _pack(msg_type: int, payload: bytes = b"") -> bytes:
    return struct.pack(">HB", 3 + len(payload), msg_type) + payload


class RTDEServer:
    """Serve RTDE on ``(host, port)`` from a background thread; one client at a time.

    Parameters
    ----------
    joints : callable ``t -> (6,)`` joint angles in radians at controller time ``t`` (s)
    host, port : where to listen (port 30004 is what ur_rtde's receive interface uses)
    version : the URControl version reported, (major, minor, bugfix, build); major 5 = e-Series (500 Hz)
    """

    def __init__(self, joints: Callable[[float], np.ndarray], host: str = "127.0.0.1", port: int = RTDE_PORT,
                 version: tuple[int, int, int, int] = (5, 11, 0, 0)):
        self.joints = joints
        self.host, self.port = host, port
        self.version = version
        self._t0 = time.monotonic()
        self._clock_offset = 0.0
        self._nan = False
        self._refuse_until = 0.0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self.connections = 0           # accepted connections so far
        self.packages_sent = 0
        self.peers: list[tuple[str, int]] = []
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((host, port))
        self._listener.listen(4)
        self._listener.settimeout(0.05)
        self._thread = threading.Thread(target=self._accept_loop, name="rtde-server", daemon=True)

    # -- control ---------------------------------------------------------------------------------
    def start(self) -> "RTDEServer":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._close_clients()
        self._thread.join(timeout=2.0)
        self._listener.close()

    def __enter__(self) -> "RTDEServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def controller_time(self) -> float:
        return time.monotonic() - self._t0 + self._clock_offset

    def drop_clients(self, pause_s: float = 0.5) -> None:
        """Close every connection and refuse new ones for ``pause_s`` seconds (a cable pulled)."""
        self._refuse_until = time.monotonic() + pause_s
        self._close_clients()

    def set_nan(self, on: bool) -> None:
        self._nan = on

    def jump_clock(self, seconds: float) -> None:
        self._clock_offset += seconds

    # -- internals -------------------------------------------------------------------------------
    def _close_clients(self) -> None:
        with self._lock:
            conns, self._conns = self._conns, []
        for c in conns:
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            c.close()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, peer = self._listener.accept()
            except (socket.timeout, OSError):
                continue
            if time.monotonic() < self._refuse_until:
                conn.close()
                continue
            self.connections += 1
            self.peers.append(peer)
            with self._lock:
                self._conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), name="rtde-client", daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.settimeout(0.002)
        buf = b""
        recipe: list[str] | None = None
        frequency = 500.0
        streaming = False
        next_send = time.monotonic()
        try:
            while not self._stop.is_set():
                try:
                    chunk = conn.recv(4096)
                    if not chunk:
                        return
                    buf += chunk
                except socket.timeout:
                    pass
                while len(buf) >= 3:
                    size, msg_type = struct.unpack_from(">HB", buf)
                    if size < 3 or len(buf) < size:
                        break
                    payload, buf = buf[3:size], buf[size:]
                    reply, recipe, frequency, streaming = self._handle(msg_type, payload, recipe, frequency, streaming)
                    if reply:
                        conn.sendall(reply)
                    if streaming:
                        next_send = time.monotonic()
                if streaming and recipe:
                    now = time.monotonic()
                    if now >= next_send:
                        conn.sendall(self._data_package(recipe, cycle_host=next_send))
                        self.packages_sent += 1
                        next_send += 1.0 / frequency
                        if now - next_send > 0.1:   # fell far behind (a stalled machine): do not burst
                            next_send = now
                    else:
                        time.sleep(min(next_send - now, 0.0005))
        except OSError:
            return
        finally:
            conn.close()

    def _handle(self, msg_type: int, payload: bytes, recipe, frequency, streaming):
        log.debug("RTDE server: message %d (%d bytes)", msg_type, len(payload))
        if msg_type == REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            return _pack(msg_type, struct.pack(">B", int(version == PROTOCOL_VERSION))), recipe, frequency, streaming
        if msg_type == GET_URCONTROL_VERSION:
            return _pack(msg_type, struct.pack(">IIII", *self.version)), recipe, frequency, streaming
        if msg_type == SETUP_OUTPUTS:
            (frequency,) = struct.unpack(">d", payload[:8])
            names = [n for n in payload[8:].decode("ascii").split(",") if n]  # ur_rtde ends the list with a comma
            types = [VARIABLE_TYPES.get(n, "NOT_FOUND") for n in names]
            ok = "NOT_FOUND" not in types
            if not ok:
                log.warning("RTDE server: unknown output variables %s", [n for n, t in zip(names, types) if t == "NOT_FOUND"])
            reply = _pack(msg_type, struct.pack(">B", 1 if ok else 0) + ",".join(types).encode("ascii"))
            return reply, (names if ok else None), frequency, streaming
        if msg_type == SETUP_INPUTS:
            names = [n for n in payload.decode("ascii").split(",") if n]
            types = [VARIABLE_TYPES.get(n, "NOT_FOUND") for n in names]
            return _pack(msg_type, struct.pack(">B", 2) + ",".join(types).encode("ascii")), recipe, frequency, streaming
        if msg_type == START:
            return _pack(msg_type, struct.pack(">B", int(recipe is not None))), recipe, frequency, recipe is not None
        if msg_type == PAUSE:
            return _pack(msg_type, struct.pack(">B", 1)), recipe, frequency, False
        if msg_type in (TEXT_MESSAGE, DATA_PACKAGE):
            return b"", recipe, frequency, streaming
        log.warning("RTDE server: ignoring message type %d", msg_type)
        return b"", recipe, frequency, streaming

    def _value(self, name: str, t: float, q: np.ndarray):
        if name == "timestamp":
            return (t,)
        if name in ("actual_q", "target_q"):
            return tuple(float(v) for v in q)
        if name == "robot_mode":
            return (ROBOT_MODE_RUNNING,)
        if name == "safety_mode":
            return (SAFETY_MODE_NORMAL,)
        if name == "speed_scaling":
            return (1.0,)
        kind = VARIABLE_TYPES[name]
        fmt = TYPE_FORMATS[kind]
        count = int(fmt[:-1]) if len(fmt) > 1 else 1
        zero = False if kind == "BOOL" else (0.0 if fmt[-1] == "d" else 0)
        return (zero,) * count

    def serve_commands(self, commands) -> None:
        """Run until ``commands`` (a multiprocessing queue) says 'stop'; see :class:`RTDEServerProcess`."""
        while True:
            name, arg = commands.get()
            if name == "stop":
                return
            getattr(self, name)(arg)

    def _data_package(self, recipe: list[str], cycle_host: float | None = None) -> bytes:
        """One package; ``cycle_host`` : the host time of the controller cycle it belongs to (a
        controller stamps each package with its cycle's time, even when this fake, starved of CPU on
        a loaded machine, sends it late); default now."""
        t = self.controller_time() if cycle_host is None else cycle_host - self._t0 + self._clock_offset
        q = np.full(6, math.nan) if self._nan else np.asarray(self.joints(t), dtype=float)
        fmt = ">B" + "".join(TYPE_FORMATS[VARIABLE_TYPES[n]] for n in recipe)
        values = [1]
        for n in recipe:
            values.extend(self._value(n, t, q))
        return _pack(DATA_PACKAGE, struct.pack(fmt, *values))


def demo_joints(t: float) -> np.ndarray:
    """A slow, smooth motion around a UR5e pose over a table (rad): joint 0 sweeps +-0.2 rad at 0.1 Hz."""
    home = np.array([0.0, -1.6, 1.6, -1.57, -1.57, 0.0])
    return home + np.array([0.2, 0.05, -0.05, 0.0, 0.0, 0.1]) * math.sin(2 * math.pi * 0.1 * t)


def _serve_process(host: str, port: int, joints, commands, ready) -> None:
    server = RTDEServer(joints, host=host, port=port).start()
    ready.set()
    try:
        server.serve_commands(commands)
    finally:
        server.stop()


class RTDEServerProcess:
    """:class:`RTDEServer` in a child process, controlled from the parent.

    ur_rtde's client holds the GIL while it reads (its Python binding does not release it), so a
    server in the same process as the client would starve; a child process avoids that.
    ``joints`` must be picklable (a module-level function).
    """

    def __init__(self, host: str | None = None, port: int = RTDE_PORT, joints=demo_joints):
        self.host = host or free_loopback_host(port)
        self.port = port
        ctx = __import__("multiprocessing").get_context("spawn")
        self._commands = ctx.Queue()
        self._ready = ctx.Event()
        self._proc = ctx.Process(target=_serve_process, args=(self.host, port, joints, self._commands, self._ready),
                                 name="rtde-server", daemon=True)

    def start(self, timeout: float = 10.0) -> "RTDEServerProcess":
        self._proc.start()
        if not self._ready.wait(timeout):
            self._proc.kill()
            raise RuntimeError(f"RTDE server on {self.host}:{self.port} did not start within {timeout} s")
        return self

    def drop_clients(self, pause_s: float = 0.5) -> None:
        self._commands.put(("drop_clients", pause_s))

    def set_nan(self, on: bool) -> None:
        self._commands.put(("set_nan", on))

    def jump_clock(self, seconds: float) -> None:
        self._commands.put(("jump_clock", seconds))

    def stop(self) -> None:
        self._commands.put(("stop", None))
        self._proc.join(3.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(1.0)

    def __enter__(self) -> "RTDEServerProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
