"""IMU orientation samples: the UDP protocol, its validator and receiver, and CSV files.

Import as ``from app.marker import imu``.

**The datagram** (one sample per UDP datagram, little-endian, 44 bytes)::

    offset size type     field
    0      4    bytes    magic b"ONIM"
    4      1    uint8    version (1)
    5      1    uint8    flags (0; reserved)
    6      2    uint16   sensor id
    8      4    uint32   sequence number (+1 per sample, wraps at 2^32)
    12     8    float64  sensor timestamp, s (the IMU's own clock)
    20     16   4xfloat32 orientation q_W_S, Hamilton (w, x, y, z): the sensor frame S in the
                          IMU's world W (gravity-aligned; its yaw drifts, no magnetometer)
    36     4    uint32   CRC-32 (zlib.crc32) of bytes 0..35
    40     4    uint32   reserved (0)

**Validation** (:class:`PacketValidator`, shared by the receiver and the file reader), each rejected
packet counted under its reason:

- ``malformed``: wrong length, magic, version, CRC, a non-finite quaternion, or a norm outside
  1 ± ``NORM_TOL`` (a packet within the tolerance is normalised);
- ``out_of_order``: a sequence number not after the last accepted one (serial-number arithmetic
  modulo 2^32, RFC 1982) - duplicates included;
- ``stale``: a sensor timestamp not after the last accepted one, or a packet older than
  ``max_age_s`` when it arrives. The sensor clock is mapped to the host clock by the smallest
  observed (arrival - sensor stamp) offset, the lower envelope that network delay cannot push down;
- ``lost``: samples missing by the sequence numbers (gaps), counted, not rejected.

The receiver listens on loopback by default (``127.0.0.1``; give the interface's address to take
packets from the network), on a background thread, and never blocks its reader.

**The CSV file** (:func:`read_csv`, :func:`write_csv`): a header ``seq,sensor_stamp,qw,qx,qy,qz``,
then one sample a row, validated with the same rules (the row's position stands for the arrival).
"""
from __future__ import annotations

import collections
import csv
import logging
import math
import socket
import struct
import threading
import time
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.errors import TrialFormatError

log = logging.getLogger(__name__)

MAGIC = b"ONIM"
VERSION = 1
_HEAD = struct.Struct("<4sBBHId4f")   # bytes 0..35
_TAIL = struct.Struct("<II")          # crc, reserved
PACKET_SIZE = _HEAD.size + _TAIL.size  # 44
NORM_TOL = 1e-3                        # |q| may differ from 1 by float32 rounding and a sloppy sender
CSV_HEADER = ("seq", "sensor_stamp", "qw", "qx", "qy", "qz")
REASONS = ("malformed", "out_of_order", "stale")


@dataclass(frozen=True)
class ImuSample:
    """One accepted orientation sample.

    seq : sequence number; sensor_stamp : s, the IMU's clock; stamp : s, host clock (the sensor
    stamp mapped by the offset estimate); q_W_S : (4,) unit quaternion (w, x, y, z).
    """

    seq: int
    sensor_stamp: float
    stamp: float
    q_W_S: np.ndarray


class PacketError(ValueError):
    """A datagram that is not a valid packet; ``reason`` is 'malformed'."""

    reason = "malformed"


def encode(seq: int, sensor_stamp: float, q_W_S, sensor_id: int = 0) -> bytes:
    """The datagram of one sample (see the module docstring)."""
    head = _HEAD.pack(MAGIC, VERSION, 0, sensor_id, seq % 2**32, float(sensor_stamp), *map(float, q_W_S))
    return head + _TAIL.pack(zlib.crc32(head), 0)


def decode(data: bytes) -> tuple[int, int, float, np.ndarray]:
    """(sensor_id, seq, sensor_stamp, q (4,)) of a datagram; raises :class:`PacketError`."""
    if len(data) != PACKET_SIZE:
        raise PacketError(f"length {len(data)}, expected {PACKET_SIZE}")
    magic, version, _flags, sensor_id, seq, stamp, *q = _HEAD.unpack_from(data)
    crc, _ = _TAIL.unpack_from(data, _HEAD.size)
    if magic != MAGIC:
        raise PacketError(f"magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise PacketError(f"version {version}, expected {VERSION}")
    if crc != zlib.crc32(data[:_HEAD.size]):
        raise PacketError("CRC mismatch")
    return sensor_id, seq, stamp, np.asarray(q, float)


class PacketValidator:
    """Accepts or rejects samples in arrival order (module docstring); counts in ``counts``."""

    def __init__(self, max_age_s: float = 0.1):
        self.max_age_s = max_age_s
        self.counts: Counter = Counter()
        self.offset: float | None = None    # host - sensor clock, lower envelope
        self._last_seq: int | None = None
        self._last_stamp = -math.inf

    def check(self, seq: int, sensor_stamp: float, q, arrival: float) -> ImuSample | None:
        """The accepted sample, or None (the reason counted)."""
        self.counts["received"] += 1
        q = np.asarray(q, float)
        norm = float(np.linalg.norm(q)) if q.shape == (4,) and np.all(np.isfinite(q)) else math.nan
        if not math.isfinite(sensor_stamp) or not abs(norm - 1.0) <= NORM_TOL:
            return self._reject("malformed")
        if self._last_seq is not None:
            step = (seq - self._last_seq) % 2**32
            if step == 0 or step >= 2**31:
                return self._reject("out_of_order")
        if sensor_stamp <= self._last_stamp:
            return self._reject("stale")
        offset = arrival - sensor_stamp
        if self.offset is None or offset < self.offset:
            self.offset = offset
        if offset - self.offset > self.max_age_s:
            return self._reject("stale")
        if self._last_seq is not None:
            self.counts["lost"] += (seq - self._last_seq) % 2**32 - 1
        self._last_seq, self._last_stamp = seq, sensor_stamp
        self.counts["accepted"] += 1
        return ImuSample(int(seq), float(sensor_stamp), float(sensor_stamp + self.offset), q / norm)

    def _reject(self, reason: str) -> None:
        self.counts[reason] += 1
        return None


class UdpReceiver:
    """IMU packets on a UDP socket, validated on a background thread.

    host : interface to listen on (loopback by default); port : 0 picks a free one (see ``port``).
    Accepted samples wait in a bounded queue (oldest dropped and counted) for :meth:`drain`.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, max_age_s: float = 0.1, queue: int = 4096,
                 sensor_id: int | None = None):
        self.validator = PacketValidator(max_age_s)
        self.sensor_id = sensor_id
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, port))
        self._sock.settimeout(0.05)
        self.address = self._sock.getsockname()
        self._queue: collections.deque = collections.deque(maxlen=queue)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.dropped = 0

    @property
    def port(self) -> int:
        return self.address[1]

    @property
    def counts(self) -> dict:
        with self._lock:
            return {**{k: 0 for k in ("received", "accepted", "lost", *REASONS)}, **self.validator.counts,
                    "dropped": self.dropped}

    def start(self) -> "UdpReceiver":
        self._thread = threading.Thread(target=self._run, name="imu-udp", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(256)
            except socket.timeout:
                continue
            except OSError:
                break
            self.handle(data, time.monotonic())

    def handle(self, data: bytes, arrival: float) -> ImuSample | None:
        """Validate one datagram (the thread's body; callable directly)."""
        with self._lock:
            try:
                sensor_id, seq, stamp, q = decode(data)
            except PacketError as exc:
                self.validator.counts["received"] += 1
                self.validator.counts["malformed"] += 1
                log.debug("IMU packet rejected: %s", exc)
                return None
            if self.sensor_id is not None and sensor_id != self.sensor_id:
                self.validator.counts["received"] += 1
                self.validator.counts["malformed"] += 1
                return None
            sample = self.validator.check(seq, stamp, q, arrival)
            if sample is not None:
                if len(self._queue) == self._queue.maxlen:
                    self.dropped += 1
                self._queue.append(sample)
            return sample

    def drain(self) -> list[ImuSample]:
        """The accepted samples since the last call, oldest first."""
        with self._lock:
            items = list(self._queue)
            self._queue.clear()
            return items

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        self._sock.close()


class UdpSender:
    """Sends samples as datagrams (the marker box's side; used by the simulator and the tests)."""

    def __init__(self, address: tuple[str, int], sensor_id: int = 0):
        self.address = address
        self.sensor_id = sensor_id
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(self, seq: int, sensor_stamp: float, q_W_S) -> None:
        self._sock.sendto(encode(seq, sensor_stamp, q_W_S, self.sensor_id), self.address)

    def send_raw(self, data: bytes) -> None:
        self._sock.sendto(data, self.address)

    def close(self) -> None:
        self._sock.close()


def write_csv(path: str | Path, seq, sensor_stamp, q_W_S) -> None:
    """Write samples: seq (N,), sensor_stamp (N,) s, q_W_S (N, 4) (w, x, y, z)."""
    q = np.asarray(q_W_S, float)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_HEADER)
        for s, t, qq in zip(seq, sensor_stamp, q):
            w.writerow([int(s), f"{t:.6f}", *(f"{v:.9f}" for v in qq)])


def read_csv(path: str | Path, max_age_s: float = math.inf) -> tuple[list[ImuSample], dict]:
    """Samples of a CSV file (header ``seq,sensor_stamp,qw,qx,qy,qz``), validated; and the counts.

    Stamps stay on the sensor clock (offset 0). A row that does not parse counts as malformed; a
    wrong header raises :class:`~app.errors.TrialFormatError`.
    """
    path = Path(path)
    validator = PacketValidator(max_age_s)
    samples = []
    with open(path, newline="") as f:
        rows = csv.reader(f)
        header = next(rows, None)
        if header is None or tuple(h.strip() for h in header) != CSV_HEADER:
            raise TrialFormatError(path, f"expected the header {','.join(CSV_HEADER)}, got {header}", "line 1")
        for row in rows:
            try:
                seq, stamp, *q = (float(v) for v in row)
                if len(q) != 4 or seq != int(seq):
                    raise ValueError
            except ValueError:
                validator.counts["received"] += 1
                validator.counts["malformed"] += 1
                continue
            sample = validator.check(int(seq) % 2**32, stamp, q, arrival=stamp)
            if sample is not None:
                samples.append(ImuSample(sample.seq, sample.sensor_stamp, sample.sensor_stamp, sample.q_W_S))
    return samples, {**{k: 0 for k in ("received", "accepted", "lost", *REASONS)}, **validator.counts}
