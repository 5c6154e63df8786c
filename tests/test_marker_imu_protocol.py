"""The IMU protocol over a real UDP socket on 127.0.0.1, and the CSV file (app.marker.imu)."""
import struct
import time
import zlib

import numpy as np
import pytest

from app.errors import TrialFormatError
from app.marker import imu

Q = np.array([0.5, 0.5, -0.5, 0.5])


def _wait_for(receiver, received, timeout=30.0):   # event-driven; the timeout is a safety net only
    end = time.monotonic() + timeout
    while receiver.counts["received"] < received and time.monotonic() < end:
        time.sleep(0.005)
    return receiver.counts


def test_encode_decode_round_trip_and_size():
    data = imu.encode(41, 12.25, Q, sensor_id=3)
    assert len(data) == imu.PACKET_SIZE == 44
    sensor_id, seq, stamp, q = imu.decode(data)
    assert (sensor_id, seq, stamp) == (3, 41, 12.25)
    np.testing.assert_allclose(q, Q, atol=1e-7)


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d[:-1], "length"),
    (lambda d: b"XXXX" + d[4:], "magic"),
    (lambda d: d[:4] + b"\x02" + d[5:], "version"),
    (lambda d: d[:20] + bytes([d[20] ^ 1]) + d[21:], "CRC"),
])
def test_decode_rejects_malformed(mutate, message):
    with pytest.raises(imu.PacketError, match=message):
        imu.decode(mutate(imu.encode(1, 1.0, Q)))


def test_a_sample_that_arrives_too_long_after_its_stamp_is_stale():
    """Age = (arrival - sensor stamp) above the lowest offset seen: 0.3 s of host time for 0.01 s of
    sensor time is 0.29 s old, past max_age_s = 0.1 (explicit arrival times: no sleeping)."""
    v = imu.PacketValidator(max_age_s=0.1)
    assert v.check(0, 100.00, Q, 5.00) is not None
    assert v.check(1, 100.01, Q, 5.05) is not None          # 0.04 s late: within the age limit
    assert v.check(2, 100.02, Q, 5.32) is None              # 0.3 s late: stale
    assert v.counts["stale"] == 1


def _with_crc(head: bytes) -> bytes:
    return head + struct.pack("<II", zlib.crc32(head), 0)


def test_udp_receiver_rejects_and_counts_over_loopback():
    # max_age_s far above any scheduling delay of a loaded machine: staleness by age is checked
    # with explicit arrival times below, not by sleeping here
    receiver = imu.UdpReceiver(max_age_s=30.0).start()
    assert receiver.address[0] == "127.0.0.1"
    sender = imu.UdpSender(receiver.address)
    try:
        for k in range(5):                                  # seq 0..4, stamps 100.00..100.04: accepted
            sender.send(k, 100.0 + 0.01 * k, Q)
        sender.send(3, 100.05, Q)                           # sequence went back: out of order
        sender.send(4, 100.06, Q)                           # duplicate of the last: out of order
        sender.send(5, 100.03, Q)                           # stamp went back: stale
        sender.send_raw(b"garbage")                         # malformed: length
        sender.send_raw(imu.encode(6, 100.06, Q)[:-4] + b"\x01\x02\x03\x04")  # reserved word set: ignored, accepted
        sender.send_raw(_with_crc(struct.pack("<4sBBHId4f", b"ONIM", 1, 0, 0, 7, 100.07, np.nan, 0, 0, 0)))   # NaN
        sender.send(8, 100.08, [2.0, 0.0, 0.0, 0.0])        # not a unit quaternion: malformed
        sender.send(10, 100.10, Q)                          # accepted; 6..9 missing -> lost
        counts = _wait_for(receiver, 13)
        samples = receiver.drain()
    finally:
        sender.close()
        receiver.stop()
    assert [s.seq for s in samples] == [0, 1, 2, 3, 4, 6, 10]
    assert counts["received"] == 13
    assert counts["accepted"] == 7
    assert counts["out_of_order"] == 2
    assert counts["stale"] == 1
    assert counts["malformed"] == 3
    assert counts["lost"] == 1 + 3                          # 5 (rejected as stale) then 7, 8, 9 before 10
    assert all(abs(np.linalg.norm(s.q_W_S) - 1) < 1e-12 for s in samples)
    # host stamps: the sensor clock plus the smallest offset, so increasing like the sensor's
    assert np.all(np.diff([s.stamp for s in samples]) > 0)


def test_sequence_number_wraps():
    v = imu.PacketValidator()
    assert v.check(2**32 - 1, 1.0, Q, 5.0) is not None
    assert v.check(0, 1.01, Q, 5.01) is not None
    assert v.check(2**32 - 2, 1.02, Q, 5.02) is None
    assert v.counts["out_of_order"] == 1 and v.counts["lost"] == 0


def test_csv_round_trip_and_bad_rows(tmp_path):
    path = tmp_path / "imu.csv"
    q = np.tile(Q, (4, 1))
    imu.write_csv(path, [0, 1, 2, 3], [0.0, 0.01, 0.02, 0.03], q)
    with open(path, "a") as f:
        f.write("4,0.04,1,0,0\n")                           # a missing component: malformed
        f.write("2,0.05,1,0,0,0\n")                         # out of order
    samples, counts = imu.read_csv(path)
    assert [s.seq for s in samples] == [0, 1, 2, 3]
    assert counts["malformed"] == 1 and counts["out_of_order"] == 1
    np.testing.assert_allclose(samples[2].q_W_S, Q)
    assert samples[3].stamp == pytest.approx(0.03)


def test_csv_wrong_header_names_the_file(tmp_path):
    path = tmp_path / "imu.csv"
    path.write_text("t,qw,qx,qy,qz\n")
    with pytest.raises(TrialFormatError, match="expected the header seq,sensor_stamp"):
        imu.read_csv(path)
